"""benches/sim_references.py: MuJoCo's SDF-plugin nut turns down its bolt's thread; CoACD's pieces are
convex, cover a cup's wall and leave its inside empty, and are cached. Needs no real meshes."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("mujoco")

from sdfzoo.benches import sim_references as refs  # noqa: E402


def _plugin_missing() -> bool:
    try:
        refs.plugin_library()
    except FileNotFoundError:
        return True
    return False


@pytest.mark.skipif(_plugin_missing(), reason="this mujoco wheel ships no libsdf_plugin.so (mujoco/plugin)")
def test_plugin_nut_stays_on_the_bolt_and_advances_one_pitch_per_turn():
    result = refs.mujoco_sdf_plugin("bolt-nut", seconds=0.2)
    assert result["steps"] == 100 and result["contacts_per_step"] > 0
    check = result["check"]
    # tightening (clockwise from +z) a right-hand thread: the nut turns negative and goes down
    assert check["turns"] < -0.01 and check["advance_mm"] < 0, check
    # the thread guides it: on the axis, upright, 2 mm (the scaled pitch) per turn within 15%
    assert check["nut_off_axis_mm_max"] < 0.5 and check["nut_tilt_deg_max"] < 3.0, check
    assert abs(result["advance_per_turn_mm"] - 2.0) < 0.3, check


def _cup(inner=0.02, wall=0.004, height=0.03, floor=0.004):
    """A closed, non-convex cup (wall on a floor), (V, 3) and (F, 3)."""
    from zoo.parts import holder

    mesh = holder(inner_radius=inner, wall=wall, height=height, floor=floor, max_edge=0.02)
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


@pytest.mark.slow  # CoACD on a 48-sided cup: ~75 s on one core
def test_coacd_pieces_are_convex_cover_the_wall_and_leave_the_inside_empty(tmp_path):
    import trimesh

    pytest.importorskip("coacd", reason="the CoACD reference needs `pip install coacd==1.0.14` (MIT), not a dependency of sdfzoo")

    vertices, faces = _cup()
    pieces, info = refs.decompose(vertices, faces, "cup-test", cache=tmp_path)
    assert not info["cached"] and len(pieces) >= 3  # a cup is no one convex piece
    hulls = [trimesh.Trimesh(v, f).convex_hull for v, f in pieces]
    for (v, f), hull in zip(pieces, hulls):
        assert abs(trimesh.Trimesh(v, f).volume - hull.volume) <= 1e-3 * hull.volume + 1e-12  # each piece is its own hull

    def inside_any(points):
        return np.any([h.contains(points) for h in hulls], axis=0)

    rng = np.random.default_rng(0)
    angle = rng.uniform(0, 2 * np.pi, 400)
    z = rng.uniform(-0.002, 0.028, 400)
    wall = np.stack([0.022 * np.cos(angle), 0.022 * np.sin(angle), z], axis=1)  # mid-wall
    cavity = np.stack([0.012 * np.cos(angle), 0.012 * np.sin(angle), rng.uniform(0.006, 0.028, 400)], axis=1)
    assert inside_any(wall).mean() > 0.95
    assert inside_any(cavity).mean() < 0.05  # the concavity survived: a bottle can go in
    again, info = refs.decompose(vertices, faces, "cup-test", cache=tmp_path)
    assert info["cached"] and len(again) == len(pieces)
    assert all(np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1]) for a, b in zip(again, pieces))
