"""How far the bolt's SDF is from its thread's screw symmetry: |f(S x) - f(x)| on points near the thread.

A nut that follows a bolt's thread moves, relative to the bolt, by the thread's screw motion S: a turn
theta about the axis and an advance of pitch theta / 2 pi along it. If the bolt's SDF were unchanged
by S, a simulation could carry a nut face's answer along the screw (its value kept) and bound only
the rest of the motion. Today the whole motion enters the bound (Lipschitz), and that is why no
Bolt-Nut face can be skipped or reused (docs/sim-bench.md). This bench measures the premise. It
checks the bolts model's NeuralSDF and, as the control, the exact signed distance of the bolt mesh the
model was fitted to. A pure turn (no advance) is measured beside the screw, for scale.

    python -m investigations screw_symmetry --out out/screw-symmetry.json

Needs $ZOO_DATA (the bolt mesh; pitch and hand are measured on it by benches.sim_scenarios.thread_pitch).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from investigations.report import write_report

ANGLES = (0.003, 0.01, 0.05, 0.2, 1.0)  # rad; a Bolt-Nut step turns the nut by about 0.003-0.006 rad
THREAD_Z = (0.020, 0.036)  # m: inside the threaded shank (thread_pitch reads 0.018-0.038) after an advance of 1/6 mm
OFFSET = 1e-4  # m: points within this of the surface, on either side (Bolt-Nut's margin)
PERCENTILES = (50, 99, 100)


def screw(points: np.ndarray, theta: float, advance_per_rad: float) -> np.ndarray:
    """Points (N, 3) turned by ``theta`` about the z axis and moved ``advance_per_rad * theta`` along it."""
    c, s = np.cos(theta), np.sin(theta)
    out = points.copy()
    out[:, 0] = c * points[:, 0] - s * points[:, 1]
    out[:, 1] = s * points[:, 0] + c * points[:, 1]
    out[:, 2] = points[:, 2] + advance_per_rad * theta
    return out


def advance_per_rad(pitch: float, hand: str) -> float:
    """m of advance along +z per rad about +z of a thread's screw motion: a right-hand thread advances +pitch a turn."""
    return (pitch if hand == "right" else -pitch) / (2 * np.pi)


def asymmetry(sdf, points: np.ndarray, angles, advance: float) -> list[dict]:
    """Per angle (both signs), percentiles in mm of |sdf(screw(x)) - sdf(x)| over ``points`` (N, 3).
    ``sdf`` maps (N, 3) float64 points to (N,) values."""
    base = sdf(points)
    rows = []
    for theta in angles:
        for signed in (theta, -theta):
            diff = 1e3 * np.abs(sdf(screw(points, signed, advance)) - base)
            rows.append({"theta": signed, **{f"p{q}_mm": float(np.percentile(diff, q)) for q in PERCENTILES}})
    return rows


def thread_samples(mesh, n: int, seed: int = 0) -> np.ndarray:
    """``n`` points (n, 3) near the threaded shank's surface: surface samples with ``THREAD_Z`` moved along their
    face's normal by up to ``OFFSET`` either way."""
    import trimesh

    rng = np.random.default_rng(seed)
    points, faces = trimesh.sample.sample_surface(mesh, 20 * n, seed=seed)
    inside = (points[:, 2] > THREAD_Z[0]) & (points[:, 2] < THREAD_Z[1])
    points, normals = points[inside][:n], mesh.face_normals[faces[inside][:n]]
    return points + normals * rng.uniform(-OFFSET, OFFSET, (len(points), 1))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000, help="points for the NeuralSDF")
    parser.add_argument("--exact-points", type=int, default=4000, help="points for the mesh's exact distance (slower)")
    parser.add_argument("--out", default="out/screw-symmetry.json")
    args = parser.parse_args(argv)
    import zoo
    from sdfzoo.benches.sim_scenarios import BOLT_FILE, data_mesh, require_meshes, thread_pitch
    from zoo.meshes import signed_distance

    require_meshes()
    torch.set_num_threads(1)
    mesh = data_mesh(BOLT_FILE)
    pitch, hand = thread_pitch(np.asarray(mesh.vertices))
    model = zoo.load("bolts")
    shape = model.shape("factory_bolt_m16")

    def neural(p):
        with torch.no_grad():
            return shape(torch.from_numpy(p)).double().numpy()

    def exact(p):
        return signed_distance(mesh, p)

    points = thread_samples(mesh, args.points)
    screw_rate = advance_per_rad(pitch, hand)
    result = {"model": f"{model.name}@{model.version}", "shape": "factory_bolt_m16", "pitch_mm": 1e3 * pitch, "hand": hand,
              "points": len(points), "exact_points": min(args.exact_points, len(points)), "offset_mm": 1e3 * OFFSET,
              "thread_z_m": THREAD_Z,
              "neural_screw": asymmetry(neural, points, ANGLES, screw_rate),
              "neural_turn": asymmetry(neural, points, ANGLES, 0.0),
              "exact_screw": asymmetry(exact, points[: args.exact_points], ANGLES, screw_rate)}
    print(f"pitch {1e3 * pitch:.3f} mm, {hand}-hand; |f(S x) - f(x)| in mm over points within {1e3 * OFFSET:g} mm of the thread")
    print(f"{'theta rad':>9} | {'NeuralSDF screw p50 p99 max':>28} | {'NeuralSDF turn p50 p99 max':>27} | {'mesh screw p50 p99 max':>23}")
    for ns, nt, ex in zip(result["neural_screw"], result["neural_turn"], result["exact_screw"]):
        cells = [" ".join(f"{r[f'p{q}_mm']:.4f}" for q in PERCENTILES) for r in (ns, nt, ex)]
        print(f"{ns['theta']:>+9.3f} | {cells[0]:>28} | {cells[1]:>27} | {cells[2]:>23}")
    write_report(args.out, result, __name__, argv)
