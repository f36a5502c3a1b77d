"""The Panda scenarios (issue 36): a Franka Panda hangs a NeuralSDF mug on the NDF rack's peg, and places a
NeuralSDF bottle upright in a holder; each with a shape of the model (seen) and one fitted by ``fit_codes`` from a
mesh of the test split (unseen).

Planning, done once before a run and written into the scene files (``scenes/panda-*.toml``) as joint-space waypoints
for the Panda's position actuators: the gripper's poses (a top-down grasp of the mug's rim opposite its handle, or
of the bottle's body; the carry; the hang or the placement; the release and the withdrawal) are found on the
object's SDF (:func:`mug_grasp`, :func:`zoo`'s ``benches.demo.hanging_pose``), turned into joint angles by damped
least-squares inverse kinematics on the MuJoCo model (:func:`ik`), with straight Cartesian segments sampled every
few centimetres, and offset by the arm's gravity torque over each actuator's gain (the feed-forward a position-
controlled arm needs not to sag). The run itself is ``zoo simulate scenes/panda-....toml``: every contact of the
object (fingers, table, rack, holder) is sdfzoo's; the robot's with the table is MuJoCo's.

    ZOO_DATA=../shared/meshes python -m sdfzoo.benches.panda_scenarios --write     # (re)plan the four scene files
    ZOO_DATA=../shared/meshes python -m sdfzoo.benches.panda_scenarios --run panda-bottle-holder  # run one, check it
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from zoo.resources import bundled

SCENES = bundled("scenes")  # the clone's scenes/, or the wheel's copy
PANDA_XML = "panda.xml"
ARM = [f"robot:panda0_joint{i}" for i in range(1, 8)]
ARM_ACTUATORS = [f"panda0_joint{i}" for i in range(1, 8)]
FINGERS = ["r_gripper_finger_joint", "l_gripper_finger_joint"]
OPEN, CLOSED = 0.04, -0.01  # finger targets: fully open; 1 cm past closed, so a closed hand presses
# the mug's rim grasp presses harder (2 cm past closed, the finger ctrlrange's end): at -0.01 the pads (about 7 N)
# let the mug turn 14 degrees and slip 24 mm in the hand during the carry, 30 degrees by the release (measured)
MUG_CLOSED = -0.02
TCP = 0.225  # link7 origin to the pads' middle along the approach axis, m
HOME = np.array([0.0, -0.1, 0.0, -2.5, 0.0, 0.85, 0.0])  # gripper down, fingers closing along -y
RACK_POSE = {"translation": [0.62, 0.30, 0.0], "rotation_deg": [0.0, 0.0, 180.0]}
PEG_START, PEG_DIR, PEG_RADIUS = np.array([0.0247, 0.0, 0.1564]), np.array([0.643, 0.0, 0.766]), 0.0095
HOLDER = {"inner_radius": 0.04, "wall": 0.006, "height": 0.035, "floor": 0.006, "max_edge": 0.012}
HOLDER_XY = np.array([0.45, 0.25])
BOTTLE_SCALE = 0.18  # the bottles' source meshes are normalised to about 1 tall: 18 cm bottles


def rot_x(deg):
    a = math.radians(deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def rot_z(deg):
    a = math.radians(deg)
    return np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])


def pose(rotation, translation) -> np.ndarray:
    t = np.eye(4)
    t[:3, :3], t[:3, 3] = rotation, translation
    return t


# the gripper's frame in link7's: z the approach, y the fingers' closing axis (toward the left finger), at the pads
LINK7_GRIPPER = pose(rot_z(-45.0), [0.0, 0.0, TCP])


# --------------------------------------------------------------------------- the model and inverse kinematics


def panda_model():
    """(MjModel, MjData) of scenes/panda.xml (the robot and the table, no object)."""
    import mujoco

    from zoo.sim.model import new_spec

    model = new_spec(SCENES / PANDA_XML).compile()
    return model, mujoco.MjData(model)


def gripper_pose(model, data, q) -> np.ndarray:
    import mujoco

    data.qpos[:7] = q
    mujoco.mj_kinematics(model, data)
    link7 = model.body("panda0_link7").id
    return pose(data.xmat[link7].reshape(3, 3), data.xpos[link7]) @ LINK7_GRIPPER


def ik(model, data, target: np.ndarray, seed: np.ndarray, iters: int = 500, tol: float = 2e-4) -> np.ndarray:
    """Joint angles (7,) that put the gripper frame at ``target`` (4x4): damped least squares on the position and
    rotation error of the gripper frame, joint limits clipped, a weak pull toward ``seed`` in the null space.
    Raises RuntimeError when it does not converge (the pose is out of reach)."""
    import mujoco
    from scipy.spatial.transform import Rotation

    lo, hi = model.jnt_range[:7, 0], model.jnt_range[:7, 1]
    q = np.array(seed, dtype=np.float64)
    link7 = model.body("panda0_link7").id
    jacp, jacr = np.zeros((3, model.nv)), np.zeros((3, model.nv))
    for _ in range(iters):
        g = gripper_pose(model, data, q)
        err = np.concatenate([target[:3, 3] - g[:3, 3], Rotation.from_matrix(target[:3, :3] @ g[:3, :3].T).as_rotvec()])
        if np.linalg.norm(err[:3]) < tol and np.linalg.norm(err[3:]) < 15 * tol:
            return q
        mujoco.mj_comPos(model, data)
        mujoco.mj_jac(model, data, jacp, jacr, g[:3, 3], link7)
        jac = np.vstack([jacp[:, :7], jacr[:, :7]])
        lam = 1e-2
        pinv = jac.T @ np.linalg.inv(jac @ jac.T + lam**2 * np.eye(6))
        dq = pinv @ err + 0.05 * (np.eye(7) - pinv @ jac) @ (seed - q)
        q = np.clip(q + np.clip(dq, -0.2, 0.2), lo, hi)
    raise RuntimeError(f"IK did not reach the gripper pose at {target[:3, 3].round(3).tolist()}: "
                       f"position error {np.linalg.norm(err[:3]):.3g} m, rotation error {np.linalg.norm(err[3:]):.3g} rad")


def gravity_ctrl(model, data, q) -> np.ndarray:
    """Position targets (7,) that hold the arm at ``q``: q plus the gravity torque there over each actuator's kp."""
    import mujoco

    data.qpos[:7], data.qvel[:] = q, 0.0
    data.qpos[7:9] = OPEN
    mujoco.mj_forward(model, data)
    kp = model.actuator_gainprm[:7, 0]
    return q + data.qfrc_bias[:7] / kp


# --------------------------------------------------------------------------- plans


@dataclass
class Keyframe:
    """The gripper at ``pose`` (4x4, world) at ``time`` (s), fingers at ``fingers``; ``straight``: the way from the
    previous keyframe is a straight line (sampled every ``step`` m), else joint-space."""
    time: float
    pose: np.ndarray
    fingers: float
    straight: bool = True


@dataclass
class Plan:
    name: str
    comment: str
    body: dict
    extra_bodies: list = field(default_factory=list)
    keyframes: list = field(default_factory=list)
    seconds: float = 0.0
    check: dict = field(default_factory=dict)
    camera: str = "front"  # scenes/panda.xml's camera the video is rendered from


def interpolate(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    from scipy.spatial.transform import Rotation, Slerp

    rots = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a[:3, :3], b[:3, :3]])))
    return pose(rots([s]).as_matrix()[0], (1 - s) * a[:3, 3] + s * b[:3, 3])


def waypoints(plan: Plan, model, data, step: float = 0.02) -> tuple[list[dict], np.ndarray]:
    """The plan's keyframes as [[control]] entries (arm and finger actuators) and the initial joint angles."""
    q = ik(model, data, plan.keyframes[0].pose, HOME)
    q0 = q.copy()
    entries = []

    def add(t, qk, fingers):
        ctrl = dict(zip(ARM_ACTUATORS, (round(float(v), 5) for v in gravity_ctrl(model, data, qk))))
        ctrl.update({f: fingers for f in FINGERS})
        entries.append({"time": round(float(t), 4), "ctrl": ctrl})

    add(0.0, q, plan.keyframes[0].fingers)
    prev = plan.keyframes[0]
    for key in plan.keyframes[1:]:
        n = 1
        if key.straight:
            rot = np.linalg.norm(_rotvec(prev.pose[:3, :3].T @ key.pose[:3, :3]))
            n = max(1, int(math.ceil(max(np.linalg.norm(key.pose[:3, 3] - prev.pose[:3, 3]) / step, rot / 0.15))))
        for i in range(1, n + 1):
            s = i / n
            q = ik(model, data, interpolate(prev.pose, key.pose, s), q)
            add(prev.time + s * (key.time - prev.time), q, key.fingers if i == n else prev.fingers)
        prev = key
    return entries, q0


def _rotvec(r):
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(r).as_rotvec()


# --------------------------------------------------------------------------- objects, searched on their SDFs


def load_sdf(spec: dict):
    """The object's SDF as the scene file builds it (model shape or saved codes, scaled)."""
    from zoo.scenes import build_sdf

    return build_sdf(spec, SCENES)[0]


def _values(sdf, points: np.ndarray) -> np.ndarray:
    import torch

    with torch.no_grad():
        return np.asarray(sdf(torch.as_tensor(points, dtype=torch.float32))).reshape(-1)


def bottom_height(sdf, x: float = 0.0, y: float = 0.0, step: float = 5e-4) -> float:
    """The lowest surface point on the vertical line through (x, y) (object frame), from below."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in sdf.bounds)
    z = np.arange(lo[2], hi[2], step)
    inside = np.nonzero(_values(sdf, np.stack([np.full_like(z, x), np.full_like(z, y), z], 1)) <= 0)[0]
    if not inside.size:
        raise RuntimeError("no surface on the object's vertical axis")
    return float(z[inside[0]])


def mug_grasp(sdf, to_handle: np.ndarray, depth: float = 0.012, res: float = 5e-4) -> tuple[np.ndarray, dict]:
    """A top-down grasp of the mug's rim on the side opposite its handle, searched on its SDF: in the vertical plane
    through the axis and away from the handle, the rim's top and the wall's inner and outer faces ``depth`` below it;
    the gripper's pads straddle the wall there, closing along the radius. Returns (gripper pose in the mug's frame
    (4x4), the numbers found)."""
    u = -np.array([to_handle[0], to_handle[1], 0.0])
    u /= np.linalg.norm(u)
    r = np.arange(0.0, 0.09, res)
    z = np.arange(-0.08, 0.08, res)
    rr, zz = np.meshgrid(r, z, indexing="ij")
    points = np.stack([rr * u[0], rr * u[1], zz], -1).reshape(-1, 3)
    inside = (_values(sdf, points) <= 0).reshape(rr.shape)
    outer = inside & (rr > 0.02)
    rim = float(zz[outer].max())
    row = np.argmin(np.abs(z - (rim - depth)))
    wall = r[outer[:, row]]
    inner, outer_r = float(wall.min()), float(wall.max())
    closing = u  # the gripper's y: toward the left finger, along the radius
    approach = np.array([0.0, 0.0, -1.0])
    grasp = pose(np.column_stack([np.cross(closing, approach), closing, approach]),
                 0.5 * (inner + outer_r) * u + np.array([0.0, 0.0, rim - depth]))
    return grasp, {"rim_z": rim, "wall_inner_r": inner, "wall_outer_r": outer_r}


def mug_hang(sdf, along: float = 0.10):
    """(mug pose on the peg in the rack's frame (4x4), handle hole (contact, to_handle, axis, size)): the handle's hole
    threaded on the peg ``along`` (m) from its root, the handle square to the peg, searched on the SDF
    (benches.demo.hanging_pose)."""
    from .demo import handle_hole, hanging_pose

    hang, _ = hanging_pose(sdf, PEG_START, PEG_DIR, PEG_RADIUS, along=along)
    return hang, handle_hole(sdf)


def mug_rest(sdf_spec: dict, hang_rack: np.ndarray, mass: float = 0.25, seconds: float = 3.0,
             damping: float = 0.02) -> np.ndarray:
    """Where the mug comes to rest on the peg (its pose in the rack's frame, 4x4): let go at ``hang_rack`` on the rack
    alone, simulated with sdfzoo's contacts, its swing damped (``damping``, N m s/rad on its free joint's rotations,
    about critical for a mug swinging from its handle). :func:`mug_hang`'s pose holds the handle square to the peg;
    a mug hangs with its centre of mass under the handle's contact, so it swings on release from there."""
    from zoo.scenes import pose_matrix
    from zoo.sim.scene import scene_simulation

    rack = pose_matrix(RACK_POSE)
    spec = {"name": "mug-rest", "method": "amortized", "margin": 0.001,
            "sim": {"dt": 0.004, "cone": "elliptic", "impratio": 10.0},  # scenes/panda.xml's options
            "bodies": [{"name": "mug", "sdf": sdf_spec, "mass": mass, "joint": "free", "pose": (rack @ hang_rack).tolist()},
                       {"name": "rack", "mesh": {"file": "rack/ndf_simple_rack.obj"}, "joint": "fixed", "pose": RACK_POSE}]}
    sim = scene_simulation(spec, base_dir=SCENES)
    sim.build()
    dof = sim.model.jnt_dofadr[sim.model.body_jntadr[sim.model.body("mug").id]]
    sim.model.dof_damping[dof + 3:dof + 6] = damping
    sim.run(seconds)
    speed = float(np.abs(sim.velocity("mug")).max())
    if speed > 0.01:
        raise RuntimeError(f"the mug did not come to rest on the peg in {seconds} s (moving at {speed:.3g})")
    return np.linalg.inv(rack) @ sim.pose("mug")


def mug_plan(name: str, sdf_spec: dict, label: str, mass: float = 0.25, closed: float = MUG_CLOSED,
             settle: float = 0.4) -> Plan:
    """The mug's plan: grasp the rim, carry, thread the handle's hole on the peg square to it (the peg rises at 50
    degrees: too steep for the mug to stay where it is let go), slide down towards the root while turning the mug into
    the pose it rests in there (:func:`mug_rest`), release it 3 mm above that pose and withdraw. ``settle`` (s): the
    hand holds the release pose that long before the fingers open (the position-controlled arm lags its targets)."""
    from zoo.scenes import pose_matrix

    sdf = load_sdf(sdf_spec)
    square_rack, (contact, to_handle, axis, size) = mug_hang(sdf, along=0.10)
    rack = pose_matrix(RACK_POSE)
    square = rack @ square_rack
    rest = rack @ mug_rest(sdf_spec, mug_hang(sdf, along=0.04)[0], mass)
    grasp, found = mug_grasp(sdf, to_handle)
    # the mug stands on the table turned so that the carry turns it least
    best = min(range(0, 360, 5), key=lambda a: np.linalg.norm(_rotvec(rest[:3, :3] @ rot_z(a).T)))
    stand = pose(rot_z(best), [0.42, -0.12, -bottom_height(sdf) + 5e-4])
    g_pick = stand @ grasp
    # along the peg the handle's hole is centred on it (the clearance is what the arm's tracking error may take);
    # the mug is let go 3 mm above resting, its hole's top over the peg
    centre = 0.5 * size[0] - PEG_RADIUS
    g_square = pose(square[:3, :3], square[:3, 3] + centre * (square[:3, :3] @ to_handle)) @ grasp
    g_release = pose(rest[:3, :3], rest[:3, 3] + [0.0, 0.0, 0.003]) @ grasp
    d = rack[:3, :3] @ (PEG_DIR / np.linalg.norm(PEG_DIR))
    g_prehang = pose(g_square[:3, :3], g_square[:3, 3] + 0.09 * d)  # the hole beyond the peg's tip
    up = lambda g, h: pose(g[:3, :3], g[:3, 3] + [0.0, 0.0, h])  # noqa: E731
    back = lambda g, h: pose(g[:3, :3], g[:3, 3] - h * g[:3, 2])  # noqa: E731
    s = settle
    keys = [
        Keyframe(0.0, up(g_pick, 0.10), OPEN), Keyframe(0.6, g_pick, OPEN), Keyframe(1.0, g_pick, closed),
        Keyframe(1.3, g_pick, closed), Keyframe(1.9, up(g_pick, 0.18), closed),
        Keyframe(3.4, g_prehang, closed), Keyframe(4.4, g_square, closed), Keyframe(4.7, g_square, closed),
        Keyframe(5.7, g_release, closed), Keyframe(5.7 + s, g_release, closed), Keyframe(6.1 + s, g_release, OPEN),
        Keyframe(6.3 + s, g_release, OPEN), Keyframe(6.8 + s, back(g_release, 0.10), OPEN),
    ]
    tilt = np.degrees(np.linalg.norm(_rotvec(square[:3, :3].T @ rest[:3, :3])))
    comment = (f"A Franka Panda hangs {label} on the NDF rack's peg. Grasp: top-down on the rim opposite the handle, "
               f"found on the SDF (rim at z = {found['rim_z']:.4f}, wall from r = {found['wall_inner_r']:.4f} to "
               f"{found['wall_outer_r']:.4f} in the mug's frame). Hang: the handle's hole (found on the SDF, "
               "benches.demo.hanging_pose) threaded square to the peg and centred on it 0.10 m up it, then slid down towards the root "
               f"while the mug turns {tilt:.0f} degrees into the pose it rests in there (found by simulating the mug "
               "alone on the rack, its swing damped: panda_scenarios.mug_rest), released 3 mm above that pose; the "
               f"hand holds there {s:.1f} s, the fingers (closed at {closed} m) open at {5.7 + s:.1f}-{6.1 + s:.1f} s "
               "and withdraw; the check is 1 s after the release.")
    return Plan(name=name, comment=comment,
                body={"name": "mug", "sdf": sdf_spec, "mass": mass, "joint": "free", "pose": stand.tolist()},
                extra_bodies=[{"name": "rack", "mesh": {"file": "rack/ndf_simple_rack.obj"}, "joint": "fixed",
                               "pose": RACK_POSE}],
                keyframes=keys, seconds=7.1 + s, camera="rack",  # from beside the rack: the hang is behind the post from the front
                check={"kind": "mug-on-peg", "release_time": 6.1 + s})


def bottle_plan(name: str, sdf_spec: dict, label: str, mass: float = 0.3) -> Plan:
    sdf = load_sdf(sdf_spec)
    bottom = bottom_height(sdf)
    stand = pose(np.eye(3), [0.45, -0.15, -bottom + 5e-4])
    grip_height = 0.07  # above the bottle's bottom: on its body, the fingers clear of the holder's rim
    # a side grasp: the hand comes level from the robot's side, the fingers close across the body
    approach = np.array([stand[0, 3], stand[1, 3], 0.0]) / np.hypot(stand[0, 3], stand[1, 3])
    closing = np.cross([0.0, 0.0, 1.0], approach)
    grasp = pose(np.column_stack([np.cross(closing, approach), closing, approach]), [0.0, 0.0, bottom + grip_height])
    g_pick = stand @ grasp
    floor_top = HOLDER["floor"]
    place = pose(np.eye(3), [HOLDER_XY[0], HOLDER_XY[1], floor_top - bottom + 0.004]) @ grasp
    up = lambda g, h: pose(g[:3, :3], g[:3, 3] + [0.0, 0.0, h])  # noqa: E731
    back = lambda g, h: pose(g[:3, :3], g[:3, 3] - h * g[:3, 2])  # noqa: E731
    keys = [
        Keyframe(0.0, back(g_pick, 0.10), OPEN), Keyframe(0.6, g_pick, OPEN), Keyframe(1.0, g_pick, CLOSED),
        Keyframe(1.2, g_pick, CLOSED), Keyframe(1.6, up(g_pick, 0.08), CLOSED),
        Keyframe(2.5, up(place, 0.06), CLOSED), Keyframe(3.0, place, CLOSED), Keyframe(3.4, place, OPEN),
        Keyframe(3.5, place, OPEN), Keyframe(3.9, back(place, 0.10), OPEN),
    ]
    comment = (f"A Franka Panda places {label} upright in a holder. Grasp: from the side, the fingers across the "
               f"bottle's body {grip_height} m above its bottom (found on the SDF at z = {bottom:.4f} in its frame); "
               "lifted, carried over the holder, lowered to 4 mm above its floor, released at 3.0-3.4 s; the hand "
               "withdraws; the check is 1 s after the release.")
    return Plan(name=name, comment=comment,
                body={"name": "bottle", "sdf": sdf_spec, "mass": mass, "joint": "free", "pose": stand.tolist()},
                extra_bodies=[{"name": "holder", "mesh": {"procedural": "holder", "params": HOLDER}, "joint": "fixed",
                               "pose": {"translation": [HOLDER_XY[0], HOLDER_XY[1], HOLDER["floor"]]}}],
                keyframes=keys, seconds=4.4,
                check={"kind": "bottle-upright", "release_time": 3.4})


PLANS = {
    "panda-bottle-holder": lambda: bottle_plan(
        "panda-bottle-holder", {"model": "bottles", "shape": "bulletarm_bottle1", "scale": BOTTLE_SCALE},
        "the bottles model's bulletarm_bottle1 (a NeuralSDF, 18 cm tall: its source mesh is about 1 tall, scaled 0.18)"),
    "panda-bottle-holder-unseen": lambda: bottle_plan(
        "panda-bottle-holder-unseen", {"codes": "panda/bottle-bulletarm_bottle9.safetensors", "scale": BOTTLE_SCALE},
        "bulletarm_bottle9 of the bottles' test split (codes fitted by fit_codes, decoder frozen; scaled 0.18)"),
    "panda-mug-rack": lambda: mug_plan(
        "panda-mug-rack", {"model": "mugs", "shape": "hoi4d_mug_0001"},
        "the mugs model's hoi4d_mug_0001 (a NeuralSDF, metres)"),
    "panda-mug-rack-unseen": lambda: mug_plan(
        "panda-mug-rack-unseen", {"codes": "panda/mug-hoi4d_mug_0042.safetensors"},
        "hoi4d_mug_0042 of the mugs' test split (codes fitted by fit_codes, decoder frozen; metres)"),
}


# --------------------------------------------------------------------------- scene files


def _toml_value(v) -> str:
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + " }"
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) or isinstance(v, np.floating):
        return repr(round(float(v), 6))
    return str(v)


def _toml_key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def scene_text(plan: Plan, entries: list[dict], q0: np.ndarray) -> str:
    lines = [f"# {line}" for line in _wrap(plan.comment)]
    lines += [
        "# Planned by benches/panda_scenarios.py (damped least-squares IK on scenes/panda.xml, gravity feed-forward);",
        "# re-plan: ZOO_DATA=../shared/meshes python -m sdfzoo.benches.panda_scenarios --write. Check: tests/test_sim_panda.py.",
        f"name = {json.dumps(plan.name)}", 'method = "amortized"', "margin = 0.001", f"mjcf = {json.dumps(PANDA_XML)}", "",
        "[sim]", "dt = 0.004", f"seconds = {plan.seconds}", f'camera = "{plan.camera}"',
        "qpos = " + _toml_value({**dict(zip(ARM, (round(float(v), 5) for v in q0))),
                                 "robot:panda0_finger_joint1": OPEN, "robot:panda0_finger_joint2": OPEN}),
        "",
    ]
    for body in [plan.body, *plan.extra_bodies]:
        lines.append("[[bodies]]")
        for k, v in body.items():
            lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")
    for e in entries:
        lines += ["[[control]]", f"time = {e['time']}", f"ctrl = {_toml_value(e['ctrl'])}", ""]
    return "\n".join(lines)


def _wrap(text: str, width: int = 116) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width)


def write(name: str) -> Path:
    plan = PLANS[name]()
    model, data = panda_model()
    entries, q0 = waypoints(plan, model, data)
    path = SCENES / f"{name}.toml"
    path.write_text(scene_text(plan, entries, q0))
    return path


# --------------------------------------------------------------------------- runs and their checks

FINGER_BODIES = ("panda0_leftfinger", "panda0_rightfinger")


def _tilt_deg(rotation: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip(rotation[2, 2], -1.0, 1.0))))


def finger_contacts(sim, body: str) -> int:
    """Contacts of the last step between ``body`` and the Panda's fingers."""
    m, d = sim.model, sim.data
    b = m.body(body).id
    fingers = {m.body(f).id for f in FINGER_BODIES}
    pairs = ((m.geom_bodyid[d.contact.geom1[i]], m.geom_bodyid[d.contact.geom2[i]]) for i in range(d.ncon))
    return sum(1 for a, c in pairs if (a == b and c in fingers) or (c == b and a in fingers))


def run(name: str, seconds: float | None = None, video: Path | None = None, progress: bool = False) -> dict:
    """Run a Panda scene and check it (see :func:`check`); with ``video``, render an MP4 from its camera."""
    import zoo.sim

    path = SCENES / f"{name}.toml"
    sim = zoo.sim.load_scene(path)
    obj = "mug" if "mug" in name else "bottle"
    seconds = sim.seconds if seconds is None else seconds
    sim.build()
    recorder = None
    if video is not None:
        from zoo.sim.render import VideoRecorder

        recorder = VideoRecorder(sim.model, camera=sim.camera, width=640, height=480)
    trace = []
    steps = int(round(seconds / sim.dt))
    every = max(1, int(round(0.04 / sim.dt)))
    for i in range(steps):
        sim.step()
        if i % every == 0:
            trace.append({"time": sim.time, "pose": sim.pose(obj), "fingers": finger_contacts(sim, obj)})
            if recorder is not None:
                recorder.capture(sim.data)
            if progress:
                print(f"t={sim.time:.2f} {obj} at {sim.pose(obj)[:3, 3].round(3).tolist()} contacts {sim.log[-1].contacts} "
                      f"fingers {trace[-1]['fingers']} step {sim.log[-1].step_s * 1e3:.1f} ms", flush=True)
    if recorder is not None:
        recorder.write(video, fps=25)
    result = check(sim, name, trace)
    log = sim.log
    result.update(step_metrics(np.array([r.step_s for r in log]), np.array([r.contacts for r in log]),
                               np.array([r.max_penetration for r in log]), np.array([r.collide_s for r in log])))
    path = ("+proxy" if sim.proxy else "+coherence") if sim.coherence else ""
    result.update({"scene": name, "method": sim.method + path,
                   "seconds": sim.time, "warnings": sim.warnings[:10]})
    return result


def step_metrics(step_s: np.ndarray, contacts: np.ndarray, penetration: np.ndarray, collide_s: np.ndarray | None = None
                 ) -> dict:
    """A run's per-step figures from its steps' arrays (S,): time per step (s), the object's contacts, its deepest
    penetration (m) and the time spent finding contacts (s); in ``zoo bench --sim``'s keys."""
    from .sim_bench import percentiles

    def pct(x, scale):
        return {**percentiles(scale * np.asarray(x), (50, 90, 99)), "max": scale * float(np.max(x))}

    out = {"steps": int(len(step_s)), "wall_s": float(step_s.sum()), "steps_per_s": len(step_s) / float(step_s.sum()),
           "step_ms": pct(step_s, 1e3), "step_ms_mean": 1e3 * float(step_s.mean()),
           "contacts_per_step": float(contacts.mean()), "contacts_max": int(contacts.max()),
           "penetration_mm": pct(penetration, 1e3), "max_penetration_mm": 1e3 * float(penetration.max())}
    if collide_s is not None:
        out["collide_ms"] = pct(collide_s, 1e3)
    return out


def check(sim, name: str, trace: list[dict]) -> dict:
    """The scenario's verdict from the simulation's state: the object was lifted by the hand, is free of the fingers
    at the end, and (bottle) stands upright in the holder or (mug) hangs with its handle's hole round the peg."""
    obj = "mug" if "mug" in name else "bottle"
    start_z = trace[0]["pose"][2, 3]
    lifted = max(t["pose"][2, 3] for t in trace) - start_z
    final = sim.pose(obj)
    out = {"lifted_m": float(lifted), "finger_contacts_end": finger_contacts(sim, obj),
           "speed_end": float(np.linalg.norm(sim.velocity(obj)[:3]))}
    if obj == "bottle":
        holder = sim.pose("holder")
        out.update({"tilt_deg": _tilt_deg(final[:3, :3]),
                    "off_axis_m": float(np.linalg.norm(final[:2, 3] - holder[:2, 3])),
                    "height_m": float(final[2, 3] - holder[2, 3])})
        out["passed"] = bool(out["lifted_m"] > 0.05 and out["tilt_deg"] < 10.0 and out["off_axis_m"] < HOLDER["inner_radius"]
                             and out["finger_contacts_end"] == 0 and out["speed_end"] < 0.02)
    else:
        from .demo import handle_hole

        contact, to_handle, axis, size = handle_hole(sim.bodies["mug"].sdf)
        centre = final[:3, :3] @ (contact - 0.5 * size[0] * to_handle) + final[:3, 3]
        rack = sim.pose("rack")
        root, d = rack[:3, :3] @ PEG_START + rack[:3, 3], rack[:3, :3] @ (PEG_DIR / np.linalg.norm(PEG_DIR))
        along = float((centre - root) @ d)
        off = float(np.linalg.norm(centre - root - along * d))
        hole_axis = final[:3, :3] @ axis
        out.update({"hole_to_peg_axis_m": off, "hole_half_size_m": float(0.5 * size.min()), "along_peg_m": along,
                    "hole_axis_to_peg_deg": float(np.degrees(np.arccos(min(1.0, abs(float(hole_axis @ d)))))),
                    "mug_height_m": float(final[2, 3])})
        out["passed"] = bool(out["lifted_m"] > 0.05 and off < 0.5 * size.min() and 0.0 < along < 0.174
                             and out["finger_contacts_end"] == 0 and out["speed_end"] < 0.02)
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--write", action="store_true", help="(re)plan the scene files")
    parser.add_argument("--run", choices=sorted(PLANS), action="append", default=[])
    parser.add_argument("--seconds", type=float)
    parser.add_argument("--video", type=Path, help="a folder for the MP4s")
    parser.add_argument("--progress", action="store_true")
    args = parser.parse_args(argv)
    if args.video is not None:
        from zoo.offscreen import choose_gl

        choose_gl()  # before mujoco is first imported
    if args.write:
        for name in PLANS:
            print(write(name))
    for name in args.run:
        video = None if args.video is None else args.video / f"{name}.mp4"
        result = run(name, args.seconds, video, args.progress)
        print(json.dumps(result, indent=1, default=str))
        if not result["passed"]:
            sys.exit(1)


if __name__ == "__main__":
    main()
