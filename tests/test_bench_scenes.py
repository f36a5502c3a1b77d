"""The scene benchmark (Table II analog) and the paper's four scene files.

Fast: the benchmark runs on a small analytic scene with an exact detector; the four scene files
are checked for what they name (models, shapes, mesh files), not collided (that needs the
models and ../shared, and is what `zoo bench --scenes` does).
"""

import json
from pathlib import Path

import numpy as np
import pytest
import torch

import zoo
from sdfzoo.benches import scenes as bench_scenes
from sdfzoo.benches.scenes import (
    PAPER_SCENES,
    BenchScene,
    matched_iterations,
    measure_scene,
    peak_memory_in_child,
    scene_paths,
    voxel_region,
)
from sdfzoo.pipeline.categories import load_category
from zoo.collision import DEFAULT_ITERS
from zoo.registry import toml_parser
from zoo.scenes import scene_from_dict

tomllib = toml_parser()
ROOT = Path(__file__).resolve().parent.parent


class SphereWithCentroidDetector(zoo.Sphere):
    """A sphere whose "detector" answers the centroid: cheap, and worse than FW, so matching is visible."""

    def detect(self, triangles):
        return torch.full(triangles.shape[:2], 1 / 3, dtype=triangles.dtype)


def small_scene(tmp_path=None) -> BenchScene:
    spec = {
        "name": "ball-plane", "margin": 0.002,
        "sdf": {"analytic": "sphere", "params": {"radius": 0.05}, "pose": {"translation": [0.01, -0.02, 0.049]}},
        "mesh": {"procedural": "plane", "params": {"size": 0.2, "max_edge": 0.01}},
    }
    scene = scene_from_dict(spec)
    scene.sdf = SphereWithCentroidDetector(0.05)
    return BenchScene(scene, "model", torch.as_tensor(np.asarray(scene.mesh.vertices), dtype=torch.float32),
                      torch.as_tensor(np.asarray(scene.mesh.faces)))


def test_the_four_scene_files_name_packaged_categories_and_staged_meshes():
    expected = {"mug-rack": ("mugs", "rack/ndf_simple_rack.obj"), "bolt-nut": ("bolts", "nut/factory_nut_m16.obj"),
                "gear-gear": ("gears", "gear/industreal_gear_medium.obj"), "bottle-holder": ("bottles", None)}
    staged = {m.file for c in ("scene_parts", "nuts", "gears") for m in load_category(c).meshes.values()}
    for path in scene_paths():
        spec = tomllib.loads(path.read_text())
        model, mesh_file = expected[spec["name"]]
        assert spec["sdf"]["model"] == model and spec["method"] == "amortized"
        assert spec["sdf"]["shape"] in load_category(model).train_stems  # a fitted shape of the model
        if mesh_file is None:
            assert spec["mesh"]["procedural"] == "holder"
        else:
            assert spec["mesh"]["file"] == mesh_file and mesh_file in staged
    assert [p.stem for p in scene_paths()] == list(PAPER_SCENES)


def test_matched_iterations_is_the_first_sweep_row_at_the_target():
    sweep = [{"iters": k, "optimality_mean": 1.0 / k} for k in (1, 2, 5, 10)]
    assert matched_iterations(sweep, 0.3) == 5
    assert matched_iterations(sweep, 1e-6) == 10  # none reaches it: the last swept
    assert matched_iterations(sweep, None) == DEFAULT_ITERS["fw"]  # no detector: FW's default


def test_the_fw_sweep_goes_on_only_until_it_matches_the_target():
    sphere = zoo.Sphere(0.1)
    gen = torch.Generator().manual_seed(3)
    tri = torch.tensor([0.13, 0.0, 0.0], dtype=torch.float64) + 0.05 * torch.randn(6, 3, 3, generator=gen, dtype=torch.float64)
    base = bench_scenes.fw_sweep(sphere, tri, iters=(1, 2))
    assert [r["iters"] for r in base] == [1, 2]  # no target: the given counts only
    assert [r["iters"] for r in bench_scenes.fw_sweep(sphere, tri, iters=(1, 2), until=1.0)] == [1, 2]  # matched already
    full = bench_scenes.fw_sweep(sphere, tri, iters=(1, 2), until=-1.0)  # never matched: every extension
    assert [r["iters"] for r in full] == [1, 2, *bench_scenes.FW_SWEEP_EXTENSION]
    at_first = full[2]["optimality_mean"]  # matched by the first extension: it stops there
    assert [r["iters"] for r in bench_scenes.fw_sweep(sphere, tri, iters=(1, 2), until=at_first)] == [1, 2, full[2]["iters"]]
    assert full[0]["optimality_mean"] > full[-1]["optimality_mean"]  # the extension is what FW reaches with more steps


def test_voxel_region_has_the_full_grids_spacing_and_holds_the_candidates():
    sphere = zoo.Sphere(0.1)
    tri = torch.tensor([[[0.09, 0.0, 0.0], [0.1, 0.01, 0.0], [0.1, 0.0, 0.01]]])
    lo, hi, samples, full_bytes = voxel_region(sphere, tri, 256, margin=1e-3)
    full_spacing = (0.2 * 1.1) / 255
    np.testing.assert_allclose(((hi - lo) / (torch.tensor(samples) - 1)).numpy(), full_spacing, rtol=1e-5)
    assert bool((lo <= tri.reshape(-1, 3).double().amin(0)).all() & (hi >= tri.reshape(-1, 3).double().amax(0)).all())
    assert full_bytes == 256**3 * 4 and np.prod(samples) < 30**3


def test_the_voxel_part_is_the_grid_collide_uses():
    from zoo.collision import clear_voxel_cache

    sphere = zoo.Sphere(0.1)
    vertices = np.array([[0.09, -0.02, -0.02], [0.09, 0.02, -0.02], [0.09, 0.0, 0.03]])
    mesh = (vertices, np.array([[0, 1, 2]]))
    lo, hi, samples, _ = voxel_region(sphere, torch.as_tensor(vertices[None]), 64, margin=1e-3)
    grid = bench_scenes.install_voxel_part(sphere, 64, lo, hi, samples)
    c = zoo.collide(sphere, mesh, method="voxel-fw", voxel_resolution=64, margin=1e-3)
    clear_voxel_cache()
    torch.testing.assert_close(c.depths, grid(c.points).to(c.depths))  # reported on the part, not a new grid
    assert len(c) == 1 and float(c.depths[0]) == pytest.approx(-0.01, abs=2e-4)


def test_measure_scene_gives_every_row_of_table_ii():
    bs = small_scene()
    report = measure_scene(bs, repeats=1, memory=False, progress=lambda *_: None)
    rows = {r["method"]: r for r in report["rows"]}
    assert list(rows) == list(bench_scenes.METHODS)
    assert report["n_triangles"] == len(bs.faces) and 0 < report["n_candidates"] < report["n_triangles"]
    # the centroid "detector" is matched by few FW iterations; more are never needed
    assert report["fw_matched_iters"] <= 3 and report["amortized_optimality_mean"] > 0
    assert rows["fw-matched"]["kwargs"] == {"method": "fw", "iters": report["fw_matched_iters"]}
    for name, r in rows.items():
        assert r["time_s"] > 0 and r["n_candidates"] == report["n_candidates"], name
        assert r["n_contacts"] > 0
    assert rows["voxel-fw-512"]["grid_bytes_full"] == 512**3 * 4
    assert rows["voxel-fw-512"]["grid_samples_built"] < 512**3 / 20  # only the part the candidates reach is built
    narrow = report["narrow_phase"]
    assert narrow["ratio"] > 0 and narrow["detect_only_ratio"] > 0
    assert narrow["detect_s"] == narrow["collide_phases_s"]["narrow"]
    assert narrow["ratio_of_medians"] == narrow["detect_s"] / narrow["value_and_grad_s"]
    assert narrow["rounds"] == bench_scenes.NARROW_ROUNDS_PER_REPEAT
    speedup = report["speedup"]  # timed interleaved, at the matched iterations
    assert speedup["fw_iters"] == report["fw_matched_iters"] and speedup["speedup"] > 0 and speedup["repeats"] == 1
    for r in rows.values():  # collide's phases and the time per candidate
        assert set(r["phases_s"]) == {"broad", "narrow", "normals"}
        assert r["per_candidate_ms"] == pytest.approx(1e3 * r["time_s"] / r["n_candidates"])
    json.dumps(report)  # JSON-ready


def test_the_paper_scale_bolt_nut_scene_is_the_bolt_nut_scene_with_the_nut_raised_in_phase():
    base = tomllib.loads((ROOT / "scenes" / "bolt-nut.toml").read_text())
    start = tomllib.loads((ROOT / "scenes" / "bolt-nut-start.toml").read_text())
    assert start["sdf"] == base["sdf"] and start["mesh"]["file"] == base["mesh"]["file"] and start["margin"] == base["margin"]
    dz, turn = start["mesh"]["pose"]["translation"][2], start["mesh"]["pose"]["rotation_deg"][2]
    pitch = 0.002  # M16 coarse thread
    turns = dz / pitch - turn / 360
    assert turns == pytest.approx(round(turns), abs=1e-9) and round(turns) > 0  # raised by whole turns of the helix
    assert bench_scenes.PAPER_TABLE_II["bolt-nut-start"] == bench_scenes.PAPER_TABLE_II["bolt-nut"]


def test_interleaved_timing_and_the_contact_checks_counts():
    calls = []
    seconds, results = bench_scenes.interleaved_seconds({"a": lambda: calls.append("a") or 1, "b": lambda: calls.append("b") or 2}, 3)
    assert calls == ["a", "b"] * 4 and results == {"a": [1, 1, 1], "b": [2, 2, 2]} and set(seconds) == {"a", "b"}
    # ratios pair the calls of one round: the median of 2/1, 4/1, 9/3, not a ratio of medians (4/1)
    assert bench_scenes.paired_ratio([2.0, 4.0, 9.0], [1.0, 1.0, 3.0]) == 3.0
    with pytest.raises(ValueError):
        bench_scenes.paired_ratio([1.0, 2.0], [1.0])

    class Found:
        triangles = torch.tensor([1, 2, 3, 9])  # 9 is not counted (its centroid lies within the margin)

    rp = bench_scenes.recall_precision(Found(), reference={1, 2, 4, 5}, counted={1, 2, 3, 4, 5})
    assert rp["recall"] == 0.5 and rp["precision"] == pytest.approx(2 / 3) and rp["missed"] == [4, 5] and rp["extra"] == [3]


def test_a_scene_without_its_model_runs_on_a_labelled_stand_in_or_says_why(monkeypatch):
    bs = small_scene()
    bs.sdf_kind = "stand-in (ModelNotFoundError)"
    report = measure_scene(bs, methods=("amortized", "fw-matched"), repeats=1, memory=False, progress=lambda *_: None)
    amortized, fw = report["rows"]
    assert "no detector" in amortized["skipped"] and fw["n_contacts"] > 0 and report["fw_matched_iters"] == DEFAULT_ITERS["fw"]


def test_peak_memory_comes_from_a_child_process(tmp_path):
    """The child's own peak (VmHWM), not this process's: ru_maxrss survives exec, so a child of a large process
    would report the parent's size; here the parent holds 400 MB more than the child ever does."""
    import resource

    ballast = torch.ones(100_000_000)  # 400 MB, held while the child runs
    scene = tmp_path / "ball.toml"
    scene.write_text(
        'name = "ball"\nmargin = 0.002\n[sdf]\nanalytic = "sphere"\nparams = { radius = 0.05 }\n'
        'pose = { translation = [0.0, 0.0, 0.049] }\n[mesh]\nprocedural = "plane"\nparams = { size = 0.2, max_edge = 0.02 }\n'
    )
    mem = peak_memory_in_child(scene, "fw-matched", 10, 5, str(tmp_path / "standins"))
    parent_peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # Linux: KiB
    assert mem["peak_rss_mb"] >= mem["peak_rss_loaded_mb"] > 0
    assert mem["peak_rss_mb"] < parent_peak_mb - 300, (mem, parent_peak_mb)
    assert mem["collide_extra_mb"] == pytest.approx(mem["peak_rss_mb"] - mem["peak_rss_loaded_mb"])
    assert mem["collide_extra_mb"] < 64, mem  # Frank-Wolfe on the plane's 200 triangles: a few MB
    del ballast
