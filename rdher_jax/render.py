"""Offscreen video of a policy: MuJoCo's own renderer (``mujoco.Renderer``) on the task's
``MjModel``, with gymnasium-robotics' Fetch camera and goal marker.

Each step's physics state is copied to the host and loaded into a plain ``MjData``: on the
``mujoco`` backend the whole float64 ``mjSTATE_INTEGRATION`` vector the state carries, on the
``mjx`` backend qpos, qvel, act and the mocap pose taken from ``mjx.Data``. The goal is drawn
as gymnasium-robotics' ``MujocoFetchEnv._render_callback`` does, by moving the ``target0`` site
to it.

MuJoCo binds its OpenGL backend (``MUJOCO_GL``: egl, osmesa, glfw) when ``mujoco`` is first
imported, and an unusable one surfaces only when a context is made (a failed EGL attempt can
also leave PyOpenGL bound to EGL for the rest of the process). So :func:`select_gl` tries a
backend in a child process, and sets ``MUJOCO_GL`` here only before ``mujoco`` is imported.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import os
import subprocess
import sys
from collections.abc import Iterable
from pathlib import Path

import numpy as np

VIDEO_SUFFIXES = (".gif", ".mp4")
AUTO_GL = ("egl", "osmesa")  # headless backends, in the order tried when MUJOCO_GL is unset
GL_PACKAGES = ("Debian: libegl1 libegl-mesa0 libgl1-mesa-dri for MUJOCO_GL=egl, "
               "libosmesa6 for MUJOCO_GL=osmesa")
DEFAULT_SIZE = 480  # gymnasium-robotics' frame size
BAR = 4  # height in pixels of the step bar drawn along the bottom edge

_PROBE = """
import os, sys
try:
    import mujoco
    m = mujoco.MjModel.from_xml_string("<mujoco/>")
    r = mujoco.Renderer(m, 16, 16)
    r.render()
    r.close()
except BaseException as e:
    print(type(e).__name__ + ": " + " ".join(str(e).split()))
    sys.stdout.flush()
    os._exit(1)
sys.stdout.flush()
os._exit(0)  # skips the GL libraries' exit handlers, which may print on some drivers
"""


class RenderError(RuntimeError):
    """The video cannot be rendered or written (one-line message)."""

    def __init__(self, msg: str) -> None:
        super().__init__(" ".join(str(msg).split()))


def check_video_path(path: str | Path, width: int, height: int) -> Path:
    """Validate an output path before anything is built: suffix, directory, mp4 writer."""
    path = Path(path)
    suffix = path.suffix.lower()
    if path.is_dir():
        raise RenderError(f"video {path} is a directory")
    if suffix not in VIDEO_SUFFIXES:
        raise RenderError(f"video must end in {' or '.join(VIDEO_SUFFIXES)}, got {str(path)!r}")
    parent = path.parent
    if not parent.is_dir():
        raise RenderError(f"video directory {parent} does not exist")
    if not os.access(parent, os.W_OK):
        raise RenderError(f"video directory {parent} is not writable")
    if suffix == ".mp4":
        import importlib.util

        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise RenderError("writing .mp4 needs imageio-ffmpeg (pip install "
                              "'rdher-jax[video]'); or write a .gif")
        if width % 2 or height % 2:
            raise RenderError(f"an .mp4 needs even width and height, got {width}x{height}")
    return path


def probe_gl(backend: str, timeout: float = 120.0) -> str | None:
    """None if MuJoCo can render offscreen with ``MUJOCO_GL=backend`` in a fresh process,
    else the one-line reason it cannot."""
    env = {**os.environ, "MUJOCO_GL": backend}
    try:
        p = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                           text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return f"no GL context within {timeout:.0f} s"
    if p.returncode == 0:
        return None
    lines = [ln for ln in p.stdout.splitlines() if ln.strip()]
    return lines[-1] if lines else f"exit status {p.returncode}"


def select_gl() -> str:
    """Choose MuJoCo's OpenGL backend for offscreen rendering and return its name.

    ``MUJOCO_GL`` if set (checked in a child process), else the first of egl, osmesa that
    works, which is then written to ``MUJOCO_GL`` for this process. If ``mujoco`` is already
    imported its choice is fixed and is kept (an unusable one fails in :class:`FrameRenderer`).
    """
    chosen = os.environ.get("MUJOCO_GL", "").strip()
    if "mujoco" in sys.modules:
        return chosen or "unset"
    if chosen:
        why = probe_gl(chosen)
        if why is not None:
            raise RenderError(f"MuJoCo cannot render offscreen with MUJOCO_GL={chosen}: {why} "
                              f"({GL_PACKAGES})")
        return chosen
    reasons = []
    for backend in AUTO_GL:
        why = probe_gl(backend)
        if why is None:
            os.environ["MUJOCO_GL"] = backend
            return backend
        reasons.append(f"{backend}: {why}")
    raise RenderError(f"MuJoCo cannot render offscreen ({'; '.join(reasons)}); install "
                      f"{GL_PACKAGES}, or set MUJOCO_GL")


def fetch_camera():
    """A free ``MjvCamera`` set as gymnasium-robotics' ``MujocoFetchEnv`` sets its renderer's."""
    import mujoco

    from rdher_jax.envs.notices import quiet_gymnasium_robotics

    quiet_gymnasium_robotics()
    from gymnasium_robotics.envs.fetch.fetch_env import DEFAULT_CAMERA_CONFIG

    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.fixedcamid = -1
    for key, value in DEFAULT_CAMERA_CONFIG.items():
        if isinstance(value, np.ndarray):
            getattr(cam, key)[:] = value
        else:
            setattr(cam, key, value)
    return cam


class FrameRenderer:
    """Renders one env's host-side physics snapshots (see :func:`snapshot`) of a ``FetchEnv``.

    Raises RenderError when MuJoCo cannot make an offscreen GL context. Use as a context
    manager, or call :meth:`close`: freeing the context before exit keeps EGL quiet.
    """

    def __init__(self, env, width: int = DEFAULT_SIZE, height: int = DEFAULT_SIZE):
        import mujoco

        self._mujoco = mujoco
        self.env = env
        # A copy: the goal marker moves a site of the model, and the backend's model is shared.
        m = copy.deepcopy(env.setup.model)
        m.vis.global_.offwidth = max(int(m.vis.global_.offwidth), width)
        m.vis.global_.offheight = max(int(m.vis.global_.offheight), height)
        self.model = m
        self.data = mujoco.MjData(m)
        mujoco.mj_resetData(m, self.data)
        mujoco.mj_forward(m, self.data)
        self.target = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "target0")
        # gymnasium-robotics places target0 at goal - (site_xpos - site_pos); its body (floor0)
        # is static, so the offset is computed once.
        self._offset = (self.data.site_xpos[self.target] - m.site_pos[self.target]).copy() \
            if self.target >= 0 else None
        self.camera = fetch_camera()
        gl = os.environ.get("MUJOCO_GL")
        try:
            self.renderer = mujoco.Renderer(m, height=height, width=width)
        except Exception as e:
            hint = "" if gl else "; set MUJOCO_GL=egl or osmesa before mujoco is imported"
            raise RenderError(f"MuJoCo cannot render offscreen with MUJOCO_GL={gl or 'unset'}: "
                              f"{type(e).__name__}: {e} ({GL_PACKAGES}{hint})") from None
        self.width, self.height = width, height

    def load(self, snap: dict) -> None:
        """Set the MjData from one env's snapshot and recompute its kinematics."""
        mj, m, d = self._mujoco, self.model, self.data
        if "bits" in snap:
            be = self.env.backend
            full = np.ascontiguousarray(snap["bits"]).view(np.float64)
            mj.mj_setState(m, d, full[: be.nstate].copy(), mj.mjtState.mjSTATE_INTEGRATION)
        else:
            for name in ("qpos", "qvel", "act", "mocap_pos", "mocap_quat"):
                getattr(d, name)[:] = np.asarray(snap[name], np.float64).reshape(
                    getattr(d, name).shape)
        mj.mj_forward(m, d)

    def frame(self, snap: dict, goal: np.ndarray) -> np.ndarray:
        """(height, width, 3) uint8 image of one snapshot with the goal marker at ``goal``."""
        self.load(snap)
        if self._offset is not None:
            self.model.site_pos[self.target] = np.asarray(goal, np.float64) - self._offset
            self._mujoco.mj_kinematics(self.model, self.data)
        self.renderer.update_scene(self.data, camera=self.camera)
        return self.renderer.render().copy()

    def close(self) -> None:
        r = getattr(self, "renderer", None)
        if r is not None:
            r.close()
            self.renderer = None

    def __enter__(self) -> FrameRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def snapshot(env, data) -> dict:
    """The part of a backend's physics state a frame needs, as arrays (jittable)."""
    if env.backend.name == "mujoco":
        return {"bits": data.bits}
    return {k: getattr(data, k) for k in ("qpos", "qvel", "act", "mocap_pos", "mocap_quat")}


def make_rollout(env, act, episodes: int):
    """A jittable ``rollout(key, policy)`` of ``episodes`` deterministic episodes, returning
    per-step snapshots (episodes, T + 1, ...), goals (episodes, T + 1, 3) and success
    (episodes, T + 1). ``act(policy, obs, goal)`` is the deterministic policy."""
    import jax
    import jax.numpy as jnp

    from .envs.rollout import rollout as env_rollout

    def record(state):
        return (snapshot(env, state.data), state.info["goal"], state.info["is_success"])

    def rollout(key, policy):
        first, _, rest = env_rollout(
            env, lambda _, s: act(policy, s.obs["observation"], s.obs["desired_goal"]),
            jax.random.split(key, episodes), record=lambda s, a, nxt: record(nxt))
        # (T, n, ...) after the first (n, ...) -> (n, T + 1, ...)
        return jax.tree.map(
            lambda x, y: jnp.swapaxes(jnp.concatenate([x[None], y], 0), 0, 1),
            record(first), rest)

    return rollout


def draw_step_bar(img: np.ndarray, t: int, length: int, success: bool) -> np.ndarray:
    """Mark step ``t`` of an episode of ``length`` steps as a bar along the bottom edge,
    green where the goal is reached. On frames at least ``length + 1`` pixels wide the bar
    grows by a pixel or more per step, so consecutive frames always differ: Pillow merges
    identical consecutive GIF frames, which would change the frame count."""
    out = img.copy()
    fill = max(1, img.shape[1] * (t + 1) // (length + 1))
    out[-BAR:, :] = (40, 40, 40)
    out[-BAR:, :fill] = (40, 200, 60) if success else (230, 230, 230)
    return out


def render_frames(renderer: FrameRenderer, snaps, goals, success):
    """Frames of every episode and step of a rollout's outputs, one at a time."""
    import jax

    snaps = jax.tree.map(np.asarray, snaps)
    goals, success = np.asarray(goals), np.asarray(success)
    n, steps = goals.shape[:2]
    for e in range(n):
        for t in range(steps):
            snap = {k: v[e, t] for k, v in snaps.items()}
            try:
                img = renderer.frame(snap, goals[e, t])
            except Exception as err:
                raise RenderError(f"rendering failed: {type(err).__name__}: {err}") from None
            yield draw_step_bar(img, t, steps - 1, bool(success[e, t] > 0.5))


@contextlib.contextmanager
def _env_var(name: str, value: str):
    old = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def write_video(path: str | Path, frames: Iterable[np.ndarray], fps: float) -> int:
    """Write ``frames`` to a .gif (Pillow) or .mp4 (imageio-ffmpeg, H.264) and return how many
    were written. The file appears only when complete: it is written under a temporary name
    and renamed into place, and removed if anything fails."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in VIDEO_SUFFIXES:
        raise RenderError(f"video must end in {' or '.join(VIDEO_SUFFIXES)}, got {str(path)!r}")
    tmp = path.with_name(f".{path.stem}.partial-{os.getpid()}{suffix}")
    count = 0

    def counted():
        nonlocal count
        for f in frames:
            count += 1
            yield f

    try:
        it = counted()
        first = next(it, None)
        if first is None:
            raise RenderError("no frames to write")
        if suffix == ".gif":
            from PIL import Image

            Image.fromarray(first).save(
                tmp, format="GIF", save_all=True, loop=0, duration=round(1000.0 / fps),
                append_images=(Image.fromarray(f) for f in it))
        else:
            import imageio_ffmpeg

            h, w = first.shape[:2]
            writer = imageio_ffmpeg.write_frames(str(tmp), (w, h), fps=fps, codec="libx264",
                                                 macro_block_size=1, ffmpeg_log_level="error")
            # imageio-ffmpeg starts ffmpeg with a preexec_fn unless told not to, and a fork
            # hook in a multithreaded (JAX) process warns and can deadlock. Without it ffmpeg
            # shares our process group, so Ctrl-C stops it too.
            with _env_var("IMAGEIO_FFMPEG_NO_PREVENT_SIGINT", "1"):
                writer.send(None)
            try:
                for f in itertools.chain([first], it):
                    writer.send(np.ascontiguousarray(f))
            finally:
                writer.close()
        os.replace(tmp, path)
    except RenderError:
        raise
    except Exception as e:
        raise RenderError(f"cannot write {path}: {type(e).__name__}: {e}") from None
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return count
