"""zoo.sim.broad_phase (every pair of a World at once) against the per-pair reference it replaces: MuJoCo's own
``mj_objectVelocity`` for each body, and for each pair its margin, the balls' test (``Pair.apart``) and its relative
motion, on random states of a model with a plane, primitives on hinges and free bodies, and SDF bodies on both sides."""

from __future__ import annotations

import math

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from zoo.sim.broad_phase import SPECULATIVE_FACTOR, body_velocities  # noqa: E402
from zoo.sim.geoms import body_pose, body_velocity  # noqa: E402

XML = """<mujoco><option timestep="0.004"/><worldbody>
<geom name="floor" type="plane" size="1 1 0.1" pos="0 0 -0.2" euler="5 -3 0"/>
<body name="arm" pos="0.1 0 0.1"><joint type="hinge" axis="0 1 0"/><geom type="capsule" size="0.02 0.1" margin="0.003"/>
  <body name="hand" pos="0 0 0.12"><joint type="hinge" axis="1 0 0"/><geom type="box" size="0.03 0.02 0.04"/>
    <geom type="sphere" size="0.015" pos="0.03 0 0.05"/></body></body>
<body name="ball" pos="0 0.05 0"><freejoint/><geom type="sphere" size="0.04" contype="0" conaffinity="0" mass="0.3"/></body>
<body name="cube" pos="0 -0.1 0.05"><freejoint/><geom type="box" size="0.03 0.03 0.03" contype="0" conaffinity="0" mass="0.2"/></body>
<body name="far" pos="0.6 0.6 0.3"><freejoint/><geom type="ellipsoid" size="0.03 0.02 0.05" mass="0.1"/></body>
</worldbody></mujoco>"""


def reference_near(world, model, data):
    """Each pair as World._detect tested it one at a time: {pair index: (margin, speculative, shift, turn)}."""
    out = {}
    for index, pair in enumerate(world.pairs):
        a = body_velocity(model, data, pair.sdf_body.body)
        b = body_velocity(model, data, pair.body)
        xa, xb = data.xpos[pair.sdf_body.body], data.xpos[pair.body]
        reach = pair.sdf_body.reach
        lever = reach + math.dist(xa, xb)
        closing = (np.linalg.norm(a[:3] - b[:3]) + reach * np.linalg.norm(a[3:]) + lever * np.linalg.norm(b[3:])) * model.opt.timestep
        margin = max(world.margin, pair.params.margin)
        speculative = closing > margin
        if speculative:
            margin = SPECULATIVE_FACTOR * closing
        if pair.apart(body_pose(data, pair.sdf_body.body), pair.surface_pose(data), margin):
            continue
        shift = a[:3] - b[:3] - np.cross(a[3:], xa) + np.cross(b[3:], xb)
        out[index] = (margin, speculative, shift, a[3:] - b[3:], pair.surface_pose(data))
    return out


def test_body_velocities_are_mujocos_object_velocities():
    model = mujoco.MjModel.from_xml_string(XML)
    data = mujoco.MjData(model)
    rng = np.random.default_rng(0)
    for _ in range(5):
        data.qpos[:] = model.qpos0 + 0.3 * rng.normal(size=model.nq)
        data.qvel[:] = rng.normal(size=model.nv)
        mujoco.mj_forward(model, data)
        every = body_velocities(model, data)
        for body in range(model.nbody):
            np.testing.assert_allclose(every[body], body_velocity(model, data, body), atol=1e-12)


def test_the_near_pairs_are_those_the_per_pair_test_keeps():
    """On 40 random states (fast ones growing margins, bodies near and far), the pairs kept, their margins, whether
    they grew, their surfaces' poses and their relative motions are the per-pair reference's."""
    model = mujoco.MjModel.from_xml_string(XML)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(0.04), "cube": zoo.Box((0.03, 0.03, 0.03))}, method="fw")
    kinds = {pair.kind for pair in world.pairs}
    assert {"plane", "segment", "mesh"} <= kinds and len(world.pairs) >= 8
    rng = np.random.default_rng(1)
    seen, speculative = 0, 0
    for _ in range(40):
        data.qpos[:] = model.qpos0 + rng.normal(scale=0.15, size=model.nq)
        data.qvel[:] = rng.normal(scale=rng.choice([0.01, 3.0]), size=model.nv)
        mujoco.mj_forward(model, data)
        expected = reference_near(world, model, data)
        near = world._broad_phase.near(data)
        assert [world.pairs.index(p) for p in near.pairs] == sorted(expected)
        for i, pair in enumerate(near.pairs):
            margin, grown, shift, turn, pose = expected[world.pairs.index(pair)]
            assert near.margins[i] == pytest.approx(margin, rel=1e-12) and bool(near.speculative[i]) == grown
            np.testing.assert_allclose(near.surface_poses[i], pose, atol=1e-15)
            closing = near.closing(i)
            np.testing.assert_allclose(closing.shift, shift, atol=1e-12)
            np.testing.assert_allclose(closing.turn, turn, atol=1e-12)
        seen += len(near.pairs)
        speculative += int(near.speculative.sum())
    assert 20 < seen < 40 * len(world.pairs) / 2 and 0 < speculative < seen  # both kinds of margin met, pairs left out
