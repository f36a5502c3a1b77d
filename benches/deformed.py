"""A category of many meshes made from a few real ones, by seeded random deformations.

`zoo fit-category` at scale is checked (tests) and measured (`zoo bench --fit-scale`) on categories
larger than the shared folder holds: each real mesh gives several variants, each under a non-uniform
scale, a taper (the cross-section grows or shrinks with the height) and a bend (the shape curves
along its height), drawn from a seed. Variants are written in every format a user brings (.obj,
.ply, .stl, .glb) into two sources (sub-folders); optionally one file is truncated, as a broken
download would leave it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

FORMATS = ("obj", "ply", "stl", "glb")


@dataclass(frozen=True)
class DeformedCategory:
    """What :func:`build_deformed_category` wrote: the folder, every mesh file, and the truncated one."""

    folder: Path
    files: list[Path]
    truncated: Path | None


def deform(vertices: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Vertices (V, 3), z up, under a random non-uniform scale, taper and bend; -> (V, 3)."""
    lo, hi = vertices.min(0), vertices.max(0)
    centre, size = (lo + hi) / 2, float((hi - lo).max())
    p = (vertices - centre) / size  # within [-0.5, 0.5]
    p = p * rng.uniform(0.75, 1.3, 3)  # non-uniform scale
    height = p[:, 2:3] - p[:, 2].min()  # 0 at the base
    taper = rng.uniform(-0.35, 0.35)
    p[:, :2] *= 1 + taper * height / max(float(height.max()), 1e-9)
    bend = rng.uniform(-0.3, 0.3)  # the axis curves sideways with the square of the height
    p[:, 0] += bend * height[:, 0] ** 2
    return p * size + centre


def build_deformed_category(sources: list[Path], folder: Path, variants: int = 4, seed: int = 0,
                            truncate: bool = True) -> DeformedCategory:
    """``variants`` deformed copies of each mesh of ``sources`` under ``folder`` (two sub-folders, every format);
    with ``truncate``, one more file, a .ply cut in half. -> what was written."""
    import trimesh

    from zoo.meshes import load_mesh

    folder = Path(folder)
    files = []
    for i, source in enumerate(sources):
        mesh = load_mesh(source)
        for k in range(variants):
            rng = np.random.default_rng([seed, i, k])
            variant = trimesh.Trimesh(deform(np.asarray(mesh.vertices), rng), np.asarray(mesh.faces), process=False)
            fmt = FORMATS[(i * variants + k) % len(FORMATS)]
            path = folder / ("scans" if k % 2 else "cad") / f"{Path(source).stem}_v{k}.{fmt}"
            path.parent.mkdir(parents=True, exist_ok=True)
            variant.export(path, file_type=fmt)
            files.append(path)
    truncated = None
    if truncate:
        truncated = folder / "scans" / "broken_download.ply"
        data = trimesh.creation.icosphere(3).export(file_type="ply")
        truncated.write_bytes(data[: len(data) // 2])
        files.append(truncated)
    return DeformedCategory(folder, files, truncated)


def smallest_meshes(folder: Path, n: int) -> list[Path]:
    """The ``n`` smallest mesh files of ``folder`` (by size: quick to sample), by name for ties."""
    from zoo.meshes import MESH_SUFFIXES

    files = [p for p in Path(folder).iterdir() if p.suffix.lower() in MESH_SUFFIXES]
    return sorted(files, key=lambda p: (p.stat().st_size, p.name))[:n]
