"""Collision scenes: a TOML file names an SDF object, a mesh object, their poses and a method.

```toml
name = "mug-rack"
method = "amortized"      # fw | pgd | voxel-fw | amortized
margin = 0.001
refine = 0                # FW steps warm-started from the method's answer

[sdf]
model = "mugs"            # a packaged model by name (zoo.load), with
shape = "hoi4d_mug_0001"  # one of its shapes; or `fit = "new_mug.obj"` to fit_codes a mesh (every load)
# scale = 0.2             # the shape this many times larger (a source mesh in other units than metres)
# codes = "new_mug.safetensors"   # or a shape fitted once and saved (shape.save, `zoo fit-codes --out`):
#                                 # loads the model it names, or `model`'s if given (refused if not the same)
# analytic = "sphere", params = { radius = 0.05 }   # an analytic SDF instead of a model
pose = { translation = [0, 0, 0], rotation_deg = [0, 0, 0] }   # xyz Euler angles, degrees; or a 4x4 list

[mesh]
procedural = "rack"       # zoo.parts: rack | holder | plane, with `params = {...}`
# file = "rack/ndf_simple_rack.obj"   # or a mesh file: relative to the scene file, then $ZOO_DATA
scale = 1.0               # e.g. 0.001 for a mesh in millimetres
pose = { translation = [0, 0, 0] }
```

A scene loads only the model it names and builds a voxel grid only for ``voxel-fw``. A scene is
named by its path or, for the bundled ones (the project's ``scenes/``, the wheel's ``zoo/data/scenes``),
by its bare name: ``load_collision_scene("demo-mug-rack")`` (:func:`resolve_scene`). Its picture is drawn by
:mod:`zoo.scene_picture` (matplotlib, imported only then).
"""

from __future__ import annotations

import importlib.util
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import zoo
from zoo.errors import DataError, InputError
from zoo.files import atomic_write_text
from zoo.meshes import load_mesh
from zoo.registry import toml_parser
from zoo.resources import bundled

tomllib = toml_parser()

ANALYTIC = {"sphere": zoo.Sphere, "box": zoo.Box, "torus": zoo.Torus, "capsule": zoo.Capsule}


@dataclass
class Scene:
    name: str
    sdf: object
    mesh: object  # trimesh.Trimesh
    sdf_pose: np.ndarray
    mesh_pose: np.ndarray
    method: str = "fw"
    margin: float = 1e-3
    refine: int = 0
    iters: int | None = None
    sdf_label: str = ""
    mesh_label: str = ""
    timings: dict = field(default_factory=dict)


def pose_matrix(spec: dict | list | None) -> np.ndarray:
    """A 4x4 world-from-object transform from ``{translation, rotation_deg}`` or a 4x4 list."""
    if spec is None:
        return np.eye(4)
    if isinstance(spec, list):
        m = np.asarray(spec, dtype=np.float64)
        if m.shape != (4, 4):
            raise InputError(f"a pose given as a matrix must be 4x4, got shape {m.shape}")
        return m
    unknown = set(spec) - {"translation", "rotation_deg"}
    if unknown:
        raise InputError(f"unknown pose keys {sorted(unknown)}; use translation = [x, y, z] and rotation_deg = [rx, ry, rz]")
    import trimesh

    rx, ry, rz = np.radians(spec.get("rotation_deg", [0, 0, 0]))
    m = trimesh.transformations.euler_matrix(rx, ry, rz, axes="sxyz")
    m[:3, 3] = spec.get("translation", [0, 0, 0])
    return m


def scene_folders() -> list[Path]:
    """Where bundled scene files live (:func:`zoo.resources.bundled`): the project's top-level
    ``scenes/`` in a clone or an editable install, else the installed wheel's copy."""
    return [bundled("scenes")]


def resolve_scene(name: str | os.PathLike) -> Path:
    """A scene file from a path or a bare name: ``"demo-mug-rack"`` or ``"scenes/demo-mug-rack.toml"``.

    Looks at the path as given, then for ``<name>.toml`` in each of :func:`scene_folders`.
    """
    given = Path(name)
    if given.is_file():
        return given
    filename = given.name if given.suffix == ".toml" else f"{given.name}.toml"
    for folder in scene_folders():
        if (folder / filename).is_file():
            return folder / filename
    bundled = sorted({p.stem for folder in scene_folders() if folder.is_dir() for p in folder.glob("*.toml")})
    raise DataError(f"scene file {name} does not exist (looked at the path, then for {filename} in "
                    f"{', '.join(str(f) for f in scene_folders())}); give a path or one of: {', '.join(bundled) or 'none'}")


def read_scene(path: str | os.PathLike) -> tuple[dict, Path]:
    """(the scene's table, its file): a path or a bundled scene's name (:func:`resolve_scene`), TOML."""
    path = resolve_scene(path)
    try:
        return tomllib.loads(path.read_text()), path
    except tomllib.TOMLDecodeError as exc:
        raise DataError(f"scene file {path} is not valid TOML: {exc}") from exc


def load_collision_scene(path: str | os.PathLike) -> Scene:
    """Read a scene file (a path, or a bundled scene's name: :func:`resolve_scene`) and build its SDF
    and mesh (loading only the model it names)."""
    spec, path = read_scene(path)
    return scene_from_dict(spec, base_dir=path.parent)


def scene_from_dict(spec: dict, base_dir: Path = Path(".")) -> Scene:
    for key in ("sdf", "mesh"):
        if key not in spec:
            raise InputError(f"a scene needs a [{key}] table; see `zoo collide --help` for the format")
    t0 = time.perf_counter()
    sdf, sdf_label = build_sdf(spec["sdf"], base_dir)
    t1 = time.perf_counter()
    mesh, mesh_label = build_mesh(spec["mesh"], base_dir)
    t2 = time.perf_counter()
    return Scene(
        name=spec.get("name", "scene"),
        sdf=sdf,
        mesh=mesh,
        sdf_pose=pose_matrix(spec["sdf"].get("pose")),
        mesh_pose=pose_matrix(spec["mesh"].get("pose")),
        method=spec.get("method", "fw"),
        margin=float(spec.get("margin", 1e-3)),
        refine=int(spec.get("refine", 0)),
        iters=spec.get("iters"),
        sdf_label=sdf_label,
        mesh_label=mesh_label,
        timings={"load_sdf_s": t1 - t0, "load_mesh_s": t2 - t1},
    )


def build_sdf(spec: dict, base_dir: Path):
    if "scale" in spec:  # a source mesh in other units than metres: the shape `scale` times larger
        sdf, label = build_sdf({k: v for k, v in spec.items() if k != "scale"}, base_dir)
        if not callable(getattr(sdf, "scaled", None)):
            raise InputError(f"[sdf] scale applies to a model's shape (model, codes); {type(sdf).__name__} cannot be scaled")
        return sdf.scaled(spec["scale"]), f"{label} x{spec['scale']}"
    if "analytic" in spec:
        kind = spec["analytic"]
        if kind not in ANALYTIC:
            raise InputError(f"unknown analytic SDF {kind!r}; choose one of {sorted(ANALYTIC)}")
        return ANALYTIC[kind](**spec.get("params", {})), kind
    if "codes" in spec:  # a shape file (shape.save, `zoo fit-codes --out`): its own model unless `model` names one
        codes_path = _resolve_file(spec["codes"], base_dir)
        shape = zoo.load_shape(codes_path, model=spec.get("model"))
        return shape, f"{shape.model.name}@{shape.model.version}:{codes_path.name}"
    if "model" not in spec:
        raise InputError("[sdf] needs `model` (with `shape` or `fit`), `codes` (a saved shape file) or `analytic`")
    model = zoo.load(spec["model"])
    if "fit" in spec:
        mesh_path = _resolve_file(spec["fit"], base_dir)
        return model.fit_codes(mesh_path), f"{model.name}@{model.version}:fit({mesh_path.name})"
    shape = spec.get("shape", model.shapes[0])
    return model.shape(shape), f"{model.name}@{model.version}:{shape}"


def build_mesh(spec: dict, base_dir: Path):
    if "procedural" in spec:
        from .parts import make_part  # trimesh's creation and remeshing: only for a scene that builds a part

        mesh, label = make_part(spec["procedural"], **spec.get("params", {})), f"procedural:{spec['procedural']}"
    elif "file" in spec:
        path = _resolve_file(spec["file"], base_dir)
        mesh, label = load_mesh(path), str(path.name)
    else:
        raise InputError("[mesh] needs `procedural` or `file`")
    scale = float(spec.get("scale", 1.0))
    if scale != 1.0:
        mesh = mesh.copy()
        mesh.apply_scale(scale)
    return mesh, label


def _resolve_file(name: str, base_dir: Path) -> Path:
    """A path as given, else relative to the scene file, else relative to $ZOO_DATA."""
    candidates = [Path(name), base_dir / name]
    if os.environ.get("ZOO_DATA"):
        candidates.append(Path(os.environ["ZOO_DATA"]) / name)
    for c in candidates:
        if c.is_file():
            return c
    raise DataError(f"file {name!r} not found (looked in {', '.join(str(c) for c in candidates)}); set ZOO_DATA or fix the path")


def run_scene(scene: Scene, warm: bool = True) -> zoo.Contacts:
    """Collide the scene; the time of the first call goes into ``scene.timings['first_collide_s']``.

    A process's first collide also pays for one-time work (lazy imports, torch's first kernels, the
    grid of "voxel-fw"), many times a collide's own cost; with ``warm``, the scene is collided a
    second time and that call's time is ``scene.timings['collide_s']`` (without, the first call's).
    """
    # trimesh stores float64; the SDF networks run faster in float32, precise enough for contacts
    mesh = (np.asarray(scene.mesh.vertices, dtype=np.float32), np.asarray(scene.mesh.faces))

    def collide():
        return zoo.collide(
            scene.sdf, mesh, sdf_pose=scene.sdf_pose.astype(np.float32), mesh_pose=scene.mesh_pose.astype(np.float32),
            margin=scene.margin, method=scene.method, refine=scene.refine, iters=scene.iters,
        )

    t0 = time.perf_counter()
    contacts = collide()
    scene.timings["first_collide_s"] = scene.timings["collide_s"] = time.perf_counter() - t0
    if warm:
        t0 = time.perf_counter()
        contacts = collide()
        scene.timings["collide_s"] = time.perf_counter() - t0
    return contacts


def contacts_summary(scene: Scene, contacts) -> dict:
    """JSON-ready description of a scene's contacts."""
    depths = contacts.depths.double()
    return {
        "scene": scene.name,
        "sdf": scene.sdf_label,
        "mesh": scene.mesh_label,
        "method": scene.method,
        "refine": scene.refine,
        "margin": scene.margin,
        "n_triangles": contacts.n_triangles,
        "n_candidates": contacts.n_candidates,
        "n_contacts": len(contacts),
        "min_depth": float(depths.min()) if len(contacts) else None,
        "timings_s": scene.timings,
        "contacts": [
            {"triangle": int(t), "point": p.tolist(), "depth": float(d), "normal": n.tolist()}
            for t, p, d, n in zip(contacts.triangles, contacts.points.double(), depths, contacts.normals.double())
        ],
    }


def write_outputs(scene: Scene, contacts, out_dir: str | os.PathLike) -> dict[str, Path | None]:
    """Write ``<name>.json`` and ``<name>.png`` (both objects and their contacts: :mod:`zoo.scene_picture`) into ``out_dir``.

    The picture needs matplotlib (``sdfzoo[pipeline]``); without it ``"png"`` is None and the
    contacts are still written, since a runtime install need not draw.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path, png_path = out / f"{scene.name}.json", out / f"{scene.name}.png"
    atomic_write_text(json_path, json.dumps(contacts_summary(scene, contacts), indent=1))
    if importlib.util.find_spec("matplotlib") is None:
        return {"json": json_path, "png": None}
    from .scene_picture import plot_scene

    plot_scene(scene, contacts, png_path)
    return {"json": json_path, "png": png_path}
