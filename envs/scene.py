"""Fetch scenes read from the installed gymnasium_robotics package (never copied).

``load_model(task, variant)`` returns a ``mujoco.MjModel``:

- ``variant="original"``: the unedited gymnasium-robotics MJCF, exactly as ``Fetch*-v4`` loads it.
- ``variant="mjx"``: the same scene edited with ``mujoco.MjSpec`` so that ``mjx.put_model``
  accepts it (see ``_edit_for_mjx`` for every edit and why).
- ``variant="warp"``: the ``mjx`` scene with the further edits MJX's Warp implementation
  (``mjx.put_model(m, impl="warp")``) needs (see ``_edit_for_warp``).

The edits are also exposed one by one in ``EDITS`` so that their effect on the dynamics can be
measured separately (``experiments/scene_edits.py``).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import mujoco
import numpy as np

from .notices import quiet_gymnasium_robotics, quiet_mjx
from .registry import task_spec

VARIANTS = ("original", "mjx", "warp")

# Robot geoms that keep colliding. In native rollouts (8 scripted + 8 random episodes per task,
# experiments/scene_edits.py) the finger boxes and the gripper link touch the table, floor and
# object; base_link rests on the floor (kept through ``_base_pads``); the upper arm touches the
# head in a few scripted Reach and PickAndPlace episodes that reach high (dropped: 0.4-1.6 mm of
# gripper motion in 1 of 8 episodes, against two mesh-mesh pairs per substep in MJX).
COLLIDING_ROBOT_GEOMS = (
    "robot0:gripper_link",
    "robot0:r_gripper_finger_link",
    "robot0:l_gripper_finger_link",
)
# Bodies whose geoms keep colliding: the world (floor plane), the table and the object.
COLLIDING_BODIES = ("world", "table0", "object0")

# The Slide puck becomes an N-sided prism. MJX keeps at most 20 vertices per hull face and
# subsamples faces of 20 or more (every second vertex), so N <= 19 keeps the prism intact; 16 to
# 128 sides were measured to deviate alike from the cylinder (see the experiment).
PUCK_SIDES = 16
# Spheres standing in for base_link's floor contacts (see ``_base_pads``).
BASE_PAD = "robot0:base_pad"
BASE_PAD_RADIUS = 0.01
PUCK_MESH = "object0:prism"


def asset_path(task: str) -> str:
    """Path of the task's MJCF inside the installed gymnasium_robotics package."""
    xml = task_spec(task).xml
    quiet_gymnasium_robotics()
    import gymnasium_robotics

    root = os.path.dirname(gymnasium_robotics.__file__)
    return os.path.join(root, "envs", "assets", "fetch", xml)


def load_spec(task: str) -> mujoco.MjSpec:
    """The task's scene as an editable ``mujoco.MjSpec``."""
    return mujoco.MjSpec.from_file(asset_path(task))


def load_model(task: str, variant: str = "original") -> mujoco.MjModel:
    """Compile the task's scene; ``variant`` is ``"original"``, ``"mjx"`` or ``"warp"``."""
    if variant not in VARIANTS:
        raise ValueError(f"unknown scene variant {variant!r}; valid: {', '.join(VARIANTS)}")
    if variant == "original":
        return mujoco.MjModel.from_xml_path(asset_path(task))
    spec = load_spec(task)
    _edit_for_mjx(spec, task)
    if variant == "warp":
        _edit_for_warp(spec, task)
    return spec.compile()


def load_edited(task: str, edits: tuple[str, ...]) -> mujoco.MjModel:
    """Compile the task's scene with only the named ``EDITS`` applied, in ``EDITS`` order."""
    unknown = set(edits) - set(EDITS)
    if unknown:
        raise ValueError(f"unknown edits {sorted(unknown)}; valid: {', '.join(EDITS)}")
    spec = load_spec(task)
    for name, edit in EDITS.items():
        if name in edits:
            edit(spec, task)
    return spec.compile()


# ---------------------------------------------------------------------------------------------
# The edits
# ---------------------------------------------------------------------------------------------


def _geom_body(geom: mujoco.MjsGeom) -> str:
    return geom.parent.name or "world"


def prune_collisions(spec: mujoco.MjSpec, task: str, base_pads: bool = True) -> None:
    """Collisions off (contype = conaffinity = 0) for all robot geoms but ``COLLIDING_ROBOT_GEOMS``.

    base_link rests on the floor at every step. Its base is held by damping 1e11 on the slide
    joints, but that damping is integrated after the constraint solve, so the solver still sees a
    movable base and the floor contact changes the weld forces and the arm's motion (gripper
    0.2-1 mm over 50 random steps when dropped). The contact is kept through ``_base_pads``
    unless ``base_pads`` is False (kept only to measure what dropping it does).
    """
    del task
    if base_pads:
        _base_pads(spec)
    for geom in spec.geoms:
        if geom.name in COLLIDING_ROBOT_GEOMS or _geom_body(geom) in COLLIDING_BODIES:
            continue
        if geom.name.startswith(BASE_PAD):
            continue
        geom.contype = 0
        geom.conaffinity = 0


def _base_pads(spec: mujoco.MjSpec) -> None:
    """Reproduce base_link's floor contacts with spheres at the contacting mesh vertices.

    MuJoCo's plane-mesh collision gives three contacts at the lowest vertices of the base mesh.
    A sphere of radius r centred r above each vertex yields the same contact: same distance,
    point, frame and (explicit pair) parameters. The base only translates, so the three points
    stay the contacting ones. Unlike the mesh (which MJX allows no margin), sphere-plane pairs
    keep the 0.001 margin that makes these contacts active at all (the vertices sit ~1e-6 m
    above the floor).
    """
    model = spec.copy().compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    base, floor = model.geom("robot0:base_link").id, model.geom("floor0").id
    body = model.geom_bodyid[base]
    contacts = [c for c in data.contact[: data.ncon] if {c.geom1, c.geom2} == {base, floor}]
    xmat = data.xmat[body].reshape(3, 3)
    for k, con in enumerate(contacts):
        normal = con.frame[:3] * (1.0 if con.geom1 == floor else -1.0)  # floor -> base
        vertex = con.pos + 0.5 * con.dist * normal
        centre = xmat.T @ (vertex + BASE_PAD_RADIUS * normal - data.xpos[body])
        name = f"{BASE_PAD}{k}"
        spec.body("robot0:base_link").add_geom(
            name=name,
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[BASE_PAD_RADIUS, 0, 0],
            pos=centre.tolist(),
            contype=0,
            conaffinity=0,
            group=4,
            rgba=[0, 0, 0, 0],
            mass=0.0,
        )
        _add_matching_pair(spec, model, floor, base, names=("floor0", name))


def puck_to_prism(spec: mujoco.MjSpec, task: str, sides: int = PUCK_SIDES) -> None:
    """Replace the Slide puck (a cylinder) by a convex ``sides``-gon prism of the same body inertia.

    The prism's circumradius is chosen so that its area equals the disc's: the mean contact
    radius then matches the cylinder's, and the puck's footprint on the table is the same.
    """
    geom = spec.geom("object0")
    if geom is None or geom.type != mujoco.mjtGeom.mjGEOM_CYLINDER:
        return
    body = spec.body("object0")
    # Read the cylinder's compiled mass and inertia before the geom changes.
    ref = spec.copy().compile()
    bid = ref.body("object0").id
    mass = float(ref.body_mass[bid])
    inertia = ref.body_inertia[bid].copy()
    ipos = ref.body_ipos[bid].copy()
    iquat = ref.body_iquat[bid].copy()

    radius, half_height = float(geom.size[0]), float(geom.size[1])
    circumradius = radius * np.sqrt(2 * np.pi / (sides * np.sin(2 * np.pi / sides)))
    angles = 2 * np.pi * np.arange(sides) / sides
    ring = np.stack([circumradius * np.cos(angles), circumradius * np.sin(angles)], axis=1)
    verts = np.concatenate(
        [np.c_[ring, np.full(sides, -half_height)], np.c_[ring, np.full(sides, half_height)]]
    )
    spec.add_mesh(name=PUCK_MESH, uservert=verts.ravel().tolist())
    geom.type = mujoco.mjtGeom.mjGEOM_MESH
    geom.meshname = PUCK_MESH

    # A mesh's own inertia differs from the cylinder's (and a mesh is recentred on its
    # centroid), so pin the body's inertial frame to the cylinder's values.
    body.explicitinertial = True
    body.mass = mass
    body.inertia = inertia
    body.ipos = ipos
    body.iquat = iquat


def zero_mesh_margins(spec: mujoco.MjSpec, task: str) -> None:
    """Zero the contact margin of every colliding pair with a mesh in it (MJX has no mesh margin).

    Mesh geoms get margin 0. A non-mesh geom with a margin that meets a mesh (the finger boxes,
    margin 0.001, against the Slide prism or, unpruned, the arm links) keeps its margin for its
    other pairs; the mesh pair gets an explicit ``<pair>`` with margin 0 and the same condim,
    friction, solref and solimp that MuJoCo's mixing rules give the dynamic contact.
    """
    del task
    quiet_mjx()
    from mujoco.mjx._src import collision_driver  # the pair enumeration put_model checks

    mesh = mujoco.mjtGeom.mjGEOM_MESH
    for geom in spec.geoms:
        if geom.type == mesh:
            geom.margin = 0.0
    model = spec.copy().compile()
    for g1, g2, ip in list(collision_driver.geom_pairs(model)):
        types = model.geom_type[[g1, g2]]
        if ip != -1 or mesh not in types or types.tolist() == [mesh, mesh]:
            continue
        if not model.geom_margin[[g1, g2]].any():
            continue
        _add_matching_pair(spec, model, int(g1), int(g2), margin=0.0)


def zero_box_margins(spec: mujoco.MjSpec, task: str) -> None:
    """Zero the margin of every dynamic contact pair of two boxes or meshes (Warp's rule).

    MJX's Warp implementation has no margin for box-box, box-mesh or mesh-mesh contacts when
    multi-contact CCD is on (``put_model(impl="warp")`` raises). After the mjx edits these are
    the finger boxes (margin 0.001) against the table box and a box object: each such pair gets
    an explicit margin-0 ``<pair>`` with the mixed contact parameters (as ``zero_mesh_margins``
    does for mesh pairs), so the fingers keep their margin against the floor and the base pads
    keep theirs (sphere-plane pairs Warp supports with a margin). Physics: a finger's contact
    with the table or the box becomes active at contact instead of 1 mm before it, and the
    soft contact settles with about 1 mm less clearance. MuJoCo's multi-contact CCD itself
    (on by default, as in gymnasium-robotics' scenes) is kept.
    """
    del task
    quiet_mjx()
    from mujoco.mjx._src import collision_driver

    solid = (mujoco.mjtGeom.mjGEOM_BOX, mujoco.mjtGeom.mjGEOM_MESH)
    # An explicit pair names its geoms: name the unnamed ones (the table's box) by their body.
    named: dict[str, int] = {}
    for geom in spec.geoms:
        if not geom.name:
            body = _geom_body(geom)
            geom.name = f"{body}:geom{named.get(body, 0)}"
            named[body] = named.get(body, 0) + 1
    model = spec.copy().compile()
    for g1, g2, ip in list(collision_driver.geom_pairs(model)):
        if ip != -1 or not all(t in solid for t in model.geom_type[[g1, g2]]):
            continue
        if not model.geom_margin[[g1, g2]].any():
            continue
        _add_matching_pair(spec, model, int(g1), int(g2), margin=0.0)


def _add_matching_pair(
    spec: mujoco.MjSpec,
    model: mujoco.MjModel,
    g1: int,
    g2: int,
    names: tuple[str, str] | None = None,
    margin: float | None = None,
) -> None:
    """Add an explicit ``<pair>`` with the parameters of the dynamic contact g1-g2.

    ``names`` are the geoms the pair is made for (default: g1 and g2 themselves); ``margin``
    defaults to MuJoCo's max of the two geom margins.
    """
    names = names or (model.geom(g1).name, model.geom(g2).name)
    if not all(names):
        raise ValueError(f"geoms {g1}, {g2} need names for an explicit pair")
    # MuJoCo's mixing rules (mj_contactParam) for geoms of equal priority.
    mix1, mix2 = model.geom_solmix[[g1, g2]]
    mix = 0.5 if mix1 + mix2 < mujoco.mjMINVAL else mix1 / (mix1 + mix2)
    fr = np.maximum(model.geom_friction[g1], model.geom_friction[g2])
    sr1, sr2 = model.geom_solref[g1], model.geom_solref[g2]
    solref = mix * sr1 + (1 - mix) * sr2 if sr1[0] > 0 and sr2[0] > 0 else np.minimum(sr1, sr2)
    spec.add_pair(
        geomname1=names[0],
        geomname2=names[1],
        condim=int(max(model.geom_condim[[g1, g2]])),
        friction=[fr[0], fr[0], fr[1], fr[2], fr[2]],
        solref=solref.tolist(),
        solimp=(mix * model.geom_solimp[g1] + (1 - mix) * model.geom_solimp[g2]).tolist(),
        margin=float(max(model.geom_margin[[g1, g2]])) if margin is None else margin,
        gap=0.0,
    )


# Order matters: pruning first leaves fewer mesh pairs for the margin edit to handle, and the
# prism must exist before the margin edit sees the finger-puck pair as a mesh pair.
EDITS: dict[str, Callable[[mujoco.MjSpec, str], None]] = {
    "prune": prune_collisions,
    "puck": puck_to_prism,
    "margins": zero_mesh_margins,
}


def _edit_for_mjx(spec: mujoco.MjSpec, task: str) -> None:
    """Edits that make the scene loadable by ``mjx.put_model``, each as small as MJX allows.

    1. ``prune_collisions``: robot geoms other than the gripper link and the two finger boxes
       get contype = conaffinity = 0. MJX has no broadphase: each of the 144-163 original pairs
       (84 mesh-mesh) would be computed every substep; 9 (Reach) to 14 remain. base_link's floor
       contact is kept as three spheres at the contacting mesh vertices (``_base_pads``): the base
       is held by damping 1e11, but the constraint solver does not see that damping, so dropping
       the contact changes the arm's motion (0.2-1 mm of gripper over 50 random steps); with the
       pads, native dynamics equal the original's to round-off.
    2. ``puck_to_prism`` (Slide): MJX has no cylinder-box or cylinder-mesh collision, so the puck
       becomes a 16-sided convex prism of equal area and height, same friction and condim, with
       the cylinder's mass, inertia and inertial frame set explicitly (a mesh's own inertia
       differs and its frame is rotated to principal axes). Its contacts with the table and the
       fingers still differ from the cylinder's: the dominant deviation left (cm over a struck
       episode; the puck hops while sliding and is very sensitive to how its contacts catch).
    3. ``zero_mesh_margins``: MJX implements no margin for mesh pairs, so mesh geoms (the
       gripper link, the prism) get margin 0; where a finger box (margin 0.001) meets a mesh, that
       pair alone gets an explicit margin-0 ``<pair>`` with the mixed contact parameters, so the
       finger boxes keep their margin against the table, floor and box objects.

    Everything MJX accepts as is stays: timestep, solver and its options, integrator, damping,
    armature, equality and actuator parameters. No option makes MJX 3.11 and MuJoCo 3.11 agree:
    native MuJoCo adds the weld's Jdot*qvel term to the reference acceleration, MJX does not
    (experiments/results/scene_edits.md, section 3).
    """
    for edit in EDITS.values():
        edit(spec, task)


# The edits of the ``warp`` scene, applied after all of ``EDITS``.
WARP_EDITS: dict[str, Callable[[mujoco.MjSpec, str], None]] = {
    "box_margins": zero_box_margins,
}


def _edit_for_warp(spec: mujoco.MjSpec, task: str) -> None:
    """Edits that make the ``mjx`` scene loadable by ``mjx.put_model(m, impl="warp")``.

    1. ``zero_box_margins``: Warp refuses a non-zero margin on a box-box, box-mesh or mesh-mesh
       pair while multi-contact CCD is on; after the mjx edits only the finger boxes (margin
       0.001) against the table and a box object remain. Those pairs get an explicit margin-0
       ``<pair>``: the contact becomes active at touch rather than 1 mm before it.

    Everything else of the mjx scene stays, multi-contact CCD included (gymnasium-robotics'
    scenes run with it). The explicit pairs are not checked by Warp and keep their margins
    (the base pads' sphere-plane pairs).
    """
    for edit in WARP_EDITS.values():
        edit(spec, task)
