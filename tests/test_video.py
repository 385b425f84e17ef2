"""Videos from ``python -m rdher_jax.evaluate <run> video=...``: frames rendered by MuJoCo
offscreen as gymnasium-robotics renders the same state, the file written whole or not at all,
and every unusable request a one-line error with exit status 2."""

import functools
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rdher_jax.envs.registry import TASKS

from rdher_jax import render

TASK = "FetchReach"
EPISODE_LENGTH = TASKS[TASK].episode_length
TINY_RUN = [f"env={TASK}", "epochs=1", "n_cycles=1", "n_batches=2", "batch_size=32",
            "buffer_size=2000", "n_test_rollouts=1", "hidden=16", "progress=false"]


@functools.cache
def working_gl() -> tuple[str | None, str]:
    """The first headless GL backend MuJoCo renders with here, or None and why not."""
    reasons = []
    for backend in render.AUTO_GL:
        why = render.probe_gl(backend)
        if why is None:
            return backend, ""
        reasons.append(f"{backend}: {why}")
    return None, "no offscreen GL backend here (" + "; ".join(reasons) + ")"


def needs_gl() -> str:
    gl, why = working_gl()
    if gl is None:
        pytest.skip(why)
    return gl


def _env(**kw) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    return {**env, "PYTHONUNBUFFERED": "1", **kw}


def _evaluate(args, **env) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "rdher_jax.evaluate", *map(str, args)],
                            env=_env(**env), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


@pytest.fixture(scope="module")
def run(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("video") / "run"
    p = subprocess.run([sys.executable, "-m", "rdher_jax.train", *TINY_RUN, f"run_dir={run_dir}"],
                       env=_env(), capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    return run_dir


@pytest.mark.slow
def test_gif_has_one_frame_per_state(run, tmp_path):
    """MUJOCO_GL unset: the first working backend is chosen; K episodes give K x (T + 1)
    frames (reset state plus every step), each showing the scene."""
    gl = needs_gl()
    out = tmp_path / "policy.gif"
    p = _evaluate([run, "episodes=1", f"video={out}", "video_episodes=2", "width=96",
                   "height=64"])
    stdout, stderr = p.communicate(timeout=300)
    assert p.returncode == 0, stderr
    assert f"wrote {out}: 2 episodes, {2 * (EPISODE_LENGTH + 1)} frames" in stdout, stdout
    assert f"MUJOCO_GL={gl}" in stdout
    assert sorted(q.name for q in tmp_path.iterdir()) == ["policy.gif"]  # no partial file left
    from PIL import Image

    with Image.open(out) as im:
        assert im.n_frames == 2 * (EPISODE_LENGTH + 1) and im.size == (96, 64)
        scenes = []
        for i in (0, EPISODE_LENGTH, im.n_frames - 1):
            im.seek(i)
            scenes.append(np.asarray(im.convert("RGB"))[: -render.BAR].astype(float))
    assert all(s.std() > 10 for s in scenes)  # a picture, not a blank frame


def test_frames_match_gymnasium_render():
    """A frame of our state equals gymnasium-robotics' own ``render()`` of the same state:
    same model, camera and goal marker (FetchPush: reset and three random steps)."""
    gl = needs_gl()
    script = """
import jax, numpy as np, gymnasium as gym, gymnasium_robotics
import rdher_jax
from rdher_jax import render
gym.register_envs(gymnasium_robotics)
genv = gym.make("FetchPush-v4", render_mode="rgb_array", width=120, height=90)
genv.reset(seed=1)
u = genv.unwrapped
env = rdher_jax.make_env("FetchPush", backend="mujoco", auto_reset=False)
state = env.reset_to(u.data.qpos.copy(), u.data.qvel.copy(), u.goal.copy())
rng, worst = np.random.default_rng(0), 0.0
with render.FrameRenderer(env, 120, 90) as r:
    for t in range(4):
        ref = genv.render()
        snap = jax.tree.map(np.asarray, render.snapshot(env, state.data))
        img = r.frame(snap, np.asarray(state.info["goal"]))
        assert img.shape == ref.shape, (img.shape, ref.shape)
        worst = max(worst, float((np.abs(img.astype(int) - ref.astype(int)) > 8).mean()))
        a = rng.uniform(-1, 1, 4).astype(np.float32)
        genv.step(a)
        state = env.step(state, jax.numpy.asarray(a))
print("worst", worst)
"""
    p = subprocess.run([sys.executable, "-c", script], env=_env(MUJOCO_GL=gl),
                       capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    worst = float(p.stdout.split("worst")[-1])
    assert worst < 1e-3, p.stdout  # measured: 0 (pixel-identical)


def test_unusable_requests_are_one_line_errors(run, tmp_path, one_line_error):
    """A bad suffix and an unusable GL backend, from the command line: exit 2, one stderr
    line, no file written."""
    cases = {
        "suffix": ([f"video={tmp_path / 'out.avi'}"], {}, "video must end in .gif or .mp4"),
        "gl": ([f"video={tmp_path / 'out.gif'}"], {"MUJOCO_GL": "nonexistent"},
               "MuJoCo cannot render offscreen with MUJOCO_GL=nonexistent"),
    }
    procs = {name: _evaluate([run, "episodes=1", *args], **env)
             for name, (args, env, _) in cases.items()}
    for name, (_, _, fragment) in cases.items():
        assert fragment in one_line_error(procs[name]), name
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("args, fragment", [
    (["video={tmp}/out"], "video must end in .gif or .mp4"),
    (["video={tmp}/missing/out.gif"], "video directory {tmp}/missing does not exist"),
    (["video={tmp}"], "is a directory"),
    (["video_episodes=2"], "video_episodes needs video=<file>"),
    (["video={tmp}/out.gif", "width=32"], "width must be 64 to 4096 pixels"),
    (["video={tmp}/out.gif", "video_episodes=0"], "video_episodes must be a positive integer"),
])
def test_bad_video_options_fail_before_anything_runs(run, tmp_path, capsys, args, fragment):
    from rdher_jax import evaluate

    args = [a.format(tmp=tmp_path) for a in args]
    with pytest.raises(SystemExit) as e:
        evaluate.main([str(run), "episodes=1", *args])
    assert e.value.code == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("error: ")
    assert fragment.format(tmp=tmp_path) in err[0]
    assert list(tmp_path.iterdir()) == []


def test_write_video_leaves_no_partial_file(tmp_path):
    """A failure while frames are produced leaves neither the file nor its temporary."""
    def frames():
        yield np.zeros((8, 8, 3), np.uint8)
        raise render.RenderError("rendering failed: boom")

    for name in ("a.gif", "a.mp4"):
        if name.endswith(".mp4"):
            pytest.importorskip("imageio_ffmpeg")
        with pytest.raises(render.RenderError, match="boom"):
            render.write_video(tmp_path / name, frames(), fps=25)
        assert list(tmp_path.iterdir()) == []


def test_write_video_frame_counts(tmp_path):
    """Every frame is kept, in .gif (distinct frames, as the step bar makes them) and .mp4."""
    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 255, (32, 48, 3), dtype=np.uint8) for _ in range(7)]
    assert render.write_video(tmp_path / "a.gif", iter(frames), fps=25) == 7
    from PIL import Image

    with Image.open(tmp_path / "a.gif") as im:
        assert im.n_frames == 7 and im.size == (48, 32)
    imageio_ffmpeg = pytest.importorskip("imageio_ffmpeg")
    assert render.write_video(tmp_path / "a.mp4", iter(frames), fps=25) == 7
    n, secs = imageio_ffmpeg.count_frames_and_secs(str(tmp_path / "a.mp4"))
    assert n == 7 and abs(secs - 7 / 25) < 0.05
    assert sorted(q.name for q in tmp_path.iterdir()) == ["a.gif", "a.mp4"]


def test_step_bar_makes_consecutive_frames_distinct():
    img = np.full((10, 64, 3), 7, np.uint8)  # the CLI's smallest width
    bars = [render.draw_step_bar(img, t, 50, success=t > 30) for t in range(51)]
    assert all(not np.array_equal(a, b) for a, b in zip(bars, bars[1:], strict=False))
    assert all(np.array_equal(b[: -render.BAR], img[: -render.BAR]) for b in bars)
