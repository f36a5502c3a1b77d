"""Two reference simulators for ``zoo bench --sim``: the scenarios of scenes/sim-*.toml without sdfzoo.

- ``mujoco_sdf_plugin`` (bolt-nut, gear-gear): MuJoCo's own SDF collision on the analytic shapes of
  its ``libsdf_plugin.so`` (``mujoco.sdf.nut``/``bolt``/``gear``), sized like ours as far as the
  plugin allows. The plugin's nut and bolt have a fixed size (12 turns per unit length, a 1-unit
  hexagon): that scenario is simulated in a world scaled by ``BOLT_SCALE`` (plugin units per metre of
  ours, chosen so that the pitch is ours, 2 mm) with every dimensional quantity scaled to match
  (gravity x k, torques x k^2, solimp's width x k, time and mass unchanged), and reported in our units.
- ``coacd_native`` (all four): what most users do today: each body's mesh cut into convex pieces by
  CoACD (cached under ``out/cache/coacd`` in the working folder), MuJoCo's native convex-convex collision, the poses,
  masses, joints, dt, friction and solref of our scene file.

Each returns the metrics of :func:`step_metrics` plus the scenario's outcome (the same checks as
benches/sim_scenarios.py where they apply). Needs $ZOO_DATA for coacd_native (the real meshes).

    python -m sdfzoo.benches.sim_references --method coacd-native --scenario bolt-nut --seconds 0.2
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import os
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from sdfzoo.benches.sim_scenarios import (
    BOLT_FILE,
    GEAR_CENTRES,
    GEAR_FILES,
    NUT_KV,
    NUT_SPEED,
    NUT_TORQUE,
    PEG_AXIS,
    PEG_RADIUS,
    PEG_ROOT,
    bolt_advance,
    count_teeth,
    data_mesh,
    gear_ratio,
    thread_pitch,
)
from zoo.files import atomic_path, sha256_file
from zoo.resources import bundled
from zoo.sim.model import quaternion

SCENES = bundled("scenes")  # the clone's scenes/, or the wheel's copy
CACHE = Path("out") / "cache" / "coacd"  # under the working folder, beside the bench's out/: never inside the package
SCENARIOS = {"bolt-nut": "sim-bolt-nut.toml", "gear-gear": "sim-gear-gear.toml",
             "mug-rack": "sim-mug-rack.toml", "bottle-holder": "sim-bottle-holder.toml"}
PLUGIN_SCENARIOS = ("bolt-nut", "gear-gear")
METHODS = ("mujoco-sdf-plugin", "coacd-native")
DEFAULT_SOLIMP = (0.9, 0.95, 0.001, 0.5, 2.0)  # zoo.sim's default: the scenes give none

# CoACD's parameters (its defaults but the log level): threshold 0.05 is its concavity bound relative
# to the mesh's size; decomposing the 50k-face gears at it takes minutes on one core (see the report).
COACD_PARAMS = {"threshold": 0.05, "max_convex_hull": -1, "preprocess_mode": "auto", "preprocess_resolution": 50,
                "resolution": 2000, "mcts_nodes": 20, "mcts_iterations": 150, "mcts_max_depth": 3, "pca": False,
                "merge": True, "decimate": False, "max_ch_vertex": 256, "seed": 0}

# -- the plugin's shapes ---------------------------------------------------------------------------

PLUGIN_SDF_LIB = "libsdf_plugin.so"
PLUGIN_SCREW = 12.0  # turns per unit length of the plugin's nut and bolt (hard-coded in nut.cc / bolt.cc)
PLUGIN_THREAD_RADIUS = 0.26  # the plugin's default "radius": thread root; crests at 0.26 + 0.5 / 12
OUR_PITCH = 0.002  # m: the M16 bolt's (measured by benches/sim_scenarios.thread_pitch)
BOLT_SCALE = 1.0 / PLUGIN_SCREW / OUR_PITCH  # plugin units per metre: 41.67, the plugin's pitch becomes 2 mm
# MuJoCo's model/plugin/sdf/nutbolt.xml: the bolt upside down (head at the bottom, shaft up) and the
# nut's resting pose on its thread (2 of its 6 pitches engaged), in plugin units
PLUGIN_BOLT_QUAT = (0.0, 1.0, 0.0, 0.0)
PLUGIN_NUT_POS = (-0.0012496, 0.00329058, 0.830362)
PLUGIN_NUT_QUAT = (-0.000212626, 0.999996, -0.00200453, 0.00185878)
# nutbolt.xml's SDF search settings (gear.xml uses 5 and 20; we keep 15 and 60 for both)
SDF_ITERATIONS, SDF_INITPOINTS = 15, 60
GEAR_TEETH = {"large": 60, "medium": 40}  # counted on our meshes (benches/sim_scenarios.count_teeth)
GEAR_MODULE = 0.001  # m: our gears' tip radii are 31 and 21 mm = module x (teeth + 2) / 2
GEAR_THICKNESS = 0.02  # m: our gears span z = 5..25 mm
GEAR_Z = 0.015


# -- timing and metrics ----------------------------------------------------------------------------


def deepest_penetration(data) -> float:
    """The deepest active contact's penetration max(0, -dist), in the model's length unit (0 with none)."""
    if data.ncon == 0:
        return 0.0
    return max(0.0, -float(data.contact.dist[:data.ncon].min()))


def simulate(model, data, seconds: float, control: Callable | None = None, record: Callable | None = None) -> dict:
    """Step ``seconds`` of simulated time; ``control(model, data)`` runs before each step (untimed),
    ``record(model, data)`` after it. Returns per-step arrays: step_s (S,), ncon (S,), penetration (S,)
    (model units) and the records (a list of S + 1, the first before any step)."""
    import mujoco

    steps = int(round(seconds / model.opt.timestep))
    step_s, ncon, penetration = np.zeros(steps), np.zeros(steps, dtype=np.int64), np.zeros(steps)
    mujoco.mj_forward(model, data)
    records = [record(model, data)] if record else []
    for i in range(steps):
        if control is not None:
            control(model, data)
        started = time.perf_counter()
        mujoco.mj_step(model, data)
        step_s[i] = time.perf_counter() - started
        ncon[i], penetration[i] = data.ncon, deepest_penetration(data)
        if record is not None:
            records.append(record(model, data))
    return {"step_s": step_s, "ncon": ncon, "penetration": penetration, "records": records}


def step_metrics(method: str, scenario: str, dt: float, run: dict, length_scale: float = 1.0) -> dict:
    """The keys every reference returns, from :func:`simulate`'s arrays; penetrations divided by
    ``length_scale`` (model units per metre of our scene) and given in mm."""
    step_s, pen_mm = run["step_s"], 1e3 * run["penetration"] / length_scale
    wall = float(step_s.sum())
    return {
        "method": method, "scenario": scenario, "dt": float(dt), "steps": int(len(step_s)), "wall_s": wall,
        "steps_per_s": len(step_s) / wall if wall > 0 else float("nan"),
        "step_ms": {"median": 1e3 * float(np.median(step_s)), "p90": 1e3 * float(np.percentile(step_s, 90))},
        "contacts_per_step": float(run["ncon"].mean()),
        "penetration_mm": {"median": float(np.percentile(pen_mm, 50)), "p99": float(np.percentile(pen_mm, 99)),
                           "max": float(pen_mm.max())},
    }


def _scene(scenario: str) -> dict:
    from zoo.scenes import read_scene

    if scenario not in SCENARIOS:
        raise SystemExit(f"unknown scenario {scenario!r}; one of {sorted(SCENARIOS)}")
    return read_scene(SCENES / SCENARIOS[scenario])[0]


def _body_pose(data, body: int) -> np.ndarray:
    """(4, 4) world-from-body of body id ``body``."""
    pose = np.eye(4)
    pose[:3, :3] = data.xmat[body].reshape(3, 3)
    pose[:3, 3] = data.xpos[body]
    return pose


def _tilt_deg(rotation: np.ndarray, start: np.ndarray) -> float:
    """Angle (degrees) between a body's z axis now (rotation (3, 3)) and at the start."""
    return math.degrees(math.acos(float(np.clip(rotation[:, 2] @ start[:, 2], -1.0, 1.0))))


# -- the drives (the same as benches/sim_scenarios.py's and the scene files') ----------------------


def nut_torque_control(body: int, torque_scale: float = 1.0) -> Callable:
    """benches/sim_scenarios.py's nut drive: tau0 + kv (w* - w) about world z on ``body``, both
    multiplied by ``torque_scale`` (k^2 in the plugin's scaled world)."""
    import mujoco

    def control(model, data):
        velocity = np.zeros(6)
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)  # world frame: rot, lin
        spin = float(velocity[2])
        data.xfrc_applied[body, 3:] = (0.0, 0.0, torque_scale * (NUT_TORQUE + NUT_KV * (NUT_SPEED - spin)))

    return control


def _nut_record(body: int, length_scale: float, start_rotation: np.ndarray) -> Callable:
    """Per step: the trace keys benches/sim_scenarios._bolt_advance reads (our metres)."""

    def record(model, data):
        pose = _body_pose(data, body)
        return {"time": float(data.time), "nut_yaw": math.atan2(pose[1, 0], pose[0, 0]),
                "nut_along_bolt": float(pose[2, 3]) / length_scale, "nut_tilt_deg": _tilt_deg(pose[:3, :3], start_rotation),
                "nut_off_axis_mm": 1e3 * float(np.hypot(*pose[:2, 3])) / length_scale}

    return record


def _gear_record(joints: dict[str, int]) -> Callable:
    """Per step: hinge angles and speeds, the trace keys benches/sim_scenarios._gear_ratio reads."""

    def record(model, data):
        row = {"time": float(data.time)}
        for name, joint in joints.items():
            row[name] = float(data.qpos[model.jnt_qposadr[joint]])
            row[f"w_{name}"] = float(data.qvel[model.jnt_dofadr[joint]])
        return row

    return record


def _bolt_outcome(trace: list[dict], pitch: float, hand: str) -> dict:
    """Advance per turn vs the thread's pitch (benches/sim_scenarios' check), the nut's wobble and final pose."""
    check = bolt_advance(None, trace, {"pitch": pitch, "hand": hand})
    return {"advance_per_turn_mm": check["advance_per_turn_mm"], "turns": check["turns"], "advance_mm": check["advance_mm"],
            "pitch_mm": check["pitch_mm"], "nut_tilt_deg_max": check["nut_tilt_deg_max"],
            "nut_off_axis_mm_max": check["nut_off_axis_mm_max"], "check": check,
            "final_pose": {k: trace[-1][k] for k in ("nut_yaw", "nut_along_bolt", "nut_tilt_deg", "nut_off_axis_mm")}}


def _gear_outcome(trace: list[dict], teeth: dict) -> dict:
    check = gear_ratio(None, trace, {"teeth": teeth})
    return {"speed_ratio": check["measured_ratio"], "expected_ratio": check["expected_ratio"], "check": check,
            "final_pose": {k: trace[-1][k] for k in ("large", "medium", "w_large", "w_medium")}}


# -- 1. MuJoCo's SDF plugin ------------------------------------------------------------------------


def plugin_library() -> Path:
    """The mujoco wheel's libsdf_plugin.so (raises FileNotFoundError when it ships none)."""
    import mujoco

    path = Path(mujoco.__file__).parent / "plugin" / PLUGIN_SDF_LIB
    if not path.is_file():
        raise FileNotFoundError(f"{path} not found: this mujoco wheel ships no SDF plugin")
    return path


_LOADED: set[str] = set()


def _load_plugin() -> None:
    """Load the SDF plugin library once per process (a second load registers its plugins twice)."""
    import mujoco

    path = str(plugin_library())
    if path not in _LOADED:
        mujoco.mj_loadPluginLibrary(path)
        _LOADED.add(path)


def _contact_defaults(friction: float, solref, solimp) -> str:
    """Every geom's contact settings as zoo.sim's contacts have them: condim 3, Coulomb friction, the
    scene's solref/solimp, pushing only on touch (zoo.sim's includemargin 0). No margin: MuJoCo 4.0.0
    sums the two geoms' margins into includemargin and its gap did not lower it (tried), so a margin
    would hold bodies apart by twice its value; the scene's margin is zoo.collide's detection distance."""
    return f'<geom condim="3" friction="{friction:.17g} 0.005 0.0001" solref="{mjcf_vector(solref)}" solimp="{mjcf_vector(solimp)}"/>'


def mjcf_vector(values) -> str:
    """An MJCF attribute value: the numbers of ``values`` (any shape), space-separated, to full precision."""
    return " ".join(f"{float(v):.17g}" for v in np.asarray(values).reshape(-1))


def nutbolt_mjcf(dt: float, friction: float, solref, solimp, mass: float, k: float = BOLT_SCALE,
                 inertial: tuple | None = None) -> str:
    """MJCF of the plugin's nut (free, ``mass``, ``inertial`` (mass, com, inertia) or MuJoCo's) on its bolt
    (fixed) in a world of ``k`` plugin units per metre: gravity x k, solimp's width (its third value, a
    length) x k."""
    solimp = list(solimp)
    solimp[2] *= k
    return f"""<mujoco model="sdf-plugin-nutbolt">
<extension>
  <plugin plugin="mujoco.sdf.nut"><instance name="nut"><config key="radius" value="{PLUGIN_THREAD_RADIUS}"/></instance></plugin>
  <plugin plugin="mujoco.sdf.bolt"><instance name="bolt"><config key="radius" value="{PLUGIN_THREAD_RADIUS}"/></instance></plugin>
</extension>
<option timestep="{dt:.17g}" gravity="0 0 {-9.81 * k:.17g}" integrator="implicitfast" sdf_iterations="{SDF_ITERATIONS}" sdf_initpoints="{SDF_INITPOINTS}"/>
<size memory="64M"/>
<asset><mesh name="nut"><plugin instance="nut"/></mesh><mesh name="bolt"><plugin instance="bolt"/></mesh></asset>
<default>{_contact_defaults(friction, solref, solimp)}</default>
<worldbody>
  <body name="nut" pos="{mjcf_vector(PLUGIN_NUT_POS)}" quat="{mjcf_vector(PLUGIN_NUT_QUAT)}">
    <freejoint name="nut"/>{_inertial(inertial)}
    <geom type="sdf" name="nut" mesh="nut" mass="{mass:.17g}"><plugin instance="nut"/></geom>
  </body>
  <body name="bolt" quat="{mjcf_vector(PLUGIN_BOLT_QUAT)}">
    <geom type="sdf" name="bolt" mesh="bolt"><plugin instance="bolt"/></geom>
  </body>
</worldbody>
</mujoco>"""


def _tooth_phase(model, mesh: int, teeth: int, k: float = 1.0) -> float:
    """The angle (rad, about the mesh's z) of a tooth's centre: the tip vertices' (within 0.1 module of
    the largest radius) angles times ``teeth`` averaged on the circle, divided by ``teeth``."""
    start = model.mesh_vertadr[mesh]
    vertices = model.mesh_vert[start:start + model.mesh_vertnum[mesh]]
    radius = np.hypot(vertices[:, 0], vertices[:, 1])
    tips = np.arctan2(vertices[:, 1], vertices[:, 0])[radius > radius.max() - 0.1 * k * GEAR_MODULE]
    return float(np.angle(np.exp(1j * teeth * tips).mean())) / teeth


def _inertial(props: tuple | None) -> str:
    """An <inertial> element from (mass, com (3,), inertia (3, 3)); "" for None (MuJoCo computes it)."""
    if props is None:
        return ""
    mass, com, inertia = props
    return (f'<inertial pos="{mjcf_vector(com)}" mass="{float(mass):.17g}" fullinertia="'
            f'{mjcf_vector([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])}"/>')


def plugin_mesh_inertial(model, name: str, mass: float, offset) -> tuple:
    """(mass, com (3,), inertia (3, 3)) of the plugin mesh ``name`` (its marching-cubes mesh, a closed
    volume) with ``mass``, its geom at ``offset`` (3,) in the body. MuJoCo's own inertia of an SDF
    geom put the gears' largest moment about x, not about their axis (4.0.0), hence this."""
    import trimesh

    mesh = model.mesh(name).id
    v0, f0 = model.mesh_vertadr[mesh], model.mesh_faceadr[mesh]
    solid = trimesh.Trimesh(model.mesh_vert[v0:v0 + model.mesh_vertnum[mesh]], model.mesh_face[f0:f0 + model.mesh_facenum[mesh]])
    return mass, np.asarray(solid.center_mass) + np.asarray(offset), np.asarray(solid.moment_inertia) * mass / solid.volume


def gears_mjcf(scene: dict, phases: dict[str, float] | None = None, inertia: dict | None = None, k: float = 1.0) -> str:
    """MJCF of two plugin spur gears on hinges, as scenes/sim-gear-gear.toml's: same axes' places (the
    medium one moved as the scene moves it), masses, initial speeds and drives; pitch diameter
    module x teeth, 20 mm thick. ``phases`` (rad) turns each gear about its axis so that the large
    gear's tooth faces the medium gear's gap on the line of centres; ``inertia`` {name: (mass, com,
    inertia)} (plugin units). ``k`` plugin units per metre: lengths x k, gravity x k, drive gains x k^2."""
    sim = scene["sim"]
    solimp = list(sim.get("solimp", DEFAULT_SOLIMP))
    solimp[2] *= k
    bodies = {b["name"]: b for b in scene["bodies"]}
    phases = phases or {"large": 0.0, "medium": 0.0}
    inertia = inertia or {}
    plugins, meshes, worldbody, actuators = [], [], [], []
    for name, body in bodies.items():
        centre = k * (np.asarray(body["anchor"], dtype=np.float64) + np.asarray(body.get("pose", {}).get("translation", [0, 0, 0])))
        plugins.append(f'<plugin plugin="mujoco.sdf.gear"><instance name="{name}"><config key="alpha" value="0"/>'
                       f'<config key="diameter" value="{k * GEAR_MODULE * GEAR_TEETH[name]:.17g}"/>'
                       f'<config key="teeth" value="{GEAR_TEETH[name]}"/><config key="thickness" value="{k * GEAR_THICKNESS:.17g}"/></instance></plugin>')
        meshes.append(f'<mesh name="{name}"><plugin instance="{name}"/></mesh>')
        worldbody.append(
            f'<body name="{name}" pos="{centre[0]:.17g} {centre[1]:.17g} 0" euler="0 0 {phases[name]:.17g}">'
            f'<joint name="{name}" type="hinge" axis="0 0 1"/>{_inertial(inertia.get(name))}'
            f'<geom type="sdf" name="{name}" mesh="{name}" pos="0 0 {k * GEAR_Z:.17g}" mass="{float(body["mass"]):.17g}">'
            f'<plugin instance="{name}"/></geom></body>')
        drive = body["drive"]
        if drive["type"] == "velocity":
            actuators.append(f'<velocity name="{name}" joint="{name}" kv="{k * k * float(drive["kv"]):.17g}"/>')
        else:  # the torque is gear x ctrl: the gear carries k^2
            actuators.append(f'<motor name="{name}" joint="{name}" gear="{k * k * float(drive.get("gear", 1.0)):.17g}"/>')
    return f"""<mujoco model="sdf-plugin-gears">
<compiler angle="radian"/>
<extension>{"".join(plugins)}</extension>
<option timestep="{float(sim["dt"]):.17g}" gravity="0 0 {-9.81 * k:.17g}" integrator="implicitfast" sdf_iterations="{SDF_ITERATIONS}" sdf_initpoints="{SDF_INITPOINTS}"/>
<size memory="64M"/>
<asset>{"".join(meshes)}</asset>
<default>{_contact_defaults(float(sim["friction"]), sim["solref"], solimp)}</default>
<worldbody>{"".join(worldbody)}</worldbody>
<actuator>{"".join(actuators)}</actuator>
</mujoco>"""


def _set_drives(model, data, scene: dict) -> None:
    """Initial hinge speeds and drive controls of a scene's bodies (by name: the joints and actuators carry them)."""
    import mujoco

    for body in scene["bodies"]:
        if body.get("joint") not in ("hinge", "slide"):
            continue
        joint = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_JOINT, body["name"])
        if body.get("velocity") is not None:
            data.qvel[model.jnt_dofadr[joint]] = float(np.asarray(body["velocity"]).reshape(-1)[0])
        if body.get("drive"):
            actuator = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, body["name"])
            data.ctrl[actuator] = float(body["drive"].get("target", body["drive"].get("ctrl", 0.0)))


def _plugin_bolt_nut(seconds: float, dt: float | None) -> dict:
    import mujoco

    scene = _scene("bolt-nut")
    sim = scene["sim"]
    dt = float(sim["dt"]) if dt is None else dt
    nut = next(b for b in scene["bodies"] if b["name"] == "nut")
    args = (dt, float(sim["friction"]), sim["solref"], sim.get("solimp", DEFAULT_SOLIMP), float(nut["mass"]))
    model = mujoco.MjModel.from_xml_string(nutbolt_mjcf(*args))
    inertial = plugin_mesh_inertial(model, "nut", float(nut["mass"]), (0.0, 0.0, 0.0))
    model = mujoco.MjModel.from_xml_string(nutbolt_mjcf(*args, inertial=inertial))
    data = mujoco.MjData(model)
    body = model.body("nut").id
    mujoco.mj_forward(model, data)
    start = data.xmat[body].reshape(3, 3).copy()
    run = simulate(model, data, seconds, nut_torque_control(body, BOLT_SCALE ** 2), _nut_record(body, BOLT_SCALE, start))
    result = step_metrics("mujoco-sdf-plugin", "bolt-nut", dt, run, BOLT_SCALE)
    crest = (PLUGIN_THREAD_RADIUS + 0.5 / PLUGIN_SCREW) / BOLT_SCALE
    result.update(_bolt_outcome(run["records"], OUR_PITCH, "right"))  # the plugin's thread: z 12 - azimuth / 2 pi, right-handed
    result["geometry"] = (
        f"mujoco.sdf.nut on mujoco.sdf.bolt (analytic, radius {PLUGIN_THREAD_RADIUS}), 1 SDF geom each; world scaled x{BOLT_SCALE:.2f} "
        f"so the pitch is 2 mm: thread {2e3 * PLUGIN_THREAD_RADIUS / BOLT_SCALE:.2f}-{2e3 * crest:.2f} mm diameter "
        f"(ours: M16, 16 mm), nut {1e3 * 0.5 / BOLT_SCALE:.0f} mm tall, {1e3 / BOLT_SCALE:.0f} mm across flats, shaft only "
        f"{1e3 * 0.5 / BOLT_SCALE:.0f} mm long, so the nut starts 2 pitches engaged (nutbolt.xml's pose), not fully on the thread "
        "10 mm above its seat as ours")
    result["notes"] = (
        f"scaled world: k = {BOLT_SCALE:.3f} plugin units per m; gravity x k, torque and kv x k^2, solimp width x k, margin 0, "
        "dt/mass/friction/solref unchanged; positions and penetrations reported in our m/mm; nut inertia of "
        f"the plugin's marching-cubes mesh at {nut['mass']} kg (Izz {model.body_inertia[body].max() / BOLT_SCALE ** 2:.3g} kg m^2 in our "
        f"units); sdf_iterations {SDF_ITERATIONS}, sdf_initpoints {SDF_INITPOINTS}; drive: benches/sim_scenarios' torque + speed servo")
    result["length_scale"] = BOLT_SCALE
    return result


def _plugin_gears(seconds: float, dt: float | None, k: float = 1.0) -> dict:
    import mujoco

    scene = _scene("gear-gear")
    if dt is not None:
        scene["sim"]["dt"] = dt
    # first build: the plugin's meshes tell where its teeth are; then turn each gear so they interleave
    model = mujoco.MjModel.from_xml_string(gears_mjcf(scene, k=k))
    tooth = {n: _tooth_phase(model, model.mesh(n).id, GEAR_TEETH[n], k) for n in GEAR_TEETH}
    # large: a tooth at angle 0 (towards the medium gear); medium: a gap (half a tooth pitch off a tooth) at pi
    phases = {"large": -tooth["large"], "medium": math.pi - tooth["medium"] - math.pi / GEAR_TEETH["medium"]}
    inertia = {b["name"]: plugin_mesh_inertial(model, b["name"], float(b["mass"]), (0.0, 0.0, k * GEAR_Z)) for b in scene["bodies"]}
    model = mujoco.MjModel.from_xml_string(gears_mjcf(scene, phases, inertia, k))
    data = mujoco.MjData(model)
    _set_drives(model, data, scene)
    joints = {n: model.joint(n).id for n in GEAR_TEETH}
    run = simulate(model, data, seconds, None, _gear_record(joints))
    result = step_metrics("mujoco-sdf-plugin", "gear-gear", float(model.opt.timestep), run, k)
    result.update(_gear_outcome(run["records"], GEAR_TEETH))
    centres = [np.asarray(b["anchor"]) + np.asarray(b.get("pose", {}).get("translation", [0, 0, 0])) for b in scene["bodies"]]
    distance = float(np.linalg.norm(centres[1] - centres[0]))
    result["geometry"] = (
        f"two mujoco.sdf.gear (analytic involute spur gears, 1 SDF geom each): 60 and 40 teeth, module {1e3 * GEAR_MODULE:.0f} mm, "
        f"{1e3 * GEAR_THICKNESS:.0f} mm thick, centre distance {1e3 * distance:.2f} mm as our scene (nominal 50 mm); the plugin's "
        "pressure angle depends on the teeth (15.4 and 19.4 deg: not a conjugate pair), its bore and tooth shape are not our meshes'")
    result["notes"] = (
        f"same dt, masses, hinges, initial speeds and drives as scenes/sim-gear-gear.toml; inertia of the plugin's "
        f"marching-cubes meshes (Izz {model.body_inertia[model.body('large').id].max():.3g}, "
        f"{model.body_inertia[model.body('medium').id].max():.3g} kg m^2); teeth phased to interleave on the line of centres; sdf_iterations {SDF_ITERATIONS}, "
        f"sdf_initpoints {SDF_INITPOINTS}. Tried: centre distances 50.0-51.0 mm, sdf_iterations 30 / initpoints 120, a world "
        "scaled x40 (k=40): the medium gear was kicked to 100+ rad/s by tooth contacts within 0.1 s in each")
    return result


def mujoco_sdf_plugin(scenario: str, seconds: float, dt: float | None = None) -> dict:
    """Simulate ``scenario`` ("bolt-nut" or "gear-gear") for ``seconds`` with MuJoCo's analytic SDF
    plugin shapes and MuJoCo's SDF collision; ``dt`` None is the scene's. Returns :func:`step_metrics`'s
    keys, "geometry", "notes" and the scenario's outcome."""
    if scenario not in PLUGIN_SCENARIOS:
        raise ValueError(f"the SDF plugin has shapes for {PLUGIN_SCENARIOS} only, not {scenario!r}")
    _load_plugin()
    return _plugin_bolt_nut(seconds, dt) if scenario == "bolt-nut" else _plugin_gears(seconds, dt)


# -- 2. CoACD + MuJoCo's native collision ----------------------------------------------------------


def cache_key(digest: str, params: dict) -> str:
    """sha256 of the mesh's digest, CoACD's parameters and version: the cache file's name."""
    import importlib.metadata

    text = json.dumps({"mesh": digest, "params": params, "coacd": importlib.metadata.version("coacd")}, sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()


def _pack(pieces: list[tuple[np.ndarray, np.ndarray]]) -> dict:
    return {"vertices": np.concatenate([v for v, _ in pieces]).astype(np.float64),
            "faces": np.concatenate([f for _, f in pieces]).astype(np.int32),
            "vertex_counts": np.array([len(v) for v, _ in pieces], dtype=np.int64),
            "face_counts": np.array([len(f) for _, f in pieces], dtype=np.int64)}


def _unpack(arrays) -> list[tuple[np.ndarray, np.ndarray]]:
    v_ends, f_ends = np.cumsum(arrays["vertex_counts"]), np.cumsum(arrays["face_counts"])
    vertices = np.split(arrays["vertices"], v_ends[:-1])
    faces = np.split(arrays["faces"], f_ends[:-1])
    return list(zip(vertices, faces))


def decompose(vertices: np.ndarray, faces: np.ndarray, digest: str, params: dict | None = None,
              cache: Path = CACHE) -> tuple[list[tuple[np.ndarray, np.ndarray]], dict]:
    """CoACD's convex pieces of a mesh (vertices (V, 3), faces (F, 3)) as [(vertices (Vi, 3) float64,
    faces (Fi, 3) int32)], and {"seconds", "cached", "key"}. ``digest`` names the mesh (its file's
    sha256); the result is cached in ``cache/<key>.npz`` (written atomically: CoACD takes minutes)."""
    params = dict(COACD_PARAMS if params is None else params)
    key = cache_key(digest, params)
    path = Path(cache) / f"{key}.npz"
    if path.is_file():
        with np.load(path) as arrays:
            return _unpack(arrays), {"seconds": float(arrays["seconds"]), "cached": True, "key": key}
    import coacd

    coacd.set_log_level("error")
    started = time.perf_counter()
    pieces = coacd.run_coacd(coacd.Mesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int32)), **params)
    seconds = time.perf_counter() - started
    buffer = io.BytesIO()  # np.savez adds ".npz" to a path that lacks it: write bytes, then rename atomically
    np.savez_compressed(buffer, **_pack(pieces), seconds=seconds, params=json.dumps(params, sort_keys=True))
    with atomic_path(path) as tmp:
        tmp.write_bytes(buffer.getvalue())
    return [(np.asarray(v, np.float64), np.asarray(f, np.int32)) for v, f in pieces], {"seconds": seconds, "cached": False, "key": key}


def source_mesh_file(sdf_spec: dict) -> Path:
    """The source mesh of a scene body's ``sdf = {model, shape}``: the category manifest's file for the
    shape, under $ZOO_DATA. The NeuralSDF is in that mesh's frame and units (Model.shape), so the mesh
    takes the body's place with no transform (checked: the SDF is ~0 on the mesh's surface)."""
    from sdfzoo.pipeline.categories import load_category

    return Path(os.environ["ZOO_DATA"]) / load_category(sdf_spec["model"]).entry(sdf_spec["shape"]).file


def body_mesh(body: dict) -> tuple[np.ndarray, np.ndarray, str, str]:
    """(vertices (V, 3), faces (F, 3), digest, label) of a scene body: its mesh, or its SDF's source mesh."""
    from zoo.meshes import load_mesh
    from zoo.scenes import build_mesh

    if "mesh" in body and "file" in body["mesh"]:
        path = Path(os.environ["ZOO_DATA"]) / body["mesh"]["file"]
    elif "sdf" in body:
        path = source_mesh_file(body["sdf"])
    else:  # a procedural part: named by its vertices and faces
        mesh, label = build_mesh(body["mesh"], SCENES)
        vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)
        digest = hashlib.sha256(vertices.tobytes() + faces.tobytes()).hexdigest()
        return vertices, faces, digest, label
    mesh = load_mesh(path)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64), sha256_file(path), path.name


def pieces_mass_properties(pieces: list[tuple[np.ndarray, np.ndarray]], mass: float):
    """(com (3,), inertia (3, 3) about it) of ``mass`` spread evenly over the convex pieces' volume
    (overlaps counted twice: CoACD's pieces barely overlap)."""
    import trimesh

    hulls = [trimesh.Trimesh(v, f).convex_hull for v, f in pieces]
    volumes = np.array([h.volume for h in hulls])
    density = mass / volumes.sum()
    com = sum(h.volume * np.asarray(h.center_mass) for h in hulls) / volumes.sum()
    inertia = np.zeros((3, 3))
    for h in hulls:
        r = np.asarray(h.center_mass) - com
        inertia += density * np.asarray(h.moment_inertia) + density * h.volume * ((r @ r) * np.eye(3) - np.outer(r, r))
    return com, inertia


def _pose(body: dict) -> np.ndarray:
    from zoo.scenes import pose_matrix

    return pose_matrix(body.get("pose"))


def native_mjcf(scene: dict, pieces: dict[str, list], dt: float) -> str:
    """MJCF of a scene's bodies, each a set of convex mesh geoms (body frame), with the scene's poses,
    masses, joints, drives and contact settings."""
    sim = scene["sim"]
    assets, worldbody, actuators = [], [], []
    for body in scene["bodies"]:
        name, parts = body["name"], pieces[body["name"]]
        pose = _pose(body)
        lines = [f'<body name="{name}" pos="{mjcf_vector(pose[:3, 3])}" quat="{mjcf_vector(quaternion(pose[:3, :3]))}">']
        joint = body.get("joint", "free")
        if joint == "free":
            lines.append(f'<freejoint name="{name}"/>')
        elif joint in ("hinge", "slide"):
            lines.append(f'<joint name="{name}" type="{joint}" axis="{mjcf_vector(body.get("axis", (0, 0, 1)))}" '
                         f'pos="{mjcf_vector(body.get("anchor", (0, 0, 0)))}"/>')
        if joint != "fixed":
            com, inertia = pieces_mass_properties(parts, float(body["mass"]))
            lines.append(f'<inertial pos="{mjcf_vector(com)}" mass="{float(body["mass"]):.17g}" fullinertia="'
                         f'{mjcf_vector([inertia[0, 0], inertia[1, 1], inertia[2, 2], inertia[0, 1], inertia[0, 2], inertia[1, 2]])}"/>')
        for i, (v, f) in enumerate(parts):
            assets.append(f'<mesh name="{name}_{i}" vertex="{mjcf_vector(v)}" face="{" ".join(str(int(x)) for x in f.reshape(-1))}"/>')
            lines.append(f'<geom type="mesh" mesh="{name}_{i}" mass="0"/>')  # the body's <inertial> holds its mass
        lines.append("</body>")
        worldbody.append("\n".join(lines))
        drive = body.get("drive")
        if drive and drive.get("type", "motor") == "velocity":
            actuators.append(f'<velocity name="{name}" joint="{name}" kv="{float(drive.get("kv", 100.0)):.17g}"/>')
        elif drive:
            actuators.append(f'<motor name="{name}" joint="{name}" gear="{float(drive.get("gear", 1.0)):.17g}"/>')
    gravity = sim.get("gravity", (0.0, 0.0, -9.81))
    return f"""<mujoco model="coacd-native">
<option timestep="{dt:.17g}" gravity="{mjcf_vector(gravity)}" integrator="{sim.get("integrator", "implicitfast")}"/>
<size memory="256M"/>
<default>{_contact_defaults(float(sim.get("friction", 1.0)), sim.get("solref", (0.02, 1.0)), sim.get("solimp", DEFAULT_SOLIMP))}</default>
<asset>{"".join(assets)}</asset>
<worldbody>{"".join(worldbody)}</worldbody>
<actuator>{"".join(actuators)}</actuator>
</mujoco>"""


def _set_free_velocity(model, data, scene: dict) -> None:
    """A free body's initial velocity (linear, angular: world), as zoo.sim sets it (its qvel's angular part is body-frame)."""
    for body in scene["bodies"]:
        if body.get("joint", "free") != "free" or body.get("velocity") is None:
            continue
        v = np.asarray(body["velocity"], dtype=np.float64)
        adr = model.jnt_dofadr[model.joint(body["name"]).id]
        data.qvel[adr:adr + 3] = v[:3]
        data.qvel[adr + 3:adr + 6] = _pose(body)[:3, :3].T @ v[3:]


def _mug_outcome(model, data, trace) -> dict:
    """benches/sim_scenarios' mug-rack check on MuJoCo's contacts: every contact on the peg's surface
    (within 1 mm of its radius, along the peg), the mug within 5 cm of its release point."""
    points = np.array(data.contact.pos[:data.ncon]).reshape(-1, 3)
    along = (points - PEG_ROOT) @ PEG_AXIS
    radial = np.linalg.norm(points - PEG_ROOT - np.outer(along, PEG_AXIS), axis=1)
    on_peg = bool(len(points) and np.all(np.abs(radial - PEG_RADIUS) < 1e-3) and np.all((along > 0) & (along < 0.2)))
    moved = float(np.linalg.norm(np.asarray(trace[-1]["position"]) - np.asarray(trace[0]["position"])))
    return {"contacts": len(points), "all_on_peg": on_peg, "moved_m": moved,
            "radial_error_mm_max": float(1e3 * np.abs(radial - PEG_RADIUS).max()) if len(points) else None,
            "passed": on_peg and moved < 0.05, "final_pose": trace[-1]}


def _bottle_outcome(model, data, trace) -> dict:
    """benches/sim_scenarios' bottle-holder check: upright (tilt < 5 deg), held by contacts, inside the wall."""
    end = trace[-1]
    offset = float(np.hypot(*end["position"][:2]))
    return {"tilt_deg_start": trace[0]["tilt_deg"], "tilt_deg_end": end["tilt_deg"], "tilt_deg_max": max(t["tilt_deg"] for t in trace),
            "axis_offset": offset, "height_end": end["position"][2], "contacts": int(data.ncon),
            # released 30 mm (bottle units) above the floor: a bottle that reached it dropped ~30 mm
            "dropped_mm": 1e3 * (trace[0]["position"][2] - end["position"][2]),
            "passed": bool(end["tilt_deg"] < 5.0 and data.ncon > 0 and offset < 0.19), "final_pose": end}


def _free_record(body: int) -> Callable:
    def record(model, data):
        pose = _body_pose(data, body)
        return {"time": float(data.time), "position": pose[:3, 3].tolist(), "quat": data.xquat[body].tolist(),
                "tilt_deg": math.degrees(math.acos(float(np.clip(pose[2, 2], -1.0, 1.0))))}

    return record


def coacd_native(scenario: str, seconds: float, dt: float | None = None, params: dict | None = None) -> dict:
    """Simulate ``scenario`` for ``seconds``: both bodies' meshes (an SDF body's source mesh) cut by
    CoACD (``params``, default COACD_PARAMS; cached), MuJoCo's native convex collision; the scene's
    poses, masses, joints, drives, dt (unless given), friction, solref and solimp. Returns
    :func:`step_metrics`'s keys, "geometry", "notes", "decomposition" and the scenario's outcome."""
    import mujoco

    from sdfzoo.benches.sim_scenarios import require_meshes

    require_meshes()
    scene = _scene(scenario)
    dt = float(scene["sim"].get("dt", 0.002)) if dt is None else dt
    pieces, decomposition = {}, {}
    for body in scene["bodies"]:
        vertices, faces, digest, label = body_mesh(body)
        pieces[body["name"]], info = decompose(vertices, faces, digest, params)
        decomposition[body["name"]] = {"mesh": label, "faces": int(len(faces)), "pieces": len(pieces[body["name"]]), **info}
    model = mujoco.MjModel.from_xml_string(native_mjcf(scene, pieces, dt))
    data = mujoco.MjData(model)
    _set_drives(model, data, scene)
    _set_free_velocity(model, data, scene)
    control, record, outcome = _native_scenario(scenario, model, data)
    run = simulate(model, data, seconds, control, record)
    result = step_metrics("coacd-native", scenario, dt, run)
    result.update(outcome(model, data, run["records"]))
    result["geometry"] = "; ".join(f"{name}: {d['mesh']} ({d['faces']} faces) -> {d['pieces']} convex pieces"
                                   for name, d in decomposition.items()) + "; same meshes, poses and joints as our scene"
    result["notes"] = (f"CoACD {json.dumps(params or COACD_PARAMS, sort_keys=True)}; decomposition s: "
                       + ", ".join(f"{n} {d['seconds']:.1f}{' (cached)' if d['cached'] else ''}" for n, d in decomposition.items())
                       + "; inertia of each body's mass spread over its pieces; contacts: condim 3, margin 0 (see _contact_defaults)")
    result["decomposition"] = decomposition
    return result


def _native_scenario(scenario: str, model, data):
    """(control, record, outcome(model, data, trace)) of a scenario on the native model."""
    import mujoco

    if scenario == "bolt-nut":
        body = model.body("nut").id
        mujoco.mj_forward(model, data)
        pitch, hand = thread_pitch(np.asarray(data_mesh(BOLT_FILE).vertices))
        return (nut_torque_control(body), _nut_record(body, 1.0, data.xmat[body].reshape(3, 3).copy()),
                lambda m, d, trace: _bolt_outcome(trace, pitch, hand))
    if scenario == "gear-gear":
        teeth = {name: count_teeth(np.asarray(data_mesh(f).vertices), GEAR_CENTRES[name]) for name, f in GEAR_FILES.items()}
        joints = {n: model.joint(n).id for n in teeth}
        return None, _gear_record(joints), lambda m, d, trace: _gear_outcome(trace, teeth)
    body = model.body("mug" if scenario == "mug-rack" else "bottle").id
    return None, _free_record(body), _mug_outcome if scenario == "mug-rack" else _bottle_outcome



# -- command line ----------------------------------------------------------------------------------


def run_reference(method: str, scenario: str, seconds: float, dt: float | None = None) -> dict:
    """One reference run by method name ("mujoco-sdf-plugin" or "coacd-native")."""
    if method == "mujoco-sdf-plugin":
        return mujoco_sdf_plugin(scenario, seconds, dt)
    if method == "coacd-native":
        return coacd_native(scenario, seconds, dt)
    raise ValueError(f"unknown method {method!r}; one of {METHODS}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--method", choices=METHODS, required=True)
    parser.add_argument("--scenario", choices=sorted(SCENARIOS), required=True)
    parser.add_argument("--seconds", type=float, default=0.2, help="simulated time (default 0.2 s)")
    parser.add_argument("--dt", type=float, default=None, help="time step (default: the scene's)")
    args = parser.parse_args(argv)
    print(json.dumps(run_reference(args.method, args.scenario, args.seconds, args.dt), indent=1, default=float), flush=True)


if __name__ == "__main__":
    main()
