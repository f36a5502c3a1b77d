"""The paper's four scenarios and a gripper, simulated on the real meshes (scenes/sim-*.toml), each with its check.

- mug-rack: the mug released above the peg comes to hang on it: every contact on the peg's surface.
- bottle-holder: the bottle lowered into the holder rests upright: the tilt of its axis.
- gear-gear: the large gear driven at constant speed turns the medium one: speed ratio vs teeth ratio.
- bolt-nut: the nut driven by a torque about the bolt's axis advances one pitch per turn.
- gripper-mug: an MJCF gripper (scenes/gripper.xml) closes on the mug, lifts it and carries it: the mug moves with the hand.

Teeth and the thread's pitch are measured on the meshes, not typed in. Needs $ZOO_DATA (the real meshes).

    python -m sdfzoo.benches.sim_scenarios --scene gear-gear --out out/sim-scenarios
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from zoo.files import atomic_write_text
from zoo.resources import bundled

SCENES = bundled("scenes")  # the clone's scenes/, or the wheel's copy
TOLERANCE = 0.05  # gear ratio and advance per turn: within 5% of the teeth ratio and the pitch

# scenes/mug-rack.toml's comment: the NDF rack's peg rises at 50 degrees from PEG_ROOT, radius 9.5 mm
PEG_ROOT = np.array([0.0247, 0.0, 0.1564])
PEG_AXIS = np.array([0.643, 0.0, 0.766]) / np.linalg.norm([0.643, 0.0, 0.766])
PEG_RADIUS = 0.0095
GEAR_CENTRES = {"large": (-0.0302, 0.0), "medium": (0.02025, 0.0)}  # scenes/gear-gear.toml: axes along z
GEAR_FILES = {"large": "gear/industreal_gear_large.obj", "medium": "gear/industreal_gear_medium.obj"}
BOLT_FILE = "bolt/factory_bolt_m16.obj"
GEAR_SETTLE_S = 0.02  # the speed ratio is measured after the first contacts' transient


# -- geometry measured on the meshes ------------------------------------------------------------


def require_meshes() -> None:
    """Exit with what to do where $ZOO_DATA (the real meshes these benches run on) is not set."""
    if not os.environ.get("ZOO_DATA"):
        raise SystemExit("set ZOO_DATA to the folder of the real meshes (../shared/meshes)")


def data_mesh(relative: str):
    import trimesh

    return trimesh.load(Path(os.environ["ZOO_DATA"]) / relative, force="mesh")


def count_teeth(vertices: np.ndarray, centre: tuple[float, float], crest: float = 3e-4) -> int:
    """Teeth of a spur gear about a z axis through ``centre``: the groups of tip vertices (V, 3) (within
    ``crest`` m of the largest radius) around the axis; the gaps between teeth are the widest gaps in angle."""
    x, y = vertices[:, 0] - centre[0], vertices[:, 1] - centre[1]
    radius = np.hypot(x, y)
    angles = np.sort(np.arctan2(y, x)[radius > radius.max() - crest])
    gaps = np.diff(np.concatenate([angles, angles[:1] + 2 * np.pi]))
    return int((gaps > 0.25 * gaps.max()).sum())


def thread_pitch(vertices: np.ndarray, z_range=(0.018, 0.038), candidates=np.arange(1.0e-3, 3.0e-3, 2.5e-5)) -> tuple[float, str]:
    """(pitch in m, "right" or "left") of a thread about the z axis: the crest vertices (V, 3) lie on a
    helix z = p theta / 2 pi + k p, so their phase (z -/+ p theta / 2 pi) mod p is coherent only at the
    true pitch and hand."""
    radius, angle = np.hypot(vertices[:, 0], vertices[:, 1]), np.arctan2(vertices[:, 1], vertices[:, 0])
    shank = (vertices[:, 2] > z_range[0]) & (vertices[:, 2] < z_range[1])
    crest = shank & (radius > radius[shank].max() - 2e-4)
    z, theta = vertices[crest, 2], angle[crest]
    best = (0.0, 0.0, "right")
    for p in candidates:
        for hand, sign in (("right", 1.0), ("left", -1.0)):
            phase = (z - sign * p * theta / (2 * np.pi)) / p * 2 * np.pi
            coherence = float(np.abs(np.exp(1j * phase).mean()))
            if coherence > best[0]:
                best = (coherence, float(p), hand)
    return best[1], best[2]


# -- running a scenario --------------------------------------------------------------------------


@dataclass
class Scenario:
    """A scene file, what to record at each step and the check computed from it."""

    scene: str
    check: Callable  # (sim, trace, extra) -> dict with "passed"
    record: Callable = lambda sim: {}  # noqa: E731  # per-step values kept in the trace
    prepare: Callable = lambda sim: None  # noqa: E731  # anything computed once before the run: -> extra
    control: Callable | None = None  # (sim, extra) before every step: prescribed motions


def start(name: str):
    """(the Scenario, its scene's Simulation built, what its ``prepare`` computed) of scenario ``name``."""
    import zoo.sim

    scenario = SCENARIOS[name]
    sim = zoo.sim.load_scene(SCENES / scenario.scene)
    sim.build()  # joint addresses, initial kinematics
    return scenario, sim, scenario.prepare(sim) or {}


def advance(scenario: Scenario, sim, extra: dict) -> None:
    """One step of the scenario: its control (if any), then the simulation's step."""
    if scenario.control is not None:
        scenario.control(sim, extra)
    sim.step()


def run(name: str, seconds: float | None = None, out: Path | None = None) -> dict:
    """Simulate scenario ``name`` (its scene's seconds unless given) and compute its check; write
    ``out/<name>.json`` when ``out`` is given. Returns the result (check, timings, penetration)."""
    require_meshes()
    scenario, sim, extra = start(name)
    path = SCENES / scenario.scene
    seconds = sim.seconds if seconds is None else seconds
    trace = [{"time": sim.time, "contacts": 0, "penetration_mm": 0.0, **scenario.record(sim)}]
    started = time.perf_counter()
    for _ in range(int(round(seconds / sim.dt))):
        advance(scenario, sim, extra)
        step = sim.log[-1]
        trace.append({"time": sim.time, "contacts": step.contacts, "penetration_mm": 1e3 * step.max_penetration, **scenario.record(sim)})
    wall = time.perf_counter() - started
    result = {
        "scenario": name, "scene": str(path.relative_to(SCENES.parent)), "simulated_s": sim.time, "dt": sim.dt,
        "steps": len(sim.log), "wall_s": wall, "steps_per_s": len(sim.log) / wall,
        "mean_collide_ms": 1e3 * float(np.mean([r.collide_s for r in sim.log])),
        "max_penetration_mm": 1e3 * max((r.max_penetration for r in sim.log), default=0.0),
        "max_contacts": max((r.contacts for r in sim.log), default=0),
        "max_raw_contacts": max((r.raw_contacts for r in sim.log), default=0),
        "speculative_steps": sum(r.speculative for r in sim.log),
        "warnings": sim.warnings[:20], "finite": all(np.isfinite(sim.pose(b)).all() for b in sim.bodies),
        "check": scenario.check(sim, trace, extra),
        "machine": platform.node(), "cpu_threads": _threads(),
    }
    result["passed"] = bool(result["check"]["passed"] and result["finite"])
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out / f"{name}.json", json.dumps({**result, "trace": trace}, indent=1, default=float))
    return result


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def _hinge_angle(sim, body: str) -> float:
    return float(sim.data.qpos[sim.bodies[body].qpos_adr])


def _tilt_deg(pose: np.ndarray) -> float:
    """Angle (degrees) between the body's z axis and the world's."""
    return math.degrees(math.acos(float(np.clip(pose[2, 2], -1.0, 1.0))))


# -- mug-rack ------------------------------------------------------------------------------------


def _mug_record(sim) -> dict:
    return {"mug": sim.pose("mug")[:3, 3].tolist(), "contacts": int(sim.log[-1].contacts) if sim.log else 0}


def _mug_on_peg(sim, trace, extra) -> dict:
    """Hanging: still held (contacts), every contact on the peg's surface (within 1 mm of its radius,
    along the peg), the mug within 5 cm of where it was released."""
    points = sim.contacts.points.double().numpy()
    along = (points - PEG_ROOT) @ PEG_AXIS
    radial = np.linalg.norm(points - PEG_ROOT - np.outer(along, PEG_AXIS), axis=1)
    on_peg = bool(len(points) and np.all(np.abs(radial - PEG_RADIUS) < 1e-3) and np.all((along > 0) & (along < 0.2)))
    moved = float(np.linalg.norm(np.asarray(trace[-1]["mug"]) - np.asarray(trace[0]["mug"])))
    return {"contacts": len(points), "all_on_peg": on_peg,
            "radial_error_mm_max": float(1e3 * np.abs(radial - PEG_RADIUS).max()) if len(points) else None,
            "moved_m": moved, "speed_end_m_s": float(np.linalg.norm(sim.velocity("mug")[:3])),
            "passed": on_peg and moved < 0.05}


# -- bottle-holder -------------------------------------------------------------------------------


def _bottle_record(sim) -> dict:
    pose = sim.pose("bottle")
    return {"bottle": pose[:3, 3].tolist(), "tilt_deg": _tilt_deg(pose)}


def _bottle_upright(sim, trace, extra) -> dict:
    """Upright and at rest in the holder: tilt under 5 degrees, held by contacts, inside the wall's radius."""
    pose = sim.pose("bottle")
    tilt = _tilt_deg(pose)
    offset = float(np.hypot(*pose[:2, 3]))
    held = sim.log[-1].contacts > 0
    return {"tilt_deg_start": trace[0]["tilt_deg"], "tilt_deg_end": tilt, "tilt_deg_max": max(t["tilt_deg"] for t in trace),
            "axis_offset": offset, "height_end": float(pose[2, 3]), "contacts": int(sim.log[-1].contacts),
            "speed_end": float(np.linalg.norm(sim.velocity("bottle")[:3])),
            "passed": bool(tilt < 5.0 and held and offset < 0.19)}


# -- gear-gear -----------------------------------------------------------------------------------


def _gear_prepare(sim) -> dict:
    teeth = {name: count_teeth(np.asarray(data_mesh(f).vertices), GEAR_CENTRES[name]) for name, f in GEAR_FILES.items()}
    return {"teeth": teeth}


def _gear_record(sim) -> dict:
    return {"large": _hinge_angle(sim, "large"), "medium": _hinge_angle(sim, "medium"),
            "w_large": float(sim.data.qvel[sim.bodies["large"].dof_adr]),
            "w_medium": float(sim.data.qvel[sim.bodies["medium"].dof_adr])}


def gear_ratio(sim, trace, extra) -> dict:
    """Speed ratio |w_medium / w_large| (mean speeds after GEAR_SETTLE_S) vs teeth_large / teeth_medium."""
    window = [t for t in trace if t["time"] >= GEAR_SETTLE_S]
    times = np.array([t["time"] for t in window])
    turned_large = window[-1]["large"] - window[0]["large"]
    turned_medium = window[-1]["medium"] - window[0]["medium"]
    expected = extra["teeth"]["large"] / extra["teeth"]["medium"]
    # mean speeds: least-squares slopes of the angles against time (a tooth's passage makes the medium gear jitter)
    w_large, w_medium = (float(np.polyfit(times, [t[g] for t in window], 1)[0]) for g in ("large", "medium"))
    measured = -w_medium / w_large if w_large else float("nan")
    error = abs(measured - expected) / expected
    return {"teeth": extra["teeth"], "expected_ratio": expected, "measured_ratio": measured, "relative_error": error,
            "window_s": [window[0]["time"], window[-1]["time"]], "w_large": w_large, "w_medium": w_medium,
            "large_turned_rad": turned_large,
            "medium_turned_rad": turned_medium, "passed": bool(error <= TOLERANCE)}


# -- bolt-nut ------------------------------------------------------------------------------------

NUT_SPEED = -1.5  # rad/s about +z: tightening a right-hand thread (the nut goes down)
NUT_KV = 1e-3  # N m s/rad: explicit servo, stable while kv dt / I_zz (1.6e-6 kg m^2) stays under 2
NUT_TORQUE = -2e-3  # N m, feed-forward: the servo alone (at most 1.3e-3 N m) did not overcome the thread's friction
BOLT_SETTLE_S = 0.1  # the nut first drops through the thread's axial play (0.9 mm) onto the bolt's flanks


def _bolt_prepare(sim) -> dict:
    pitch, hand = thread_pitch(np.asarray(data_mesh(BOLT_FILE).vertices))
    return {"pitch": pitch, "hand": hand}


def _nut_torque(sim, extra) -> None:
    """The torque about the bolt's axis (world z) that turns the nut: tau0 + kv (w* - w), applied at its centre of mass."""
    spin = float(sim.velocity("nut")[5])
    sim.data.xfrc_applied[sim.bodies["nut"].body_id, 3:] = (0.0, 0.0, NUT_TORQUE + NUT_KV * (NUT_SPEED - spin))


def _bolt_record(sim) -> dict:
    pose = sim.pose("nut")  # the bolt is fixed at the origin: the nut's height is its place along the bolt
    return {"nut_yaw": math.atan2(pose[1, 0], pose[0, 0]), "nut_along_bolt": float(pose[2, 3]),
            "nut_tilt_deg": _tilt_deg(pose), "nut_off_axis_mm": 1e3 * float(np.hypot(*pose[:2, 3]))}


def bolt_advance(sim, trace, extra) -> dict:
    """Advance per turn of the nut along the bolt after BOLT_SETTLE_S vs the thread's pitch (least-squares
    slope of height against angle); a right-hand thread advances +pitch per +turn (counter-clockwise from +z)."""
    window = [t for t in trace if t["time"] >= BOLT_SETTLE_S]
    angle = np.unwrap([t["nut_yaw"] for t in window])
    height = np.array([t["nut_along_bolt"] for t in window])
    turns = (angle[-1] - angle[0]) / (2 * np.pi)
    per_turn = float(np.polyfit(angle / (2 * np.pi), height, 1)[0]) if abs(turns) > 0 else float("nan")
    signed_pitch = extra["pitch"] if extra["hand"] == "right" else -extra["pitch"]
    error = abs(per_turn - signed_pitch) / extra["pitch"]
    return {"pitch_mm": 1e3 * extra["pitch"], "hand": extra["hand"], "turns": float(turns),
            "advance_mm": 1e3 * float(height[-1] - height[0]), "advance_per_turn_mm": 1e3 * per_turn,
            "relative_error": error, "window_s": [window[0]["time"], window[-1]["time"]],
            "nut_tilt_deg_max": max(t["nut_tilt_deg"] for t in trace), "nut_off_axis_mm_max": max(t["nut_off_axis_mm"] for t in trace),
            "passed": bool(error <= TOLERANCE)}


# -- gripper-mug ---------------------------------------------------------------------------------

PADS = ("left_pad", "right_pad")
GRASPED_AT = 0.2  # s: the scene's waypoints have closed the fingers by then (scenes/sim-gripper-mug.toml)


def _gripper_record(sim) -> dict:
    touching = {sim.model.geom(int(g)).name for g in sim.world.contact_geoms[:, 1]}
    return {"mug": sim.pose("mug")[:3, 3].tolist(), "hand": sim.pose("hand")[:3, 3].tolist(),
            "pads": sorted(touching & set(PADS)), "table": "table" in touching, "tilt_deg": _tilt_deg(sim.pose("mug"))}


def _gripper_carried(sim, trace, extra) -> dict:
    """Rests on the table until grasped, then rises and moves with the hand (slipping less than 2 mm), held by both pads."""
    start = np.asarray(trace[0]["mug"])
    grasped = next(r for r in trace if r["time"] >= GRASPED_AT)
    end = trace[-1]
    mug_move = np.asarray(end["mug"]) - np.asarray(grasped["mug"])
    hand_move = np.asarray(end["hand"]) - np.asarray(grasped["hand"])
    settled = max(float(np.linalg.norm(np.asarray(r["mug"]) - start)) for r in trace if r["time"] < 0.04)  # before the pads arrive
    on_table = all(r["table"] for r in trace if 0.01 <= r["time"] < 0.04)  # released at its resting height: it lands first
    slip = float(np.linalg.norm(mug_move - hand_move))
    both = end["pads"] == sorted(PADS)
    return {"mug_rise_mm": 1e3 * float(mug_move[2]), "mug_shift_mm": 1e3 * float(mug_move[0]),
            "hand_rise_mm": 1e3 * float(hand_move[2]), "hand_shift_mm": 1e3 * float(hand_move[0]), "slip_mm": 1e3 * slip,
            "resting_drift_mm": 1e3 * settled, "on_table_before_grasp": on_table, "pads_touching_end": end["pads"],
            "tilt_deg_end": end["tilt_deg"],
            "passed": bool(on_table and settled < 2e-3 and mug_move[2] > 0.02 and slip < 0.002 and both)}


SCENARIOS = {
    "mug-rack": Scenario("sim-mug-rack.toml", _mug_on_peg, record=_mug_record),
    "bottle-holder": Scenario("sim-bottle-holder.toml", _bottle_upright, record=_bottle_record),
    "gear-gear": Scenario("sim-gear-gear.toml", gear_ratio, record=_gear_record, prepare=_gear_prepare),
    "bolt-nut": Scenario("sim-bolt-nut.toml", bolt_advance, record=_bolt_record, prepare=_bolt_prepare, control=_nut_torque),
    "gripper-mug": Scenario("sim-gripper-mug.toml", _gripper_carried, record=_gripper_record),
}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=sorted(SCENARIOS), action="append", default=[],
                        help="scenario to run (repeat for several)")
    parser.add_argument("--seconds", type=float, default=None, help="simulated time (default: the scene's)")
    parser.add_argument("--out", type=Path, default=Path("out/sim-scenarios"))
    args = parser.parse_args(argv)
    if not args.scene:
        parser.error("name a --scene")
    for name in args.scene:
        result = run(name, args.seconds, args.out)
        summary = {k: result[k] for k in ("scenario", "passed", "steps", "wall_s", "steps_per_s", "max_penetration_mm", "max_contacts")}
        print(json.dumps({**summary, "check": result["check"]}, default=float), flush=True)


if __name__ == "__main__":
    main()
