"""MjSpec builders of the paper's seven systems (supplementary section B) and their spec helpers.

Each ``build_<system>(p, timestep)`` takes the full parameter dict of one instance (defaults
filled in by the registry, ``gnwarp.sim.systems``; the cheetah also the fixed system's, which
calibrate its density) and the physics timestep, and returns a ``mujoco.MjSpec`` mirroring the
DeepMind Control Suite model (the JACO: dm_control's manipulation suite, with capsules in place
of the meshes).
"""
from __future__ import annotations

import math

import mujoco
import numpy as np

from gnwarp.state import quat_axis_angle, quat_mul, quat_rotate

__all__ = ["build_pendulum", "build_cartpole", "build_acrobot", "build_swimmer", "build_cheetah", "build_walker",
           "build_jaco", "CHEETAH_BODIES", "CHEETAH_LIMBS", "JACO_BODIES", "JACO_ACTUATOR_NAMES"]


# ------------------------------------------------------------------------------------------------
# Spec helpers.


def _capsule_volume(radius: float, length: float) -> float:
    """Volume of a capsule with cylinder length `length` (MuJoCo's exact formula)."""
    return math.pi * radius**2 * length + 4.0 / 3.0 * math.pi * radius**3


_FLOOR_RGBA = (0.4, 0.45, 0.5, 1.0)
_SELF_RGBA = (0.7, 0.5, 0.3, 1.0)
_DECOR_RGBA = (0.3, 0.5, 0.7, 1.0)
_EFFECTOR_RGBA = (0.7, 0.4, 0.2, 1.0)
_DEG = math.pi / 180.0


def _new_spec(model_name: str, timestep: float) -> mujoco.MjSpec:
    spec = mujoco.MjSpec()
    spec.modelname = model_name
    spec.compiler.degree = False  # every angle below is in radians
    spec.compiler.autolimits = True
    spec.option.timestep = timestep
    return spec


def _disable(spec: mujoco.MjSpec, *flags: mujoco.mjtDisableBit) -> None:
    for flag in flags:
        spec.option.disableflags |= int(flag)


def _floor(spec: mujoco.MjSpec, size, pos=(0.0, 0.0, 0.0), **kwargs) -> None:
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=size, pos=pos,
                            rgba=_FLOOR_RGBA, **kwargs)


def _hinge(body, name: str, axis, **kwargs):
    return body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_HINGE, axis=axis, **kwargs)


def _slide(body, name: str, axis, **kwargs):
    return body.add_joint(name=name, type=mujoco.mjtJoint.mjJNT_SLIDE, axis=axis, **kwargs)


def _limits(low: float, high: float) -> dict:
    return {"limited": mujoco.mjtLimited.mjLIMITED_TRUE, "range": [low, high]}


_UNLIMITED = {"limited": mujoco.mjtLimited.mjLIMITED_FALSE}


def _motor(spec: mujoco.MjSpec, name: str, joint: str, gear: float, ctrlrange=(-1.0, 1.0)):
    act = spec.add_actuator(name=name, target=joint, trntype=mujoco.mjtTrn.mjTRN_JOINT)
    act.set_to_motor()
    act.gear[0] = gear
    act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
    act.ctrlrange = list(ctrlrange)
    return act


def _capsule(body, name: str, radius: float, fromto=None, pos=None, quat=None, half_length=None,
             **kwargs):
    geom = body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_CAPSULE, **kwargs)
    if fromto is not None:
        geom.fromto = list(fromto)
        geom.size = [radius, 0.0, 0.0]
    else:
        geom.size = [radius, half_length, 0.0]
        geom.pos = list(pos)
        if quat is not None:
            geom.quat = list(quat)
    return geom


# ------------------------------------------------------------------------------------------------
# The systems. Each builder takes the full parameter dict (defaults filled in) and returns a spec.


def build_pendulum(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """suite/pendulum.xml: a massless rod with a 1 kg bob, torque at the hinge."""
    spec = _new_spec("pendulum", timestep)
    _disable(spec, mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _floor(spec, [2.5, 2.5, 0.2])
    length = 0.5 * p["length"]
    pole = spec.worldbody.add_body(name="pole", pos=[0, 0, 0.6])
    _hinge(pole, "hinge", [0, 1, 0], damping=0.1)
    pole.add_geom(name="base", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                  fromto=[0, -0.03, 0, 0, 0.03, 0], size=[0.021, 0, 0], mass=0.0,
                  rgba=_DECOR_RGBA)
    _capsule(pole, "pole", 0.02, fromto=[0, 0, 0, 0, 0, length], mass=0.0, rgba=_SELF_RGBA)
    # The bob's size does not change with the parameters, so its mass factor is a mass.
    pole.add_geom(name="mass", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[0, 0, length],
                  size=[0.05, 0, 0], mass=1.0 * p["mass"], rgba=_EFFECTOR_RGBA)
    _motor(spec, "torque", "hinge", gear=1.0)
    return spec


_CARTPOLE_POLE_RADIUS = 0.045
# dm_control gives the 1 m pole 0.1 kg; keep that density when its length or thickness changes.
_CARTPOLE_POLE_DENSITY = 0.1 / _capsule_volume(_CARTPOLE_POLE_RADIUS, 1.0)


def build_cartpole(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """suite/cartpole.xml: a cart on a rail (force input) with an unactuated pole."""
    spec = _new_spec("cart-pole", timestep)
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
    _disable(spec, mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _floor(spec, [4, 4, 0.2], pos=[0, 0, -0.05])
    for name, y in (("rail1", 0.07), ("rail2", -0.07)):
        _capsule(spec.worldbody, name, 0.02, fromto=[-2, y, 1, 2, y, 1], rgba=_DECOR_RGBA)
    cart = spec.worldbody.add_body(name="cart", pos=[0, 0, 1])
    _slide(cart, "slider", [1, 0, 0], damping=5e-4, solref_limit=[0.08, 1], **_limits(-1.8, 1.8))
    # The cart's size never changes, so its mass factor is a mass.
    cart.add_geom(name="cart", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.2, 0.15, 0.1],
                  mass=1.0 * p["cart_mass"], rgba=_SELF_RGBA)
    pole = cart.add_body(name="pole_1")
    _hinge(pole, "hinge_1", [0, 1, 0], damping=2e-6)
    _capsule(pole, "pole_1", _CARTPOLE_POLE_RADIUS * p["pole_thickness"],
             fromto=[0, 0, 0, 0, 0, 1.0 * p["pole_length"]], density=_CARTPOLE_POLE_DENSITY,
             rgba=_SELF_RGBA)
    _motor(spec, "slide", "slider", gear=10.0)
    return spec


def build_acrobot(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """suite/acrobot.xml (Coulom's model): two 1 kg links, torque at the elbow only."""
    spec = _new_spec("acrobot", timestep)
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_RK4
    # dm_control disables all constraints; contacts are named too so every contact-free system
    # carries the same flag.
    _disable(spec, mujoco.mjtDisableBit.mjDSBL_CONSTRAINT, mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _floor(spec, [3, 3, 0.2])
    upper = spec.worldbody.add_body(name="upper_arm", pos=[0, 0, 2])
    _hinge(upper, "shoulder", [0, 1, 0], damping=0.05)
    upper.add_geom(name="upper_arm_decoration", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                   fromto=[0, -0.06, 0, 0, 0.06, 0], size=[0.051, 0, 0], mass=0.0,
                   rgba=_DECOR_RGBA)
    _capsule(upper, "upper_arm", 0.05, fromto=[0, 0, 0, 0, 0, 1], mass=1.0, rgba=_SELF_RGBA)
    lower = upper.add_body(name="lower_arm", pos=[0, 0, 1])
    _hinge(lower, "elbow", [0, 1, 0], damping=0.05)
    _capsule(lower, "lower_arm", 0.049, fromto=[0, 0, 0, 0, 0, 1], mass=1.0, rgba=_SELF_RGBA)
    lower.add_site(name="tip", pos=[0, 0, 1], size=[0.01, 0, 0])
    _motor(spec, "elbow", "elbow", gear=2.0)
    return spec


# dm_control's swimmer link: a 0.01 kg inertial box .002 x .1 x .02 m (it sets the link's inertia
# and so the drag of MuJoCo's inertia-based fluid model) plus a massless visual capsule.
_SWIMMER_BOX = (0.001, 0.05, 0.01)  # half sizes: thickness (in plane), half length, height
_SWIMMER_DENSITY = 0.01 / (8 * _SWIMMER_BOX[0] * _SWIMMER_BOX[1] * _SWIMMER_BOX[2])


def build_swimmer(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """suite/swimmer.py + swimmer.xml: N links in a viscous medium, N-1 motors between links.

    Link i is centered on its body frame along y with half length h_i; its joint sits at -h_i and
    the next link's frame at h_i + h_{i+1}, so the chain stays connected for any lengths.
    """
    n = int(p["n_links"])
    spec = _new_spec(f"swimmer{n}", timestep)
    spec.option.density = 3000.0
    _disable(spec, mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _floor(spec, [2.5, 2.5, 0.1])
    spec.worldbody.add_geom(name="target", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[1, 1, 0.05],
                            size=[0.1, 0, 0], contype=0, conaffinity=0, rgba=_EFFECTOR_RGBA)

    half = [_SWIMMER_BOX[1] * p[f"link_length_{i}"] for i in range(n)]
    thick = [p[f"link_thickness_{i}"] for i in range(n)]
    joint_range = 2 * math.pi / n  # dm_control: +-360/N degrees

    def add_link(body, i: int) -> None:
        h, t = half[i], thick[i]
        body.add_geom(name="inertial" if i == 0 else f"inertial_{i - 1}",
                      type=mujoco.mjtGeom.mjGEOM_BOX,
                      size=[_SWIMMER_BOX[0] * t, h, _SWIMMER_BOX[2] * t],
                      density=_SWIMMER_DENSITY, rgba=[0, 0, 0, 0])
        _capsule(body, "visual" if i == 0 else f"visual_{i - 1}", 0.01 * t,
                 fromto=[0, -h, 0, 0, h, 0], mass=0.0, rgba=_SELF_RGBA)

    head = spec.worldbody.add_body(name="head", pos=[0, 0, 0.05])
    root = {"pos": [0, -half[0], 0], **_UNLIMITED}
    _slide(head, "rootx", [1, 0, 0], **root)
    _slide(head, "rooty", [0, 1, 0], **root)
    _hinge(head, "rootz", [0, 0, 1], **root)
    # Massless decorations of the head, scaled with its length.
    s = p["link_length_0"]
    head.add_geom(name="head", type=mujoco.mjtGeom.mjGEOM_ELLIPSOID, pos=[0, -0.022 * s, 0],
                  size=[0.02 * thick[0], 0.04 * s, 0.017 * thick[0]], mass=0.0, rgba=_SELF_RGBA)
    head.add_geom(name="nose", type=mujoco.mjtGeom.mjGEOM_SPHERE, pos=[0, -0.06 * s, 0],
                  size=[0.004, 0, 0], mass=0.0, rgba=_EFFECTOR_RGBA)
    _capsule(head, "eyes", 0.004, fromto=[-0.006, -0.054 * s, 0.005, 0.006, -0.054 * s, 0.005],
             mass=0.0, rgba=_DECOR_RGBA)
    add_link(head, 0)
    head.add_site(name="head", size=[0.01, 0, 0])

    parent = head
    for i in range(1, n):
        body = parent.add_body(name=f"segment_{i - 1}", pos=[0, half[i - 1] + half[i], 0])
        add_link(body, i)
        body.add_site(name=f"site_{i - 1}", size=[0.01, 0, 0])
        _hinge(body, f"joint_{i - 1}", [0, 0, 1], pos=[0, -half[i], 0], armature=1e-6,
               solref_limit=[0.05, 1], solimp_limit=[0, 0.8, 0.1, 0.5, 2],
               **_limits(-joint_range, joint_range))
        _motor(spec, f"motor_{i - 1}", f"joint_{i - 1}", gear=5e-4)
        parent = body
    return spec


# suite/cheetah.xml, per body: (parent, pos in parent, joint range (deg), stiffness, damping,
# geoms as (pos, pitch (deg), half length)); the torso's first geom spans -.5..+.5 along x.
CHEETAH_BODIES = {
    "torso": (None, (0, 0, 0.7), None, None, None,
              [((0, 0, 0), -90.0, 0.5), ((0.6, 0, 0.1), 50.0, 0.15)]),
    "bthigh": ("torso", (-0.5, 0, 0), (-30, 60), 240, 6, [((0.1, 0, -0.13), -218.0, 0.145)]),
    "bshin": ("bthigh", (0.16, 0, -0.25), (-50, 50), 180, 4.5, [((-0.14, 0, -0.07), -116.0, 0.15)]),
    "bfoot": ("bshin", (-0.28, 0, -0.14), (-230, 50), 120, 3, [((0.03, 0, -0.097), -15.0, 0.094)]),
    "fthigh": ("torso", (0.5, 0, 0), (-57, 0.4), 180, 4.5, [((-0.07, 0, -0.12), 30.0, 0.133)]),
    "fshin": ("fthigh", (-0.14, 0, -0.24), (-70, 50), 120, 3, [((0.065, 0, -0.09), -34.0, 0.106)]),
    "ffoot": ("fshin", (0.13, 0, -0.18), (-28, 28), 60, 1.5, [((0.045, 0, -0.07), -34.0, 0.07)]),
}
CHEETAH_LIMBS = tuple(b for b in CHEETAH_BODIES if b != "torso")
_CHEETAH_GEARS = {"bthigh": 120, "bshin": 90, "bfoot": 60, "fthigh": 90, "fshin": 60, "ffoot": 30}
_CHEETAH_RADIUS = 0.046
_CHEETAH_TOTAL_MASS = 14.0  # dm_control: <compiler settotalmass="14"/>


def _cheetah_spec(p: dict[str, float], timestep: float, density: float,
                  torso_lift: float) -> mujoco.MjSpec:
    spec = _new_spec("cheetah", timestep)
    spec.stat.center = [0, 0, 0.7]
    spec.stat.extent = 2.0
    _floor(spec, [100, 1.25, 0.5], pos=[98, 0, 0], conaffinity=1)
    bodies = {}
    for name, (parent, pos, rng, stiffness, damping, geoms) in CHEETAH_BODIES.items():
        length, thickness = p[f"length_{name}"], p[f"thickness_{name}"]
        parent_body = spec.worldbody if parent is None else bodies[parent]
        # Child frames sit at the end of the parent's link: they scale with the parent's length.
        scale = 1.0 if parent is None else p[f"length_{parent}"]
        body_pos = np.asarray(pos, dtype=float) * scale
        if parent is None:
            body_pos[2] += torso_lift
            body = parent_body.add_body(name=name, pos=body_pos)
            free = {"damping": 0.0, "armature": 0.0, "stiffness": 0.0, **_UNLIMITED}
            _slide(body, "rootx", [1, 0, 0], **free)
            _slide(body, "rootz", [0, 0, 1], **free)
            _hinge(body, "rooty", [0, 1, 0], **free)
        else:
            angle = p[f"base_angle_{name}"]
            body = parent_body.add_body(name=name, pos=body_pos,
                                        quat=quat_axis_angle([0, 1, 0], angle))
            _hinge(body, name, [0, 1, 0], stiffness=stiffness, damping=damping, armature=0.1,
                   **_limits(rng[0] * _DEG, rng[1] * _DEG))
        bodies[name] = body
        for k, (gpos, pitch, half_length) in enumerate(geoms):
            _capsule(body, name if k == 0 else "head", _CHEETAH_RADIUS * thickness,
                     pos=np.asarray(gpos) * length, quat=quat_axis_angle([0, 1, 0], pitch * _DEG),
                     half_length=half_length * length, density=density, contype=1, conaffinity=1,
                     condim=3, friction=[0.4, 0.1, 0.1], rgba=_SELF_RGBA)
    for name in CHEETAH_LIMBS:
        _motor(spec, name, name, gear=_CHEETAH_GEARS[name])
    return spec


def _lowest_point(model: mujoco.MjModel) -> float:
    """Lowest z of the capsules of all non-world bodies at qpos0."""
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    low = np.inf
    for g in range(model.ngeom):
        if model.geom_bodyid[g] == 0:
            continue
        axis = data.geom_xmat[g].reshape(3, 3)[:, 2]
        radius, half = model.geom_size[g, :2]
        low = min(low, data.geom_xpos[g, 2] - abs(axis[2]) * half - radius)
    return float(low)


_CHEETAH_FIXED: dict[str, float] = {}


def _cheetah_fixed(p: dict[str, float]) -> dict[str, float]:
    """The density that gives the fixed cheetah (parameters ``p``) its 14 kg, and its feet's
    clearance at qpos0."""
    if not _CHEETAH_FIXED:
        raw = _cheetah_spec(p, 0.01, 1000.0, 0.0).compile()
        density = 1000.0 * _CHEETAH_TOTAL_MASS / float(raw.body_mass.sum())
        fixed = _cheetah_spec(p, 0.01, density, 0.0).compile()
        _CHEETAH_FIXED.update(density=density, lowest=_lowest_point(fixed))
    return _CHEETAH_FIXED


def build_cheetah(p: dict[str, float], timestep: float, fixed: dict[str, float]) -> mujoco.MjSpec:
    """suite/cheetah.xml: planar half-cheetah, 3 root dofs, 6 motors, contacts with the floor.

    dm_control rescales its geoms to 14 kg in total (settotalmass); we bake that into one density
    so that parameterized bodies keep it and their masses follow their sizes. The torso starts
    raised or lowered so the lowest point keeps the fixed model's clearance above the floor.
    ``fixed``: the parameters of the fixed cheetah (the registry's defaults), which set both.
    """
    fixed = _cheetah_fixed(fixed)
    probe = _cheetah_spec(p, timestep, fixed["density"], 0.0).compile()
    lift = fixed["lowest"] - _lowest_point(probe)
    return _cheetah_spec(p, timestep, fixed["density"], lift)


def build_walker(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """suite/walker.xml: planar biped, 3 root dofs, hips, knees and ankles, contacts with floor."""
    spec = _new_spec("planar walker", timestep)
    spec.stat.center = [0, 0, 1]
    spec.stat.extent = 2.0
    geom_kw = {"contype": 1, "conaffinity": 0, "friction": [0.7, 0.1, 0.1]}
    _floor(spec, [250, 0.8, 0.2], pos=[248, 0, 0], **{**geom_kw, "conaffinity": 1})
    joint_kw = {"damping": 0.1, "armature": 0.01, "solimp_limit": [0, 0.99, 0.01, 0.5, 2]}
    torso = spec.worldbody.add_body(name="torso", pos=[0, 0, 1.3])
    free = {**joint_kw, "armature": 0.0, "damping": 0.0, **_UNLIMITED}
    _slide(torso, "rootz", [0, 0, 1], **free)
    _slide(torso, "rootx", [1, 0, 0], **free)
    _hinge(torso, "rooty", [0, 1, 0], **free)
    _capsule(torso, "torso", 0.07, pos=[0, 0, 0], half_length=0.3, rgba=_SELF_RGBA, **geom_kw)
    foot_quat = quat_axis_angle([0, 1, 0], math.pi / 2)  # zaxis="1 0 0"
    for side, y in (("right", -0.05), ("left", 0.05)):
        thigh = torso.add_body(name=f"{side}_thigh", pos=[0, y, -0.3])
        _hinge(thigh, f"{side}_hip", [0, -1, 0], **joint_kw, **_limits(-20 * _DEG, 100 * _DEG))
        _capsule(thigh, f"{side}_thigh", 0.05, pos=[0, 0, -0.225], half_length=0.225,
                 rgba=_SELF_RGBA, **geom_kw)
        leg = thigh.add_body(name=f"{side}_leg", pos=[0, 0, -0.7])
        _hinge(leg, f"{side}_knee", [0, -1, 0], pos=[0, 0, 0.25], **joint_kw,
               **_limits(-150 * _DEG, 0.0))
        _capsule(leg, f"{side}_leg", 0.04, pos=[0, 0, 0], half_length=0.25, rgba=_SELF_RGBA,
                 **geom_kw)
        foot = leg.add_body(name=f"{side}_foot", pos=[0.06, 0, -0.25])
        _hinge(foot, f"{side}_ankle", [0, -1, 0], pos=[-0.06, 0, 0], **joint_kw,
               **_limits(-45 * _DEG, 45 * _DEG))
        _capsule(foot, f"{side}_foot", 0.05, pos=[0, 0, 0], quat=foot_quat, half_length=0.1,
                 rgba=_SELF_RGBA, **geom_kw)
    for side in ("right", "left"):
        for joint, gear in (("hip", 100), ("knee", 50), ("ankle", 20)):
            _motor(spec, f"{side}_{joint}", f"{side}_{joint}", gear=gear)
    return spec


# Kinova JACO (j2n6s300) after dm_control's third_party/kinova/jaco_arm.xml + jaco_hand.xml:
# the same kinematic tree and masses, capsules instead of meshes, the base and the finger tips
# fused into the world and the proximal finger bodies. Per body: (parent, pos, quat, joint ref,
# joint class, geoms as (fromto in the body frame, radius, mass)). Joints 2, 3, 5 and the fingers
# get a `ref` so that qpos0 is the upright "candle" pose with half-closed fingers, inside the
# limits, while joint angles keep Kinova's (and dm_control's) convention.
_JACO_HAND_QUAT = np.array([0.0, 0.70710678118, 0.70710678118, 0.0])  # dm_control's wristsite
_JACO_ARM = {
    "shoulder": (None, (0, 0, 0.15675), (0, 0, 1, 0), 0.0, "large",
                 [((0, 0, 0, 0, 0.0016, -0.11875), 0.045, 0.643205)]),
    "arm": ("shoulder", (0, 0.0016, -0.11875), (0, 0, -0.707107, 0.707107), math.pi, "large",
            [((0, 0, 0, 0, -0.41, 0), 0.04, 1.16915)]),
    "forearm": ("arm", (0, -0.41, 0), (0, 0, 1, 0), math.pi, "large",
                [((0, 0, 0, 0, 0.2073, -0.0114), 0.035, 0.673443)]),
    "wrist_1": ("forearm", (0, 0.2073, -0.0114), (0, 0, -0.707107, 0.707107), 0.0, "small",
                [((0, 0, 0, 0, -0.03703, -0.06414), 0.03, 0.221432)]),
    "wrist_2": ("wrist_1", (0, -0.03703, -0.06414), (0, 0, 0.5, 0.866025), math.pi, "small",
                [((0, 0, 0, 0, -0.03703, -0.06414), 0.03, 0.221432)]),
    # The hand extends along the wrist's +z: dm_control's hand frame points its -z there.
    "hand": ("wrist_2", (0, -0.03703, -0.06414), (0, 0, 0.5, 0.866025), 0.0, "small",
             [((0, 0, 0, 0, 0, 0.12), 0.04, 0.54719)]),
}
# Finger frames in dm_control's hand frame; each finger is a proximal (0.0255 kg) and a distal
# (0.0133 kg) capsule.
_JACO_FINGERS = {
    "finger_1": ((0.00279, 0.03126, -0.11467), (0.24396, -0.63159, -0.38818, 0.62521)),
    "finger_2": ((-0.02226, -0.02707, -0.11482), (0.601679, -0.254671, 0.659653, -0.37146)),
    "finger_3": ((0.02226, -0.02707, -0.11482), (0.659653, -0.37146, 0.601679, -0.254671)),
}
_JACO_FINGER_GEOMS = [((0, 0, 0, 0.044, -0.003, 0), 0.011, 0.0255204),
                      ((0.044, -0.003, 0, 0.084, -0.006, 0), 0.009, 0.0132655)]
_JACO_FINGER_RANGE = (0.15, 1.35)
_JACO_JOINTS = {  # dm_control's joint classes
    "large": {"armature": 4.0, "frictionloss": 2.0, "damping": 0.01},
    "small": {"armature": 2.0, "frictionloss": 1.0, "damping": 0.01},
    "finger": {"armature": 0.1, "frictionloss": 0.1, "damping": 0.75},
}
_JACO_LIMITS = {"arm": (0.820305, 5.462881), "forearm": (0.331613, 5.951573)}
# dm_control's velocity actuators: kv, |target velocity| (rad/s), |force| (peak torque, N m).
_JACO_ACTUATORS = {
    "large": (500.0, 36 * _DEG, 30.5),
    "small": (500.0, 48 * _DEG, 6.8),
    "finger": (10.0, 5.0, 1.0),
}
JACO_BODIES = tuple(_JACO_ARM) + tuple(_JACO_FINGERS)
JACO_ACTUATOR_NAMES = tuple(f"joint_{i}" for i in range(1, 7)) + tuple(_JACO_FINGERS)


def build_jaco(p: dict[str, float], timestep: float) -> mujoco.MjSpec:
    """A kinematically faithful Kinova JACO: 6 arm joints, 3 fingers, 9 velocity actuators."""
    spec = _new_spec("jaco", timestep)
    # The velocity actuators act as stiff dampers: integrate them implicitly.
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    _disable(spec, mujoco.mjtDisableBit.mjDSBL_CONTACT)
    _floor(spec, [1.5, 1.5, 0.1])
    spec.worldbody.add_geom(name="base", type=mujoco.mjtGeom.mjGEOM_CYLINDER,
                            fromto=[0, 0, 0, 0, 0, 0.15675], size=[0.045, 0, 0], mass=0.0,
                            rgba=_DECOR_RGBA)

    def add_joint(body, name: str, kind: str, ref: float, limits):
        kw = dict(_JACO_JOINTS[kind])
        kw.update(_limits(*limits) if limits is not None else _UNLIMITED)
        _hinge(body, name, [0, 0, 1], ref=ref, **kw)
        kv, vmax, fmax = _JACO_ACTUATORS[kind]
        act = spec.add_actuator(name=name, target=name, trntype=mujoco.mjtTrn.mjTRN_JOINT)
        act.set_to_velocity(kv=kv)
        act.gear[0] = p[f"gear_{name}"]
        act.ctrllimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.ctrlrange = [-vmax, vmax]
        act.forcelimited = mujoco.mjtLimited.mjLIMITED_TRUE
        act.forcerange = [-fmax, fmax]

    def add_geoms(body, name: str, geoms, frame_quat=None, frame_pos=None):
        for k, (fromto, radius, mass) in enumerate(geoms):
            fromto = np.asarray(fromto, dtype=float)
            if frame_quat is not None:
                fromto = np.concatenate([quat_rotate(frame_quat, fromto[:3]) + frame_pos,
                                         quat_rotate(frame_quat, fromto[3:]) + frame_pos])
            _capsule(body, f"{name}_{k}", radius, fromto=fromto, mass=mass * p[f"mass_{name}"],
                     rgba=_SELF_RGBA if k == 0 else _DECOR_RGBA)

    bodies = {}
    for i, (name, (parent, pos, quat, ref, kind, geoms)) in enumerate(_JACO_ARM.items(), start=1):
        parent_body = spec.worldbody if parent is None else bodies[parent]
        # A joint with ref r shows its body frame at q = r: turn the frame by r about the axis so
        # the pose at angle q stays dm_control's.
        body = parent_body.add_body(name=name, pos=list(pos),
                                    quat=quat_mul(np.asarray(quat, dtype=float), quat_axis_angle([0, 0, 1], ref)))
        add_joint(body, f"joint_{i}", kind, ref, _JACO_LIMITS.get(name))
        add_geoms(body, name, geoms)
        bodies[name] = body
    hand = bodies["hand"]
    finger_ref = 0.5 * sum(_JACO_FINGER_RANGE)
    for name, (pos, quat) in _JACO_FINGERS.items():
        frame = quat_mul(_JACO_HAND_QUAT, np.asarray(quat, dtype=float))
        body = hand.add_body(name=name, pos=quat_rotate(_JACO_HAND_QUAT, np.asarray(pos, dtype=float)),
                             quat=quat_mul(frame, quat_axis_angle([0, 0, 1], finger_ref)))
        add_joint(body, name, "finger", finger_ref, _JACO_FINGER_RANGE)
        # Geoms are given in the dm_control finger frame, which is ours turned back by the ref.
        add_geoms(body, name, _JACO_FINGER_GEOMS,
                  frame_quat=quat_axis_angle([0, 0, 1], -finger_ref), frame_pos=np.zeros(3))
    return spec
