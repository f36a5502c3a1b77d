"""zoo.sim holding by friction: a box squeezed between two prescribed fingers and lifted, against MuJoCo's own contacts.

The gripper scene's slip (docs/sim-scenarios.md) is not in how contacts are added: MuJoCo's own
contacts put back through :func:`zoo.sim.contacts.add_contacts` step exactly as ``mj_step``, and
an analytic SDF box lifted by box-mesh fingers rises as far as MuJoCo's box does. (The slip came from
the prescribed fingers rotating within each step about their own centre of mass; see the scene.)
"""

from __future__ import annotations

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")
trimesh = pytest.importorskip("trimesh")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from benches.sim_scenarios import FINGERS, PHASES, SQUEEZE, _finger_offset, native_grip, native_grip_xml  # noqa: E402
from zoo.sim.contacts import ContactRows, add_contacts  # noqa: E402

DT = 0.002
STEPS = int(round(PHASES["carry"][1] / DT))
HALF = 0.04  # the box: 8 cm, 0.2 kg
FINGER_HALF = (0.01, 0.005, 0.02)  # each finger: 1 kg, pad centre 4.8 cm from the box's axis
PAD_Y = {"left_finger": (0.048, 0.045 - SQUEEZE), "right_finger": (-0.048, -0.045 + SQUEEZE)}  # finger centres: open, closed


def _prescribe(qpos, qvel, qadr: int, dadr: int, finger: str, t: float) -> None:
    """The finger's pose and velocity for the step ending at ``t`` (benches.sim_scenarios.native_grip's)."""
    a, b = PHASES["close"]
    close, offset, velocity = _finger_offset(t)
    y_open, y_closed = PAD_Y[finger]
    vel = velocity.copy()
    vel[1] = (y_closed - y_open) / (b - a) if a <= t < b else 0.0
    pos = np.array([0.0, y_open + close * (y_closed - y_open), 0.05]) + offset
    qpos[qadr:qadr + 7] = np.concatenate([pos - vel * DT, [1.0, 0.0, 0.0, 0.0]])
    qvel[dadr:dadr + 6] = np.concatenate([vel, np.zeros(3)])


def _native_box_z(readd: bool) -> np.ndarray:
    """The box's height at every step of the native grip; ``readd``: MuJoCo's contacts cleared after mj_step1
    and appended again by add_contacts, the constraint stage rebuilt as zoo.sim's step does, then mj_step2."""
    model = mujoco.MjModel.from_xml_string(native_grip_xml())
    data = mujoco.MjData(model)
    joints = {f: (model.jnt_qposadr[model.body(f).jntadr[0]], model.jnt_dofadr[model.body(f).jntadr[0]]) for f in FINGERS}
    for f in FINGERS:
        data.xfrc_applied[model.body(f).id, 2] = model.body_mass[model.body(f).id] * -model.opt.gravity[2]
    solimp = model.geom_solimp[0].tolist()
    heights = []
    for _ in range(STEPS):
        for f, (qadr, dadr) in joints.items():
            _prescribe(data.qpos, data.qvel, qadr, dadr, f, data.time + DT)
        if not readd:
            mujoco.mj_step(model, data)
        else:
            mujoco.mj_step1(model, data)
            n, c = data.ncon, data.contact
            rows = ContactRows(pos=c.pos[:n].copy(), dist=c.dist[:n].copy(), frame=c.frame[:n].copy(),
                               geom=np.stack([c.geom1[:n], c.geom2[:n]], axis=1).astype(np.int32))
            data.ncon = 0
            assert add_contacts(model, data, rows, 1.0, tuple(model.geom_solref[0]), solimp) == n
            mujoco.mj_makeConstraint(model, data)
            mujoco.mj_island(model, data)
            mujoco.mj_projectConstraint(model, data)
            mujoco.mj_referenceConstraint(model, data)
            mujoco.mj_step2(model, data)
        heights.append(float(data.qpos[2]))
    return np.array(heights)


def test_added_contacts_step_as_mujocos_own():
    """MuJoCo's contacts of a grip, put back by add_contacts: the same trajectory as mj_step (frame, dist,
    friction, mu, dim, solref, solimp and the rebuilt constraint stage all as MuJoCo's own)."""
    native, readded = _native_box_z(False), _native_box_z(True)
    assert native[-1] - native[0] > 0.008  # it was lifted
    np.testing.assert_allclose(readded, native, rtol=0, atol=1e-9)


def _box_mesh(half) -> tuple[np.ndarray, np.ndarray]:
    box = trimesh.creation.box(extents=2 * np.asarray(half))
    return np.asarray(box.vertices, dtype=np.float64), np.asarray(box.faces)


def _sdf_box_lifted_by_mesh_fingers(**friction_settings) -> tuple[float, float]:
    """(rise, shift) in mm of an 8 cm, 0.2 kg zoo.Box squeezed 1.5 mm by two 1 kg box-mesh fingers, lifted 1 cm
    and carried 1 cm with friction 1 (native_grip's motion), in zoo.sim."""
    sim = zoo.sim.Simulation(dt=DT, friction=1.0, solref=(0.01, 1.0), **friction_settings)
    pose = np.eye(4)
    pose[2, 3] = HALF + 5e-4
    sim.add_body("box", sdf=zoo.Box(half_extents=(HALF, HALF, HALF)), mass=0.2, inertia=np.full(3, 0.2 * (2 * HALF) ** 2 / 6), pose=pose)
    table = np.eye(4)
    table[2, 3] = -0.005
    sim.add_body("table", mesh=_box_mesh((0.3, 0.3, 0.005)), joint="fixed", pose=table)
    h = np.asarray(FINGER_HALF)
    inertia = np.array([h[1] ** 2 + h[2] ** 2, h[0] ** 2 + h[2] ** 2, h[0] ** 2 + h[1] ** 2]) / 3  # 1 kg box
    for finger in FINGERS:
        start = np.eye(4)
        start[:3, 3] = (0.0, PAD_Y[finger][0], 0.05)
        sim.add_body(finger, mesh=_box_mesh(FINGER_HALF), mass=1.0, inertia=inertia, pose=start)
    sim.build()
    m, d = sim.model, sim.data
    for finger in FINGERS:
        d.xfrc_applied[sim.bodies[finger].body_id, 2] = m.body_mass[sim.bodies[finger].body_id] * -m.opt.gravity[2]
    start = sim.pose("box")[:3, 3].copy()
    for _ in range(STEPS):
        for finger in FINGERS:
            body = sim.bodies[finger]
            _prescribe(d.qpos, d.qvel, body.qpos_adr, body.dof_adr, finger, sim.time + DT)
        sim.step()
    assert not sim.warnings, sim.warnings
    return 1e3 * (sim.pose("box")[2, 3] - start[2]), 1e3 * (sim.pose("box")[0, 3] - start[0])


def _slip(rise: float, shift: float) -> float:
    return float(np.hypot(rise - 10.0, shift - 10.0))


def test_sdf_box_lifted_by_mesh_fingers_rises_as_native():
    """Under MuJoCo's default friction (pyramidal cone, impratio 1) the box rises and moves within 0.5 mm of
    MuJoCo's own box (8.4 and 9.8 mm)."""
    rise, shift = _sdf_box_lifted_by_mesh_fingers()
    native = native_grip()
    assert abs(rise - native["mug_rise_mm"]) < 0.5, (rise, native)
    assert abs(shift - native["mug_shift_mm"]) < 0.5, (shift, native)


def test_grasping_friction_settings_reach_the_solver_and_hold_the_box_as_native():
    """MuJoCo's grasping settings (elliptic cone, impratio 10, as the gripper scene sets them) reach the solver
    through Simulation: the box slips less than under the defaults and stays within 0.5 mm of MuJoCo's own box
    under the same settings."""
    settings = {"cone": "elliptic", "impratio": 10.0}
    rise, shift = _sdf_box_lifted_by_mesh_fingers(**settings)
    native = native_grip(**settings)
    assert abs(rise - native["mug_rise_mm"]) < 0.5, (rise, native)
    assert abs(shift - native["mug_shift_mm"]) < 0.5, (shift, native)
    assert _slip(rise, shift) < _slip(*_sdf_box_lifted_by_mesh_fingers()) - 0.05
