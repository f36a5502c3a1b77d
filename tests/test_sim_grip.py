"""zoo.sim holding by friction in an MJCF gripper (scenes/gripper.xml), against MuJoCo's own contacts.

MuJoCo's own contacts of a grip, put back through :func:`zoo.sim.contacts.add_contacts` with the parameters
:func:`zoo.sim.geoms.mixed_parameters` computes, step exactly as ``mj_step``; and a ``zoo.Box`` attached to a
body and lifted by the gripper rises as far as MuJoCo's own box does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from zoo.sim.contacts import ContactRows, add_contacts  # noqa: E402
from zoo.sim.control import Waypoints  # noqa: E402
from zoo.sim.geoms import geom_parameters, mixed_parameters  # noqa: E402

GRIPPER = Path(__file__).resolve().parent.parent / "scenes" / "gripper.xml"
HALF = 0.04  # the box: 8 cm, 0.2 kg
SECONDS = 0.5
# close (the pads touch an 8 cm box at 0.017 and are driven 1 cm past), lift 2 cm, carry 1 cm
WAYPOINTS = [
    {"time": 0.0, "mocap": {"hand_target": [0.0, 0.0, 0.13]}, "ctrl": {"left": 0.0, "right": 0.0}},
    {"time": 0.04, "ctrl": {"left": 0.0, "right": 0.0}},
    {"time": 0.14, "mocap": {"hand_target": [0.0, 0.0, 0.13]}, "ctrl": {"left": 0.027, "right": 0.027}},
    {"time": 0.2, "mocap": {"hand_target": [0.0, 0.0, 0.13]}},
    {"time": 0.35, "mocap": {"hand_target": [0.0, 0.0, 0.15]}},
    {"time": 0.45, "mocap": {"hand_target": [0.01, 0.0, 0.15]}},
]


def _gripper_with_box(native: bool, **options):
    """(model, data) of scenes/gripper.xml with an 8 cm, 0.2 kg box on the table: a colliding box geom (``native``),
    or one MuJoCo does not collide (sdfzoo's SDF gets attached)."""
    spec = mujoco.MjSpec.from_file(str(GRIPPER))
    for key, value in options.items():
        setattr(spec.option, key, value)
    body = spec.worldbody.add_body(name="box", pos=[0.0, 0.0, HALF])
    body.add_freejoint()
    body.add_geom(name="box", type=mujoco.mjtGeom.mjGEOM_BOX, size=[HALF] * 3, mass=0.2,
                  contype=1 if native else 0, conaffinity=1 if native else 0)
    model = spec.compile()
    return model, mujoco.MjData(model)


def _run(model, data, step) -> np.ndarray:
    """The box's position (3,) after every step of the waypoints, each step taken by ``step(model, data)``."""
    waypoints = Waypoints(model, WAYPOINTS)
    box = model.body("box").id
    positions = []
    for _ in range(int(round(SECONDS / model.opt.timestep))):
        waypoints.apply(data, data.time)
        step(model, data)
        positions.append(data.xpos[box].copy())
    return np.array(positions)


def _readded(model, data) -> None:
    """mj_step, with MuJoCo's contacts cleared after mj_step1 and appended again through add_contacts with the
    parameters mixed_parameters computes for their geoms, the constraint stage rebuilt as zoo.sim does. MuJoCo's
    ``exclude`` flag is copied back: MuJoCo leaves out a contact at or beyond its margin (``dist >= includemargin``),
    while sdfzoo keeps a separated contact that the step can close (its speculative contacts, zoo.sim.contacts)."""
    mujoco.mj_step1(model, data)
    n, c = data.ncon, data.contact
    contacts = [(c.pos[i].copy(), c.dist[i], c.frame[i].copy(), c.geom1[i], c.geom2[i]) for i in range(n)]
    expected = [(c.dim[i], c.friction[i].copy(), c.solref[i].copy(), c.solimp[i].copy(), c.includemargin[i]) for i in range(n)]
    exclude = c.exclude[:n].copy()
    data.ncon = 0
    for (pos, dist, frame, g1, g2), (dim, friction, solref, solimp, includemargin) in zip(contacts, expected):
        params = mixed_parameters(model, geom_parameters(model, g1), geom_parameters(model, g2))
        assert params.condim == dim and np.allclose(params.friction, friction) and np.allclose(params.solref, solref)
        assert np.allclose(params.solimp, solimp) and params.margin - params.gap == pytest.approx(includemargin)
        rows = ContactRows(pos=pos[None], dist=np.array([dist]), frame=frame[None], geom=np.array([[g1, g2]], dtype=np.int32))
        assert add_contacts(model, data, rows, params) == 1
    data.contact.exclude[:n] = exclude
    mujoco.mj_makeConstraint(model, data)
    mujoco.mj_island(model, data)
    mujoco.mj_projectConstraint(model, data)
    mujoco.mj_referenceConstraint(model, data)
    mujoco.mj_step2(model, data)


def test_added_contacts_with_mixed_parameters_step_as_mujocos_own():
    """MuJoCo's contacts of the grip (pads, box, table: geoms of different solref, friction and priority mixed),
    put back by add_contacts with zoo.sim's own mixing of their geoms' parameters: the same trajectory as mj_step."""
    native = _run(*_gripper_with_box(True), mujoco.mj_step)
    readded = _run(*_gripper_with_box(True), _readded)
    assert native[-1, 2] - native[0, 2] > 0.015  # it was lifted
    np.testing.assert_allclose(readded, native, rtol=0, atol=1e-9)


def _sdf_box_run(**options) -> np.ndarray:
    model, data = _gripper_with_box(False, **options)
    world = zoo.sim.attach(model, {"box": zoo.Box(half_extents=(HALF, HALF, HALF))}, method="fw")
    return _run(model, data, lambda m, d: world.step(d))


@pytest.mark.parametrize("cone", ["pyramidal", "elliptic"])
def test_sdf_box_lifted_by_the_gripper_rises_as_native(cone):
    """The gripper lifts an attached zoo.Box 2 cm and carries it 1 cm as it does MuJoCo's own box, under MuJoCo's
    default cone and its grasping one: the end positions agree within 0.5 mm."""
    options = {"cone": getattr(mujoco.mjtCone, f"mjCONE_{cone.upper()}")}
    native = _run(*_gripper_with_box(True, **options), mujoco.mj_step)
    ours = _sdf_box_run(**options)
    assert native[-1, 2] - native[0, 2] > 0.015 and native[-1, 0] > 0.008
    np.testing.assert_allclose(ours[-1], native[-1], atol=5e-4)
