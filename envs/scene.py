"""Fetch scenes read from the installed gymnasium_robotics package (never copied).

``load_model(task, variant)`` returns a ``mujoco.MjModel``:

- ``variant="original"``: the unedited gymnasium-robotics MJCF, exactly as ``Fetch*-v4`` loads it.
- ``variant="mjx"``: the same scene edited with ``mujoco.MjSpec`` so that ``mjx.put_model``
  accepts it (see ``_edit_for_mjx`` for every edit and why).
"""

from __future__ import annotations

import os

import mujoco

TASK_XML = {
    "FetchReach": "reach.xml",
    "FetchPush": "push.xml",
    "FetchSlide": "slide.xml",
    "FetchPickAndPlace": "pick_and_place.xml",
}

VARIANTS = ("original", "mjx")


def asset_path(task: str) -> str:
    """Path of the task's MJCF inside the installed gymnasium_robotics package."""
    import gymnasium_robotics

    root = os.path.dirname(gymnasium_robotics.__file__)
    return os.path.join(root, "envs", "assets", "fetch", TASK_XML[task])


def load_spec(task: str) -> mujoco.MjSpec:
    return mujoco.MjSpec.from_file(asset_path(task))


def load_model(task: str, variant: str = "original") -> mujoco.MjModel:
    """Compile the task's scene; ``variant`` is ``"original"`` or ``"mjx"``."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown scene variant {variant!r}; valid: {', '.join(VARIANTS)}")
    if variant == "original":
        return mujoco.MjModel.from_xml_path(asset_path(task))
    spec = load_spec(task)
    _edit_for_mjx(spec, task)
    return spec.compile()


def _edit_for_mjx(spec: mujoco.MjSpec, task: str) -> None:
    """Edits that make the scene loadable by ``mjx.put_model``."""
    for geom in spec.geoms:
        geom.margin = 0.0
