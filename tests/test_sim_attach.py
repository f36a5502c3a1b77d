"""zoo.sim.attach on MuJoCo models written here, as a user writes them: which geoms an SDF body meets (held against
MuJoCo's own collision filter), each primitive's surface, planes, SDF against SDF, errors, and the user's loop
(``world.step`` against ``mujoco.mj_step`` under ``world.hooked()``, RK4, a chained control callback, the managed
viewer's calls), ending with the grasp the design names: a gripper of primitives under a mocap-welded hand lifts
the mugs model's NeuralSDF mug off a plane."""

from __future__ import annotations

import numpy as np
import pytest

mujoco = pytest.importorskip("mujoco")

import zoo  # noqa: E402
import zoo.sim  # noqa: E402
from zoo.errors import InputError  # noqa: E402
from zoo.sim.geoms import geom_surface, partner_geoms  # noqa: E402

BALL = 0.05


def _ball_on(geom_xml: str, height: float, extra: str = "", timestep: float = 0.002, integrator: str = "implicitfast") -> str:
    """A model: ``geom_xml`` in the world and a free 5 cm ball body (visual sphere, not colliding) ``height`` above."""
    return f"""<mujoco><option timestep="{timestep}" integrator="{integrator}"/><worldbody>{geom_xml}
<body name="ball" pos="0 0 {height}"><freejoint/><geom type="sphere" size="{BALL}" contype="0" conaffinity="0" mass="0.5"/></body>
</worldbody>{extra}</mujoco>"""


def _settle(xml: str, seconds: float = 0.4, **options) -> tuple[np.ndarray, object]:
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw", **options)
    world.step(data, int(round(seconds / model.opt.timestep)))
    return data.qpos[:3].copy(), world


# -- what an SDF body meets ------------------------------------------------------------------------


FILTER_XML = """<mujoco><worldbody>
<geom name="floor" type="plane" size="1 1 0.1"/>
<geom name="visual_only" type="box" size="0.1 0.1 0.1" contype="0" conaffinity="0"/>
<geom name="other_group" type="box" size="0.1 0.1 0.1" contype="2" conaffinity="2"/>
<body name="probe"><freejoint/><geom name="probe_geom" type="sphere" size="0.3" contype="{contype}" conaffinity="{conaffinity}"/>
  <body name="child"><joint type="hinge"/><geom name="child_geom" type="sphere" size="0.1"/></body>
</body>
<body name="welded_to_world"><geom name="fixed_box" type="box" size="0.1 0.1 0.1"/></body>
<body name="excluded"><joint type="slide"/><geom name="excluded_geom" type="sphere" size="0.1"/></body>
<body name="free_a"><freejoint/><geom name="a1" type="capsule" size="0.05 0.1"/><geom name="a2" type="box" size="0.1 0.1 0.1"/></body>
<body name="free_b"><freejoint/><geom name="b1" type="cylinder" size="0.05 0.1" contype="2" conaffinity="1"/></body>
</worldbody><contact><exclude body1="probe" body2="excluded"/></contact></mujoco>"""


def _native_partners(model) -> set[str]:
    """The geoms MuJoCo's own collision pairs with ``probe_geom`` when everything overlaps at the origin."""
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    probe = model.geom("probe_geom").id
    names = set()
    for i in range(data.ncon):
        g1, g2 = int(data.contact.geom1[i]), int(data.contact.geom2[i])
        if probe in (g1, g2):
            names.add(model.geom(g2 if g1 == probe else g1).name)
    return names


@pytest.mark.parametrize("types", [(1, 1), (2, 2), (1, 0), (0, 2)])
def test_the_geoms_an_sdf_body_meets_are_those_mujocos_own_collision_pairs(types):
    """A colliding probe geom overlapping every other geom: MuJoCo's own contacts name exactly the geoms that
    partner_geoms gives for an SDF with the probe's contype and conaffinity (same body, weld and parent-child
    filters, contype/conaffinity both ways, <exclude>)."""
    model = mujoco.MjModel.from_xml_string(FILTER_XML.format(contype=types[0], conaffinity=types[1]))
    probe = model.body("probe").id
    ours = {model.geom(g).name for g in partner_geoms(model, probe, types, set(), set())}
    assert ours == _native_partners(model)
    assert "child_geom" not in ours and "excluded_geom" not in ours and "visual_only" not in ours


def test_an_attached_body_meets_its_parent_when_the_model_disables_that_filter():
    xml = FILTER_XML.format(contype=1, conaffinity=1).replace("<worldbody>", '<option><flag filterparent="disable"/></option><worldbody>')
    model = mujoco.MjModel.from_xml_string(xml)
    ours = {model.geom(g).name for g in partner_geoms(model, model.body("probe").id, (1, 1), set(), set())}
    assert "child_geom" in ours and ours == _native_partners(model)


@pytest.mark.parametrize("kind,size,radius", [("sphere", [0.03], None), ("capsule", [0.02, 0.05], None),
                                              ("cylinder", [0.02, 0.05], None), ("ellipsoid", [0.03, 0.02, 0.05], None)])
def test_tessellated_primitives_lie_within_the_tolerance_of_their_surface(kind, size, radius):
    """Every vertex on the primitive's surface, and every face centre within the tolerance inside it (the sag)."""
    tolerance = 1e-4
    model = mujoco.MjModel.from_xml_string(f'<mujoco><worldbody><geom type="{kind}" size="{" ".join(map(str, size))}"/></worldbody></mujoco>')
    vertices, faces = geom_surface(model, 0, tolerance)
    centres = vertices[faces].mean(axis=1)

    def exact(points):  # the primitive's signed distance (the ellipsoid's normalised by its smallest radius: a bound)
        if kind == "sphere":
            return np.linalg.norm(points, axis=1) - size[0]
        if kind == "capsule":
            z = np.clip(points[:, 2], -size[1], size[1])
            return np.linalg.norm(points - np.stack([0 * z, 0 * z, z], axis=1), axis=1) - size[0]
        if kind == "cylinder":
            d = np.stack([np.hypot(points[:, 0], points[:, 1]) - size[0], np.abs(points[:, 2]) - size[1]], axis=1)
            return np.minimum(d.max(axis=1), 0) + np.linalg.norm(np.maximum(d, 0), axis=1)
        return (np.linalg.norm(points / np.asarray(size), axis=1) - 1) * min(size)

    assert np.abs(exact(vertices)).max() < 1e-9
    assert exact(centres).min() > -1.5 * tolerance


def test_a_box_geom_is_its_twelve_exact_triangles():
    model = mujoco.MjModel.from_xml_string('<mujoco><worldbody><geom type="box" size="0.1 0.2 0.3"/></worldbody></mujoco>')
    vertices, faces = geom_surface(model, 0, 1e-4)
    assert len(faces) == 12 and np.allclose(np.abs(vertices), [0.1, 0.2, 0.3])


@pytest.mark.parametrize("geom,top", [
    ('<geom type="plane" size="0.5 0.5 0.1"/>', 0.0),
    ('<geom type="box" size="0.2 0.2 0.02" pos="0 0 0.02"/>', 0.04),  # two triangles a face, far larger than the ball
    ('<geom type="cylinder" size="0.2 0.02" pos="0 0 0.02"/>', 0.04),
    ('<geom type="capsule" size="0.03 0.2" pos="0 0 0.03" euler="0 90 0"/>', 0.06),
    ('<geom type="sphere" size="0.3" pos="0 0 -0.26"/>', 0.04),
    ('<geom type="ellipsoid" size="0.3 0.3 0.02" pos="0 0 0.02"/>', 0.04),
])
def test_a_ball_comes_to_rest_on_every_kind_of_geom(geom, top):
    """The ball dropped 1 cm onto each primitive rests with its centre one radius above the geom's top, within the
    soft contact's sink (under 1 mm at MuJoCo's default solref) and the tessellation's tolerance."""
    position, world = _settle(_ball_on(geom, top + BALL + 0.01))
    assert position[2] == pytest.approx(top + BALL, abs=1e-3)
    assert abs(position[0]) < 1e-3 and abs(position[1]) < 1e-3
    assert world.stats.contacts >= 1 and len(world.contacts) == world.stats.contacts


def test_a_plane_is_infinite():
    """A plane of size 0.1 still holds a ball 50 m away from its origin (MuJoCo's planes are infinite)."""
    xml = _ball_on('<geom type="plane" size="0.1 0.1 0.1"/>', BALL + 0.005).replace('pos="0 0', 'pos="50 -30')
    position, _ = _settle(xml, seconds=0.2)
    assert position[2] == pytest.approx(BALL, abs=1e-3)


def test_an_sdf_body_rests_on_another_through_its_extracted_surface():
    """A ball on a fixed SDF ball: one side's SDF against the other's marching-cubes surface; it rests at the sum of
    the radii within the surface's grid error and the contact's sink."""
    xml = _ball_on('<body name="base" pos="0 0 0"><geom type="sphere" size="0.08" contype="0" conaffinity="0"/></body>', 0.08 + BALL + 0.005)
    model = mujoco.MjModel.from_xml_string(xml.replace("<option", '<option gravity="0 0 -9.81"'))
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL), "base": zoo.Sphere(radius=0.08)}, method="fw")
    assert [(p.sdf_body.name, p.frame) for p in world.pairs] == [("ball", "body")]
    world.step(data, 150)
    assert data.qpos[2] == pytest.approx(0.08 + BALL, abs=1.5e-3)


def test_bad_attachments_raise_typed_errors():
    model = mujoco.MjModel.from_xml_string(_ball_on('<geom type="plane" size="1 1 0.1"/>', 0.1).replace(
        "</worldbody>", '<body name="empty" pos="1 0 0"/><body name="solid"><geom type="box" size="0.1 0.1 0.1"/></body></worldbody>'))
    with pytest.raises(InputError, match="no body named"):
        zoo.sim.attach(model, {"missing": zoo.Sphere(radius=0.1)})
    with pytest.raises(InputError, match="has no geom"):
        zoo.sim.attach(model, {"empty": zoo.Sphere(radius=0.1)})
    with pytest.raises(InputError, match="still collide"):
        zoo.sim.attach(model, {"solid": zoo.Sphere(radius=0.1)})
    with pytest.raises(InputError, match="MjModel"):
        zoo.sim.attach("scene.xml", {"ball": zoo.Sphere(radius=0.1)})


def test_empty_pairs_and_disabled_contacts_step_with_no_contacts():
    xml = _ball_on("", 1.0)  # nothing to touch
    position, world = _settle(xml, seconds=0.1)
    assert world.pairs == [] and len(world.contacts) == 0 and position[2] < 1.0
    disabled = _ball_on('<geom type="plane" size="1 1 0.1"/>', 0.06).replace("<option", '<option><flag contact="disable"/></option><option')
    position, world = _settle(disabled, seconds=0.2)
    assert world.pairs == [] and position[2] < 0.0  # fell through: the model disables contacts


def test_contact_parameters_come_from_the_geoms():
    """The ball's contacts carry MuJoCo's mix of its geom's and the floor's parameters: a higher-priority floor's."""
    floor = '<geom type="plane" size="1 1 0.1" friction="0.3 0.01 0.001" solref="0.005 0.8" priority="1" condim="4"/>'
    model = mujoco.MjModel.from_xml_string(_ball_on(floor, BALL))
    data = mujoco.MjData(model)
    zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw").step(data)
    assert data.ncon >= 1
    contact = data.contact[0]
    assert contact.dim == 4 and np.allclose(contact.friction, [0.3, 0.3, 0.01, 0.001, 0.001])
    assert np.allclose(contact.solref, [0.005, 0.8])


# -- the user's loop -------------------------------------------------------------------------------


def _trajectory(xml: str, steps: int, hooked: bool, calls=None) -> np.ndarray:
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw")
    out = []
    if hooked:
        with world.hooked():
            for i in range(steps):
                (calls or (lambda m, d, i: mujoco.mj_step(m, d)))(model, data, i)
                out.append(np.concatenate([data.qpos, data.qvel]))
    else:
        for _ in range(steps):
            world.step(data)
            out.append(np.concatenate([data.qpos, data.qvel]))
    return np.array(out)


BOUNCE = _ball_on('<geom type="plane" size="1 1 0.1"/><geom type="box" size="0.05 0.05 0.05" pos="0.08 0 0.02" euler="10 20 30"/>', 0.12)


@pytest.mark.parametrize("integrator", ["implicitfast", "Euler"])
def test_hooked_mj_step_follows_world_step_exactly(integrator):
    xml = BOUNCE.replace('integrator="implicitfast"', f'integrator="{integrator}"')
    stepped, hooked = _trajectory(xml, 200, False), _trajectory(xml, 200, True)
    assert stepped[-1, 2] < 0.1  # it fell and met the box and the floor
    np.testing.assert_array_equal(hooked, stepped)


def test_rk4_gets_the_contacts_at_every_stage():
    """RK4 (MuJoCo integrates it through mj_forward four times a step) holds the ball on the floor, and world.step
    and the hook agree."""
    xml = _ball_on('<geom type="plane" size="1 1 0.1"/>', BALL + 0.01, integrator="RK4", timestep=0.001)
    stepped, hooked = _trajectory(xml, 300, False), _trajectory(xml, 300, True)
    assert stepped[-1, 2] == pytest.approx(BALL, abs=1e-3)
    np.testing.assert_array_equal(hooked, stepped)


def test_the_hook_chains_the_users_control_callback_and_restores_it():
    model = mujoco.MjModel.from_xml_string(_ball_on('<geom type="plane" size="1 1 0.1"/>', BALL))
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw")
    calls = []

    def user(m, d):
        calls.append(d.time)
        d.qfrc_applied[0] = 1.0  # the user's own control still acts

    mujoco.set_mjcb_control(user)
    try:
        with world.hooked():
            for _ in range(10):
                mujoco.mj_step(model, data)
            assert data.ncon >= 1  # sdfzoo's contact with the floor
        assert mujoco.get_mjcb_control() is user
    finally:
        mujoco.set_mjcb_control(None)
    assert len(calls) == 10 and data.qvel[0] > 0


def test_other_models_step_untouched_under_the_hook():
    """The hook is MuJoCo's global callback: a second model stepped inside it gets no sdfzoo contacts."""
    xml = _ball_on('<geom type="plane" size="1 1 0.1"/>', BALL + 0.01)
    model, other = mujoco.MjModel.from_xml_string(xml), mujoco.MjModel.from_xml_string(xml)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw")
    other_data = mujoco.MjData(other)
    with world.hooked():
        for _ in range(100):
            mujoco.mj_step(other, other_data)
    assert other_data.qpos[2] < 0  # fell through its floor: nothing added to it


def test_the_managed_viewers_calls_keep_the_trajectory():
    """The managed viewer forwards the model when it starts and while paused, and steps it otherwise: extra
    mj_forward calls at a standing state leave the trajectory as world.step gives it."""
    def viewer(m, d, i):
        if i == 0 or 50 <= i < 55:
            for _ in range(3):
                mujoco.mj_forward(m, d)  # paused frames: no time passes
        mujoco.mj_step(m, d)

    stepped, hooked = _trajectory(BOUNCE, 120, False), _trajectory(BOUNCE, 120, True, calls=viewer)
    np.testing.assert_allclose(hooked, stepped, rtol=0, atol=1e-9)


# -- the grasp ------------------------------------------------------------------------------------

GRASP_XML = """<mujoco><option timestep="0.002" cone="elliptic" impratio="10"/>
<default><geom solref="0.01 1"/></default>
<worldbody>
  <geom name="ground" type="plane" size="0.5 0.5 0.01"/>
  <body name="target" mocap="true" pos="0 0 0.13"/>
  <body name="hand" pos="0 0 0.13" gravcomp="1"><freejoint/>
    <geom type="box" size="0.015 0.075 0.008" mass="0.4"/>
    <body name="finger_a" pos="0 0.065 -0.03" gravcomp="1">
      <joint name="a" type="slide" axis="0 -1 0" range="0 0.04" damping="20"/>
      <geom name="pad_a" type="box" size="0.012 0.004 0.03" pos="0 0 -0.04" mass="0.05"/>
      <geom type="capsule" size="0.004 0.02" pos="0 0.002 -0.005" mass="0.01"/>
    </body>
    <body name="finger_b" pos="0 -0.065 -0.03" gravcomp="1">
      <joint name="b" type="slide" axis="0 1 0" range="0 0.04" damping="20"/>
      <geom name="pad_b" type="box" size="0.012 0.004 0.03" pos="0 0 -0.04" mass="0.05"/>
      <geom type="capsule" size="0.004 0.02" pos="0 -0.002 -0.005" mass="0.01"/>
    </body>
  </body>
  <body name="mug" pos="0 0 0.0446"><freejoint/>
    <geom name="mug_visual" type="cylinder" size="0.04 0.045" contype="0" conaffinity="0" mass="0.2"/>
  </body>
</worldbody>
<equality><weld body1="hand" body2="target" solref="0.005 1"/></equality>
<actuator><position name="a" joint="a" kp="600"/><position name="b" joint="b" kp="600"/></actuator>
</mujoco>"""


def _grasp(hooked: bool, shape, steps: int = 250, proxy=True) -> dict:
    """The grasp driven by hand-written targets: close over 40-140 ms, lift 3 cm over 200-400 ms."""
    model = mujoco.MjModel.from_xml_string(GRASP_XML)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"mug": shape}, proxy=proxy)
    mug, hand = model.body("mug").id, model.body("hand").id
    trace = []

    def control(t):
        data.ctrl[:] = 0.03 * np.clip((t - 0.04) / 0.1, 0.0, 1.0)  # the pads touch at ~0.018: squeezed 1.2 cm past
        data.mocap_pos[0, 2] = 0.13 + 0.03 * np.clip((t - 0.2) / 0.2, 0.0, 1.0)

    def record():
        touched = {model.geom(int(g)).name for g in world.contact_geoms[:, 1]}
        trace.append({"t": data.time, "mug": data.xpos[mug].copy(), "hand": data.xpos[hand].copy(), "touched": touched,
                      "state": np.concatenate([data.qpos, data.qvel])})

    if hooked:
        with world.hooked():
            for _ in range(steps):
                control(data.time)
                mujoco.mj_step(model, data)
                record()
    else:
        for _ in range(steps):
            control(data.time)
            world.step(data)
            record()
    return {"trace": trace, "start": trace[0]["mug"], "bake_seconds": world.bake_seconds,
            "lazy_bricks": world.proxies["mug"].lazy_bricks}


@pytest.mark.slow  # 2 x 250 steps of the NeuralSDF mug against a plane and two pads: 30-90 s on 2 shared cores
def test_a_gripper_of_primitives_lifts_the_neuralsdf_mug_the_same_through_step_and_hook():
    """The design's check: the mugs model's hoi4d_mug_0001 attached by body name to a user's MJCF (a plane, a hand of
    boxes and capsules welded to a mocap target, two slide fingers under position actuators). It rests on the plane,
    the fingers close on it, and it rises with the hand touching both pads; world.step and plain mj_step inside
    world.hooked() give identical runs."""
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    stepped, hooked = _grasp(False, shape), _grasp(True, shape)
    assert hooked["lazy_bricks"] == 0  # the proxy baked ahead at attach: no step bakes
    trace = stepped["trace"]
    resting = [r for r in trace if r["t"] < 0.04]
    assert all("ground" in r["touched"] for r in resting[2:])  # released at its resting height: touching from step 2
    assert max(np.linalg.norm(r["mug"] - stepped["start"]) for r in resting) < 2e-3  # settles into MuJoCo's soft contact
    end = trace[-1]
    assert {"pad_a", "pad_b"} <= end["touched"] and "ground" not in end["touched"]
    grasped = next(r for r in trace if r["t"] >= 0.2)
    rise_mug, rise_hand = end["mug"][2] - grasped["mug"][2], end["hand"][2] - grasped["hand"][2]
    assert rise_hand > 0.025 and abs(rise_mug - rise_hand) < 2e-3
    np.testing.assert_array_equal(np.stack([r["state"] for r in hooked["trace"]]), np.stack([r["state"] for r in trace]))


@pytest.mark.slow  # 3 x 150 steps of the grasp and a proxy's whole bake (25 s on 2 cores): 60-150 s
def test_the_grasp_is_the_same_to_the_last_bit_whatever_the_proxy_cache_held(tmp_path, monkeypatch):
    """A scene gives the same trajectory from an empty proxy cache (its bricks baked lazily as the steps reach them,
    a few at a time), from the cache that run left, and from a cache baked ahead in other batches: a brick's values
    do not depend on which bricks were baked with it (zoo.proxy's EVAL_MULTIPLE), as MuJoCo gives the same step for
    the same model and state."""
    import gc

    from zoo.proxy import cached_proxy

    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))
    shape = zoo.load("mugs").shape("hoi4d_mug_0001")
    steps = 150  # resting on the plane, then the pads close on it (40-140 ms)
    empty = _grasp(False, shape, steps, proxy="lazy")
    gc.collect()  # the run's proxy, dropped, writes what it baked
    left = _grasp(False, shape, steps, proxy="lazy")
    gc.collect()
    assert empty["lazy_bricks"] > 100 and left["lazy_bricks"] < empty["lazy_bricks"] / 4  # baked, then mostly read
    full = cached_proxy(shape, margin=1e-3)
    assert full.bake_all(progress=False) > 1000 and full.n_pending == 0
    del full
    gc.collect()
    ahead = _grasp(False, shape, steps)  # the default: baked ahead, here found whole in the cache
    assert ahead["lazy_bricks"] == 0
    states = [np.stack([r["state"] for r in run["trace"]]) for run in (empty, left, ahead)]
    assert not np.array_equal(states[0][0], states[0][-1])  # it moved
    np.testing.assert_array_equal(states[1], states[0])
    np.testing.assert_array_equal(states[2], states[0])


@pytest.mark.parametrize("reduce", ["exact", False, True])
def test_a_contact_the_proxy_reads_as_separated_reaches_mujoco_at_the_sdfs_depth(reduce):
    """A ball at rest 20 um into a box, on a coarse proxy (4 mm cells) that reads its lowest point 40-60 um above the
    box (the trilinear interpolant of a convex SDF lies above it mid-cell): filtered on the proxy's depth, that
    contact is separated and not closing, and was dropped before the SDF saw it. Where the SDF's depths decide
    (``reduce="exact"`` or False), the filters take a proxy's depth at its least (less its error bound); on the
    default (True) it is a near miss (read within the proxy's p99 error of touching); either way the SDF's answer
    decides: MuJoCo gets the contact at the SDF's depth."""
    from zoo.contact_filters import GRAZING_COS, SEPARATED_COS, usable_rows
    from zoo.proxy import bake_proxy

    sphere = zoo.Sphere(radius=BALL)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=4e-3)
    # the surface point, near the bottom, that the proxy reads furthest above the sphere: it is turned to the bottom
    angles = np.radians(np.linspace(0.0, 8.0, 33))
    tilt, turn = (a.ravel() for a in np.meshgrid(angles, np.linspace(0.0, 2 * np.pi, 24, endpoint=False)))
    down = np.stack([np.sin(tilt) * np.cos(turn), np.sin(tilt) * np.sin(turn), -np.cos(tilt)], axis=1)
    above = proxy.read_numpy(BALL * down)[0]
    best = int(np.argmax(above))
    assert above[best] > 4e-5 and above[best] < proxy.error_bound
    sink = 2e-5
    # the ball's orientation takes that point to straight below its centre: a rotation about axis down x (0, 0, -1)
    axis = np.cross(down[best], [0.0, 0.0, -1.0])
    angle = np.arcsin(np.linalg.norm(axis))
    quat = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * axis / max(np.linalg.norm(axis), 1e-12)])
    xml = _ball_on('<geom type="box" size="0.2 0.2 0.05" pos="0 0 -0.05"/>', BALL - sink).replace(
        f'pos="0 0 {BALL - sink}"', f'pos="0 0 {BALL - sink}" quat="{" ".join(map(str, quat))}"')
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": sphere}, method="fw", proxy={"ball": proxy}, reduce=reduce)
    mujoco.mj_forward(model, data)
    world.add_contacts(data)
    contacts = world.contacts
    assert len(contacts) >= 1
    assert float(contacts.depths.min()) == pytest.approx(-sink, abs=2e-6)  # the SDF's depth, not the proxy's
    # on the proxy's depth at the ball's lowest point (at rest: nothing closes), the filter drops it without the slack
    up = np.array([[0.0, 0.0, 1.0]])
    bottom = np.array([[0.0, 0.0, 0.0]])
    reading = np.array([above[best] - sink])
    for slack, expected in ((0.0, False), (proxy.error_bound, True)):
        assert usable_rows(bottom, reading, up, up, np.zeros(3), np.zeros(3), 0.003, GRAZING_COS, SEPARATED_COS,
                           slack)[0] == expected


@pytest.mark.parametrize("reduce", ["exact", True])
def test_a_near_miss_the_sdf_has_separated_does_not_reach_mujoco(reduce):
    """A ball at rest 10 um above a box, on the coarse proxy above, its lowest point where the proxy reads it
    closest: the proxy reads it separated, within its p99 error (the default's near miss) and its error bound (the
    exact path's slack), so the collider lets it through; the SDF has it 10 um apart, not closing: MuJoCo gets no
    contact."""
    from zoo.proxy import bake_proxy

    sphere = zoo.Sphere(radius=BALL)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=4e-3)
    gap = 1e-5
    assert float(proxy.read_numpy(np.array([[0.0, 0.0, -BALL]]))[0][0]) + gap < proxy.error["p99"]  # a node: read exactly
    model = mujoco.MjModel.from_xml_string(_ball_on('<geom type="box" size="0.2 0.2 0.05" pos="0 0 -0.05"/>', BALL + gap))
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": sphere}, method="fw", proxy={"ball": proxy}, reduce=reduce)
    mujoco.mj_forward(model, data)
    world.add_contacts(data)
    assert world.stats.raw_contacts >= 1  # let through to the SDF
    assert len(world.contacts) == 0


def test_surface_extraction_queries_near_the_surface_only_and_matches_a_dense_grid(monkeypatch):
    """zoo.sim.surface's narrow-band sampling gives the dense grid's signs everywhere and its values near the surface;
    a sphere's extracted vertices lie on it within a small fraction of a cell."""
    from zoo.sim import surface

    shape = zoo.Torus(major=0.05, minor=0.015)
    sparse, lo, cell = surface.sdf_grid(shape, 40)
    monkeypatch.setattr(surface, "COARSE", 1)
    dense, lo_dense, _ = surface.sdf_grid(shape, 40)
    n = tuple(min(a, b) for a, b in zip(sparse.shape, dense.shape))
    a, b = sparse[:n[0], :n[1], :n[2]], dense[:n[0], :n[1], :n[2]]
    assert np.allclose(lo, lo_dense) and np.array_equal(np.sign(a), np.sign(b))
    near = np.abs(b) < 2 * cell[0]
    assert near.sum() > 1000 and np.abs(a - b)[near].max() < 1e-6
    monkeypatch.setattr(surface, "COARSE", 4)
    vertices, faces = surface.surface_mesh(zoo.Sphere(radius=0.05), 64)
    assert np.abs(np.linalg.norm(vertices, axis=1) - 0.05).max() < 0.05 * (0.11 / 64)
    normals = np.cross(vertices[faces[:, 1]] - vertices[faces[:, 0]], vertices[faces[:, 2]] - vertices[faces[:, 0]])
    outward = np.einsum("ij,ij->i", normals, vertices[faces].mean(axis=1))
    assert (outward[np.linalg.norm(normals, axis=1) > 0] > 0).all()  # every face with an area faces out


# -- MuJoCo's renderer ------------------------------------------------------------------------------

def test_mujocos_renderer_draws_the_attached_body_and_its_contacts(tmp_path):
    """Offscreen (EGL or OSMesa, chosen by zoo.offscreen before mujoco loaded): the ball resting on the floor is drawn,
    its sdfzoo contacts add pixels when the contact flags are on, and the frames are written as a GIF and an MP4."""
    from zoo.offscreen import choose_gl

    if choose_gl() is None:
        pytest.skip("no offscreen OpenGL here (MUJOCO_GL=egl, or osmesa with Debian's libosmesa6)")
    import imageio.v3 as iio

    from zoo.sim.render import VideoRecorder, free_camera

    xml = _ball_on('<geom type="plane" size="1 1 0.1" rgba="0.5 0.5 0.5 1"/>', BALL)
    xml = xml.replace(f'type="sphere" size="{BALL}"', 'type="sphere" size="0.01"')  # a small visual: the contact shows
    xml = xml.replace("<worldbody>", '<visual><scale contactwidth="1" contactheight="0.3"/></visual><worldbody><light pos="0 0 1"/>')
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw")
    world.step(data, 20)
    assert data.ncon >= 1
    camera = free_camera(model, data, [model.body("ball").id], lookat=(0.0, 0.0, 0.0), distance=0.15)
    with VideoRecorder(model, camera=camera, width=160, height=120, contacts=True) as with_contacts, \
            VideoRecorder(model, camera=camera, width=160, height=120, contacts=False) as without:
        drawn, plain = with_contacts.capture(data), without.capture(data)
        assert plain.std() > 5  # not a blank frame: the ball over the floor
        assert (np.abs(drawn.astype(int) - plain.astype(int)).sum(axis=2) > 30).sum() > 20  # the contacts' marks
        world.step(data)
        with_contacts.capture(data)
        gif, mp4 = with_contacts.write(tmp_path / "ball.gif", fps=10), with_contacts.write(tmp_path / "ball.mp4", fps=10)
    assert iio.imread(gif, index=None).shape[:3] == (2, 120, 160)
    assert mp4.stat().st_size > 0


@pytest.mark.parametrize("half_length", [0.0, 0.06])
def test_spheres_and_capsules_meet_an_sdf_in_closed_form_at_the_exact_depth(half_length):
    """A zoo.Sphere body over a tilted capsule (or sphere) geom: one step's deepest contact lies at the exact signed
    distance between the two (centre to segment, less both radii), with the exact normal."""
    geom = "sphere" if half_length == 0 else "capsule"
    size = "0.02" if half_length == 0 else f"0.02 {half_length}"
    xml = _ball_on(f'<geom type="{geom}" size="{size}" pos="0.01 0 0" euler="0 70 0"/>', 0.068, timestep=0.001)  # penetrating: kept however still
    model = mujoco.MjModel.from_xml_string(xml.replace("<option", '<option gravity="0 0 0"'))
    data = mujoco.MjData(model)
    world = zoo.sim.attach(model, {"ball": zoo.Sphere(radius=BALL)}, method="fw", margin=2e-3)
    assert [p.kind for p in world.pairs] == ["segment"]
    world.step(data)
    mujoco.mj_forward(model, data)
    centre, rotation = data.xpos[model.body("ball").id], data.geom_xmat[0].reshape(3, 3)
    axis = rotation[:, 2]
    t = np.clip((centre - data.geom_xpos[0]) @ axis, -half_length, half_length)
    nearest = data.geom_xpos[0] + t * axis
    exact = float(np.linalg.norm(centre - nearest)) - BALL - 0.02
    deepest = int(np.argmin(world.contacts.depths.numpy()))
    assert world.contacts.depths[deepest].item() == pytest.approx(exact, abs=2e-5 if half_length == 0 else 1e-4)
    expected_normal = (nearest - centre) / np.linalg.norm(nearest - centre)  # from the SDF towards the capsule
    assert np.allclose(world.contacts.normals[deepest].numpy(), expected_normal, atol=1e-2)


def test_a_mujoco_gl_backend_that_cannot_load_says_what_to_install(tmp_path):
    """mujoco imports its renderer at import: MUJOCO_GL=osmesa without OSMesa fails there with an AttributeError deep in
    PyOpenGL. `import zoo.sim` says what to install or unset instead (a stand-in mujoco fails the same way here)."""
    import os
    import subprocess
    import sys

    fake = tmp_path / "mujoco"
    fake.mkdir()
    (fake / "__init__.py").write_text("raise AttributeError(\"'NoneType' object has no attribute 'glGetError'\")\n")
    env = {**os.environ, "MUJOCO_GL": "osmesa", "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    done = subprocess.run([sys.executable, "-c", "import zoo.sim"], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode != 0
    assert "MissingDependencyError" in done.stderr and "libosmesa6" in done.stderr and "unset MUJOCO_GL" in done.stderr
