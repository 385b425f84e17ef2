"""Our reset sampling against gymnasium-robotics' ``Fetch*-v4``, as distributions.

``tests/test_envs.py`` checks that both stay inside the documented ranges; a range bug that stays
inside them (half the range, a shifted centre, the PickAndPlace lift drawn too rarely) passes
that. Here each coordinate of the object's start position and of the goal is compared between
our ``reset`` (vmapped over keys, ``mujoco`` backend) and gymnasium-robotics' ``reset`` (over
seeds) with a two-sample Kolmogorov-Smirnov test; coordinates that never vary (the table height)
must be equal. Seeds are fixed, so the outcome is deterministic. The test also shows that the
threshold rejects both kinds of bug on the same samples.
"""

from __future__ import annotations

import functools
import warnings

import jax
import numpy as np
import pytest
from rdher_jax.envs import GYMNASIUM_TASK_NAMES
from rdher_jax.envs.registry import task_spec

from rdher_jax import make_env

warnings.filterwarnings("ignore", category=UserWarning)
gym = pytest.importorskip("gymnasium")
gymnasium_robotics = pytest.importorskip("gymnasium_robotics")
stats = pytest.importorskip("scipy.stats")
gym.register_envs(gymnasium_robotics)

# A coordinate fails when the KS test rejects at this level. At 1,000 samples a side it rejects
# a shift by 15% of a uniform range (KS distance 0.15) with p ~ 1e-10 and a range halved
# (distance 0.25) with p ~ 1e-27; a correct sampler gets past it with probability 0.999.
ALPHA = 1e-3


@functools.cache
def samples(task: str, n: int) -> dict[str, dict[str, np.ndarray]]:
    """``{"ours": {...}, "theirs": {...}}``, each with ``goal`` (n, 3) and, for object tasks,
    ``obj`` (n, 3) and ``obj_dist`` (n,), the object's xy distance from the gripper's start."""
    env = make_env(task, backend="mujoco")
    st = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.PRNGKey(2024), n))
    ours = {"goal": np.asarray(st.obs["desired_goal"], np.float64)}
    genv = gym.make(task_spec(task).gymnasium_id).unwrapped
    obs = [genv.reset(seed=s)[0] for s in range(n)]
    theirs = {"goal": np.stack([o["desired_goal"] for o in obs]).astype(np.float32)
              .astype(np.float64)}
    if env.spec.has_object:
        ours["obj"] = np.asarray(st.obs["observation"][:, 3:6], np.float64)
        theirs["obj"] = np.stack([o["observation"][3:6] for o in obs])
    grip0 = np.asarray(genv.initial_gripper_xpos)
    for s in (ours, theirs):
        if "obj" in s:
            s["obj_dist"] = np.linalg.norm(s["obj"][:, :2] - grip0[:2], axis=-1)
    genv.close()
    return {"ours": ours, "theirs": theirs}


def columns(s: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    out = {f"goal {a}": s["goal"][:, k] for k, a in enumerate("xyz")}
    if "obj" in s:
        out.update({f"object {a}": s["obj"][:, k] for k, a in enumerate("xyz")})
        out["object xy distance from the gripper"] = s["obj_dist"]
    return out


def mismatches(ours: dict[str, np.ndarray], theirs: dict[str, np.ndarray]) -> dict[str, str]:
    """Coordinates whose distributions differ: KS p < ALPHA, or a constant that is not equal."""
    bad = {}
    for name, ref in columns(theirs).items():
        x = columns(ours)[name]
        if np.ptp(ref) == 0:  # a constant (a table height): ours must be the same number
            if not np.allclose(x, ref[0], rtol=0, atol=1e-6):
                bad[name] = f"constant {ref[0]:.6f}, ours in [{x.min():.6f}, {x.max():.6f}]"
            continue
        res = stats.ks_2samp(x, ref)
        if res.pvalue < ALPHA:
            bad[name] = f"KS D={res.statistic:.3f} p={res.pvalue:.1e}"
    return bad


def check(task: str, n: int) -> None:
    s = samples(task, n)
    assert mismatches(s["ours"], s["theirs"]) == {}


@pytest.mark.parametrize("task", GYMNASIUM_TASK_NAMES)
def test_reset_distribution_matches_gymnasium(task):
    check(task, 1000)


@pytest.mark.slow
@pytest.mark.parametrize("task", GYMNASIUM_TASK_NAMES)
def test_reset_distribution_matches_gymnasium_5000(task):
    check(task, 5000)


def _bugged(s: dict[str, np.ndarray], name: str, bug: str) -> dict[str, np.ndarray]:
    """``s`` with coordinate ``name`` ("goal x", "object y", ...) broken: its spread halved about
    its lowest value (half the range; for PickAndPlace's goal z, half the lift) or shifted by
    15% of its spread."""
    field, axis = name.split()
    key, k = {"goal": "goal", "object": "obj"}[field], "xyz".index(axis)
    out = {f: v.copy() for f, v in s.items()}
    col = out[key][:, k]
    if bug == "half range":
        out[key][:, k] = col.min() + (col - col.min()) / 2
    else:
        out[key][:, k] = col + 0.15 * np.ptp(col)
    return out


@pytest.mark.parametrize("task", GYMNASIUM_TASK_NAMES)
@pytest.mark.parametrize("bug", ["half range", "shifted centre"])
def test_the_threshold_rejects_range_bugs(task, bug):
    s = samples(task, 1000)
    coords = [f"{f} {a}" for f in ("goal", "object") for a in "xyz"]
    varying = [c for c, v in columns(s["theirs"]).items() if c in coords and np.ptp(v) > 0]
    assert {"goal x", "goal y"} <= set(varying)
    for name in varying:
        bad = mismatches(_bugged(s["ours"], name, bug), s["theirs"])
        assert name in bad, (name, bug)
