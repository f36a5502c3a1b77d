"""`zoo demo`: a mug hung on a rack, its contacts, and error against run time.

Needs nothing outside the package: the scene is the bundled file ``scenes/demo-mug-rack.toml``
(also ``zoo collide demo-mug-rack``): the rack is procedural and the mug is a shape of the ``mugs``
model shipped with sdfzoo, loaded by name. The pose written in that file, which hangs the mug by its
handle, was found from the SDF itself (:func:`mug_rack_scene`, :func:`hanging_pose`). Where no
``mugs`` model is packaged (a checkout before the first training run), the demo says so and hangs
an analytic ring instead.
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import numpy as np
import torch

import zoo
from zoo.errors import InputError, ZooError
from zoo.parts import make_part
from zoo.scenes import Scene, load_collision_scene, run_scene, scene_from_dict, write_outputs

DEMO_SCENE = "demo-mug-rack"  # scenes/demo-mug-rack.toml: mug_rack_scene(zoo.load("mugs")), written down
MUG_MODEL = "mugs"
PREFERRED_MUGS = ("hoi4d_mug_0001",)  # scanned mugs in metres; any other shape works too
RACK = {"height": 0.30, "post_radius": 0.012, "peg_length": 0.09, "peg_radius": 0.006, "peg_height": 0.20,
        "peg_angle_deg": 20.0, "base": 0.16, "max_edge": 0.006}  # zoo.parts.rack's, in metres
CONTACT_ROWS = 15  # contacts printed; the JSON holds them all
RACK_MUG_SIZE = 0.13  # the mug size (normalised cube side, metres) the rack's sizes suit


def demo_scene() -> tuple[Scene, str]:
    """The demo's scene and a line saying what it is: the mug on the rack, or the ring without a mugs model."""
    try:
        scene = load_collision_scene(DEMO_SCENE)
    except ZooError as exc:
        return scene_from_dict(demo_scene_spec()), f"no {MUG_MODEL!r} model is packaged ({exc}); hanging an analytic ring instead"
    if getattr(scene.sdf.model, "detector", None) is None:
        scene.method = "fw"  # a mugs package without a detector (mug_rack_scene's rule)
    return scene, f"{scene.sdf_label} hung by its handle on a procedural rack ({scene.method})"


def mug_rack_scene(model, stem: str | None = None, along: float = 0.06, press: float = 5e-4) -> Scene:
    """A shape of ``model`` hung by its handle on the procedural rack's peg, ``along`` up the peg.

    The rack is scaled to the mug (sizes are for a 0.13 m mug: a shape in other units gets a rack
    in its units), and so are ``along``, ``press`` (how far the handle presses into the peg) and
    the margin. Method "amortized" where the model has a detector, else "fw".
    """
    stem = stem or next((s for s in PREFERRED_MUGS if s in model.shapes), model.shapes[0])
    shape = model.shape(stem)
    factor = (1.0 / float(shape.similarity.scale)) / RACK_MUG_SIZE
    rack, pose = rack_for(shape, along, press)
    return Scene(
        name="demo-mug-rack", sdf=shape, mesh=make_part("rack", **rack), sdf_pose=pose, mesh_pose=np.eye(4),
        method="amortized" if model.detector is not None else "fw", margin=1e-3 * factor,
        sdf_label=f"{model.name}@{model.version}:{stem}", mesh_label="procedural:rack",
    )


def rack_for(shape, along: float = 0.06, press: float = 5e-4, fit_peg: bool = False) -> tuple[dict, np.ndarray]:
    """The procedural rack's parameters scaled to ``shape`` (its normalised cube's side against ``RACK_MUG_SIZE``),
    and the pose (4, 4) that hangs the shape by its handle on the peg, ``along`` up it and pressed ``press`` into it
    (both scaled too). ``fit_peg``: a peg thicker than 80% of the handle's hole is thinned to that."""
    factor = (1.0 / float(shape.similarity.scale)) / RACK_MUG_SIZE
    rack = {k: (v if k == "peg_angle_deg" else v * factor) for k, v in RACK.items()}
    if fit_peg:
        rack["peg_radius"] = min(rack["peg_radius"], 0.4 * float(handle_hole(shape)[3].min()))
    a = np.radians(rack["peg_angle_deg"])
    peg_start = np.array([0.0, 0.0, rack["peg_height"]])
    pose, _ = hanging_pose(shape, peg_start, (np.cos(a), 0.0, np.sin(a)), rack["peg_radius"], along * factor, press * factor)
    return rack, pose


def handle_hole(shape, n_angles: int = 12, pixels: int = 96):
    """Where a mug's handle can hang: its hole, found from the SDF alone, in the source frame.

    Vertical sections through the centre of the shape's normalised frame (unit cube, z up) are
    sampled on ``pixels`` x ``pixels`` grids at ``n_angles`` headings; in each, the outside
    (f > 0) is split into connected regions, and one that does not reach the border is a hole.
    The largest hole is the handle's.

    Returns:
        contact (3,): the hole's point farthest from the body at mid-height, the inner face of
            the handle's bar, which rests on a peg through the hole;
        to_handle (3,): unit, in the hole's plane, from the body's axis towards the handle;
        axis (3,): unit, the hole's axis (normal to its plane);
        size (2,): the hole's width and height.
    """
    from scipy import ndimage

    sim = shape.similarity
    rot, scale, shift = np.asarray(sim.rotation, dtype=np.float64), float(sim.scale), np.asarray(sim.translation, dtype=np.float64)
    up = np.array([0.0, 0.0, 1.0])
    s = (np.arange(pixels) + 0.5) / pixels - 0.5
    a, b = np.meshgrid(s, s, indexing="ij")  # (P, P): along the heading, up
    best = None
    for theta in np.linspace(0.0, np.pi, n_angles, endpoint=False):
        heading = np.array([np.cos(theta), np.sin(theta), 0.0])
        points = (a[..., None] * heading + b[..., None] * up).reshape(-1, 3)
        with torch.no_grad():
            f = torch.as_tensor(shape(torch.as_tensor(_to_source(points, rot, scale, shift)))).reshape(pixels, pixels)
        labels, n = ndimage.label(f.numpy() > 0)
        border = set(np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]])).tolist())
        for k in set(range(1, n + 1)) - border:
            mask = labels == k
            if best is None or mask.sum() > best[0].sum():
                best = (mask, heading)
    if best is None:
        raise InputError("no handle found: no vertical section of the shape encloses a hole to hang it by")
    mask, heading = best
    ha, hb = a[mask], b[mask]
    if ha.mean() < 0:  # point the heading from the body's axis towards the handle
        heading, ha = -heading, -ha
    mid = 0.5 * (hb.min() + hb.max())
    row = np.abs(hb - mid) <= 1.5 / pixels
    contact = (ha[row].max() + 0.5 / pixels) * heading + mid * up
    axis = np.cross(up, heading)
    size = np.array([np.ptp(ha), np.ptp(hb)]) + 1.0 / pixels
    return _to_source(contact[None], rot, scale, shift)[0], heading @ rot, axis @ rot, size / scale


def _to_source(points_n: np.ndarray, rot: np.ndarray, scale: float, shift: np.ndarray) -> np.ndarray:
    """Normalised-frame points (N, 3) -> source frame: inverse of p_n = scale * rot @ p + shift."""
    return ((points_n - shift) / scale) @ rot


def hanging_pose(shape, peg_start, peg_dir, peg_radius: float, along: float, press: float = 5e-4):
    """A 4x4 world-from-shape pose that hangs ``shape`` by its handle on a peg.

    The peg is a cylinder of ``peg_radius`` from ``peg_start`` along ``peg_dir``; the handle's
    hole (:func:`handle_hole`) is threaded on it ``along`` from the start, the handle pointing
    up (perpendicular to the peg) so the body hangs below, and the inner face of the handle's
    bar pressed ``press`` into the peg's top. Returns (pose, hole size (2,)).
    """
    contact, to_handle, axis, size = handle_hole(shape)
    d = np.asarray(peg_dir, dtype=np.float64)
    d = d / np.linalg.norm(d)
    up = np.array([0.0, 0.0, 1.0]) - d[2] * d
    up = up / np.linalg.norm(up)
    if size.min() < 2 * peg_radius:
        raise InputError(f"the handle's hole ({size.min():.4g}) is narrower than the peg ({2 * peg_radius:.4g})")
    rot = np.column_stack([up, d, np.cross(up, d)]) @ np.column_stack([to_handle, axis, np.cross(to_handle, axis)]).T
    pose = np.eye(4)
    pose[:3, :3] = rot
    pose[:3, 3] = np.asarray(peg_start, dtype=np.float64) + along * d + (peg_radius - press) * up - rot @ contact
    return pose, size


def demo_scene_spec() -> dict:
    """A torus "handle" hung on the procedural rack's peg, pressing 0.5 mm into it (no mugs model)."""
    x = 0.06  # along the peg, which rises at 20 degrees from (0, 0, 0.20)
    peg_top = 0.20 + x * np.tan(np.radians(20.0)) + 0.006
    major, minor = 0.035, 0.008
    return {
        "name": "demo-ring-rack",
        "method": "fw",
        "margin": 1e-3,
        "sdf": {
            "analytic": "torus",
            "params": {"major": major, "minor": minor},
            # axis along x so the peg passes through the hole; the hole's top rests on the peg
            "pose": {"translation": [x, 0.0, peg_top - (major - minor) - 5e-4], "rotation_deg": [0, 90, 0]},
        },
        "mesh": {"procedural": "rack"},
    }


def error_vs_runtime(scene, iters=(1, 2, 5, 10, 20, 50), repeats: int = 3) -> list[dict]:
    """Optimality (eq. 12) and time of the amortized detector and of Frank-Wolfe at several iteration counts on
    the scene's candidates; times are medians of ``repeats`` calls after a warm-up (a first call pays for caches)."""
    from zoo.collision import candidate_triangles
    from zoo.geometry import invert_pose, transform_points

    from .scenes import median_seconds

    sdf_from_mesh = invert_pose(torch.as_tensor(scene.sdf_pose, dtype=torch.float64)) @ torch.as_tensor(scene.mesh_pose)
    verts = transform_points(sdf_from_mesh.float(), torch.as_tensor(np.asarray(scene.mesh.vertices), dtype=torch.float32))
    tris = verts[torch.as_tensor(np.asarray(scene.mesh.faces))]
    tris = tris[candidate_triangles(scene.sdf, tris, scene.margin)]
    if not len(tris):
        return []
    solvers = {}
    if scene.method == "amortized":
        solvers["amortized"] = lambda: scene.sdf.detect(tris)
    for k in iters:
        solvers[f"fw-{k}"] = partial(zoo.solvers.frank_wolfe, scene.sdf, tris, iters=k)
    rows = []
    for name, solve in solvers.items():
        seconds, bary = median_seconds(solve, repeats)
        gap = zoo.solvers.optimality(scene.sdf, tris, bary)
        rows.append({"method": name, "optimality_mean": float(gap.mean()), "optimality_p90": float(gap.quantile(0.9)),
                     "ms_per_triangle": 1e3 * seconds / len(tris)})
    return rows


def contacts_table(scene, contacts, rows: int = CONTACT_ROWS):
    """A rich table of the first ``rows`` contacts (triangle, point, depth, normal), titled with the counts."""
    from rich.table import Table

    table = Table(title=f"{scene.name}: {len(contacts)} contacts, {contacts.n_candidates} candidates of {contacts.n_triangles} triangles")
    for col in ("triangle", "point", "depth (mm)", "normal"):
        table.add_column(col)
    for t, p, d, n in list(zip(contacts.triangles, contacts.points, contacts.depths, contacts.normals))[:rows]:
        table.add_row(str(int(t)), np.array2string(p.numpy(), precision=4, suppress_small=True), f"{1e3 * float(d):+.3f}",
                      np.array2string(n.numpy(), precision=2))
    return table


def run_demo(out_dir: str = "out/demo") -> dict:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    scene, note = demo_scene()
    console.print(note)
    contacts = run_scene(scene)
    paths = write_outputs(scene, contacts, Path(out_dir))

    console.print(contacts_table(scene, contacts))
    if len(contacts) > CONTACT_ROWS:
        console.print(f"... {len(contacts) - CONTACT_ROWS} more in {paths['json']}")

    rows = error_vs_runtime(scene)
    et = Table(title="error against run time on the candidate triangles (medians of 3 calls)")
    for col in ("method", "optimality mean", "optimality p90", "ms / triangle"):
        et.add_column(col)
    for r in rows:
        et.add_row(r["method"], f"{r['optimality_mean']:.2e}", f"{r['optimality_p90']:.2e}", f"{r['ms_per_triangle']:.4f}")
    console.print(et)
    console.print(f"wrote {paths['json']} and {paths['png']}")
    return {"contacts": len(contacts), "paths": paths, "error_vs_runtime": rows}
