"""zoo.proxy: the narrow-band baked proxy of an SDF, its cache, and CoherentCollider(proxy=) on it.

The proxy is held against the analytic SDFs (exact answers) and the mugs NeuralSDF on held-out points; its lower
bounds out of band against the true values; the lazy proxy against the eager one (the same answers, bricks baked only
where read, saved, reloaded and baked on); the cache keyed, reused, refused when corrupt and rebuilt; and the
proxy-screened collider's contacts against the full CoherentCollider and zoo.collide at the same poses.
"""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
import torch
from test_coherence import plane_mesh, pose, rotation, slide_along_peg, sphere_rolling_over_plane
from tiny_packages import flip_byte

import zoo
from zoo.errors import ChecksumError, DataError, InputError
from zoo.geometry import invert_pose, transform_points
from zoo.proxy import (
    ABOVE,
    BRICK,
    ERROR_BRICKS,
    IN_BAND,
    NOT_READY,
    PROXY_FILE,
    UNKNOWN,
    bake_proxy,
    cached_proxy,
    default_band,
    default_spacing,
    load_proxy,
    proxy_key,
    save_proxy,
)


def shell_points(sdf, n: int, reach: float, seed: int = 0) -> torch.Tensor:
    """(n, 3) random points within about ``reach`` of a sphere-like SDF's surface: random directions from the centre,
    projected on the surface by one Newton step and moved along the gradient."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (torch.as_tensor(b, dtype=torch.float64) for b in sdf.bounds)
    p = lo + (hi - lo) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    d, grad = sdf.value_and_grad(p)
    surface = p - d.unsqueeze(-1) * grad
    offset = reach * (2 * torch.rand(n, 1, generator=g, dtype=torch.float64) - 1)
    return (surface + offset * grad).float()


@pytest.fixture(scope="module")
def sphere_proxy():
    sphere = zoo.Sphere(0.05, center=(0.01, 0.0, -0.02))
    return sphere, bake_proxy(sphere, margin=1e-3, spacing=1e-3)


@pytest.fixture(scope="module")
def mug():
    return zoo.load("mugs").shape("hoi4d_mug_0001")


@pytest.fixture(scope="module")
def mug_proxy(mug):
    """The mug's proxy on a coarse grid (2 mm: a second's bake; the default for the mug is 0.49 mm)."""
    return bake_proxy(mug, margin=1e-3, spacing=2e-3)


# -- reading --------------------------------------------------------------------------------------


def test_defaults_follow_the_size_and_the_margin(mug):
    assert default_spacing(mug.bounds, 1e-3) == pytest.approx(float((mug.bounds[1] - mug.bounds[0]).max()) / 256)
    assert default_spacing(((0, 0, 0), (0.041, 0.041, 0.041)), 1e-4) == pytest.approx(1e-4)  # the bolt: the margin
    assert default_spacing(((0, 0, 0), (1.0, 1.0, 1.0)), 0.0) == pytest.approx(1 / 256)
    assert default_band(1e-3, 5e-4) == pytest.approx(2e-3)


def test_sphere_in_band_within_the_error_bound(sphere_proxy):
    sphere, proxy = sphere_proxy
    assert 0 < proxy.error["max"] < 1e-5 and proxy.error_bound == pytest.approx(2 * proxy.error["max"])
    points = shell_points(sphere, 20_000, 1.5e-3, seed=3)  # the band is 3 mm
    values, grads, status = proxy.read(points)
    truth, truth_grad = sphere.value_and_grad(points)
    assert bool((status == IN_BAND).all())  # everything within the band is read in band
    assert float((values - truth).abs().max()) <= proxy.error_bound
    assert float((grads - truth_grad).norm(dim=-1).max()) < 0.05  # the interpolant's gradient: O(h / radius)
    assert values.dtype == torch.float32 and grads.shape == (20_000, 3) and status.dtype == torch.int8
    d64 = proxy(points.double())
    assert d64.dtype == torch.float64 and torch.allclose(d64.float(), values, atol=1e-6)


def test_out_of_band_values_are_lower_bounds(sphere_proxy):
    sphere, proxy = sphere_proxy
    g = torch.Generator().manual_seed(1)
    lo, hi = (b.double() for b in sphere.bounds)
    points = (lo - 0.03 + (hi - lo + 0.06) * torch.rand(50_000, 3, generator=g, dtype=torch.float64)).float()
    values, grads, status = proxy.read(points)
    truth = sphere(points)
    inside = status == IN_BAND
    assert bool((values[inside] <= truth[inside] + proxy.error_bound).all())
    assert bool((values[~inside] <= truth[~inside] + 1e-6).all())  # a lower bound wherever the proxy is out of band
    above, unknown = status == ABOVE, status == UNKNOWN
    assert above.sum() > 1000 and unknown.sum() > 1000  # far outside, and deep inside
    assert bool((values[above] >= proxy.band).all()) and bool((truth[above] >= proxy.band).all())
    assert bool((truth[unknown] < -proxy.band).all())
    assert bool(torch.isfinite(values).all() & torch.isfinite(grads).all())
    outside = (points < proxy.lo.float()).any(-1) | (points > proxy.hi.float()).any(-1)
    assert outside.sum() > 100 and bool((status[outside] == ABOVE).all())


def test_outside_the_region_the_nearest_brick_bounds_a_round_shape_far_from_its_box():
    """Past the corners of a sphere's box the surface is far: the nearest brick's bound says so (not only the band
    plus the distance to the box), in the numpy read and in the compiled one, and a lazy proxy bakes no brick for it."""
    from zoo.proxy_kernel import COUNTS, MISSING, read

    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3, lazy=True)
    baked = proxy.n_baked
    corners = torch.tensor([[1.0, 1.0, 1.0], [-1.0, 1.0, -1.0], [1.0, -1.0, -1.0]], dtype=torch.float64)
    points = corners * (proxy.hi.double() + 2e-3)  # just past the region's corners
    values, _, status = proxy.read(points)
    truth = sphere(points)
    gap = (points - points.clamp(proxy.lo.double(), proxy.hi.double())).norm(dim=-1)
    assert bool((status == ABOVE).all()) and bool((values <= truth + 1e-9).all())
    assert bool((values > proxy.band + gap + 5e-3).all())  # well above what the box alone says
    assert proxy.n_baked == baked  # the coarse values alone, no brick baked
    missing, counts = np.zeros(4, dtype=np.int64), np.zeros(1, dtype=COUNTS)
    compiled = [read(*p, proxy.grid(), missing, counts[0]) for p in points.numpy()]
    assert all(c[4] != MISSING for c in compiled)
    assert np.allclose([c[0] for c in compiled], values.numpy(), atol=1e-9)


def test_box_with_its_kinks(sphere_proxy):
    box = zoo.Box((0.03, 0.02, 0.01))
    proxy = bake_proxy(box, margin=1e-3, spacing=5e-4)
    g = torch.Generator().manual_seed(2)
    points = (torch.rand(30_000, 3, generator=g) * 2 - 1) * torch.tensor([0.033, 0.023, 0.013])
    values, _, status = proxy.read(points)
    truth = box(points)
    near = truth.abs() <= 1e-3
    assert near.sum() > 1000 and bool((status[near] == IN_BAND).all())
    err = (values - truth).abs()[status == IN_BAND]
    # the interpolant cuts the edges and corners by up to about half a cell; the held-out measure saw that too
    assert float(err.max()) <= proxy.error_bound and float(err.median()) < 1e-7
    assert bool((values[status != IN_BAND] <= truth[status != IN_BAND] + 1e-6).all())


@pytest.mark.slow
def test_neural_sdf_within_its_stated_bound_on_held_out_points(mug, mug_proxy):
    proxy = mug_proxy
    assert proxy.error["samples"] > 10_000 and proxy.error["median"] <= proxy.error["p99"] <= proxy.error["max"]
    # other held-out points: uniform in the cells the band holds, another seed
    from zoo.proxy import measure_error

    again = measure_error(proxy, mug, samples=8000, seed=7)
    assert again["max"] <= proxy.error_bound
    points = mug_surface_points(mug, 4000)
    values, _, status = proxy.read(points)
    assert points.shape[0] > 3000
    assert bool((status == IN_BAND).all())
    assert float((values - mug(points)).abs().max()) <= proxy.error_bound


def mug_surface_points(mug, n: int) -> torch.Tensor:
    """(at most n, 3) points within 1 mm of the mug's surface (two Newton steps from random points near it)."""
    g = torch.Generator().manual_seed(11)
    lo, hi = (b.double() for b in mug.bounds)
    p = (lo + (hi - lo) * torch.rand(20 * n, 3, generator=g, dtype=torch.float64)).float()
    d = mug(p)
    p = p[d.abs() < 0.01][:n]
    for _ in range(2):
        d, grad = mug.value_and_grad(p)
        p = p - d.unsqueeze(-1) * grad / grad.norm(dim=-1, keepdim=True).square()
    p = p + 5e-4 * (2 * torch.rand(p.shape[0], 1, generator=g) - 1) * torch.nn.functional.normalize(grad, dim=-1)
    return p[mug(p).abs() < 1e-3]  # where the steps converged


def test_bad_arguments(sphere_proxy):
    sphere, _ = sphere_proxy
    with pytest.raises(InputError, match="band"):
        bake_proxy(sphere, margin=1e-3, band=5e-4)
    with pytest.raises(InputError, match="spacing"):
        bake_proxy(sphere, spacing=-1.0)
    with pytest.raises(InputError, match="is not an SDF"):
        bake_proxy(object())
    with pytest.raises(InputError):
        sphere_proxy[1](torch.tensor([[math.nan, 0.0, 0.0]]))


# -- the cache ------------------------------------------------------------------------------------


@pytest.mark.slow
def test_the_cache_is_keyed_reused_and_refuses_a_corrupt_file(mug, tmp_path, monkeypatch):
    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))
    first = cached_proxy(mug, margin=1e-3, spacing=3e-3)
    folders = list((tmp_path / "proxies").iterdir())
    assert len(folders) == 1 and folders[0].name.startswith("hoi4d_mug_0001-")
    assert sorted(p.name for p in folders[0].iterdir()) == sorted([PROXY_FILE, "SHA256SUMS"])  # nothing half-written left

    import zoo.proxy

    def no_bake(*args, **kwargs):
        raise AssertionError("baked again")

    monkeypatch.setattr(zoo.proxy, "bake_proxy", no_bake)
    again = cached_proxy(mug, margin=1e-3, spacing=3e-3)  # reused: no bake
    assert torch.equal(again.nodes, first.nodes) and torch.equal(again.status, first.status)
    assert again.error == first.error and again.error_bound == first.error_bound
    created = first.nodes.clone()
    probe = mug_surface_points(mug, 200)
    assert torch.equal(again(probe), first(probe))  # both bake the same bricks lazily
    monkeypatch.undo()
    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))

    # other settings, another shape: other keys
    settings = {"spacing": 3e-3, "band": 7e-3, "lipschitz": 2.0}
    key = proxy_key(mug, settings)
    assert key != proxy_key(mug, {**settings, "spacing": 2e-3})
    assert key != proxy_key(zoo.load("mugs").shape("edf_mug1"), settings)
    assert proxy_key(zoo.Sphere(0.1), settings) is None  # only a model's shapes are cached

    # a flipped byte: refused with a typed error, then rebuilt by cached_proxy
    flip_byte(folders[0] / PROXY_FILE, offset=-10)
    with pytest.raises(ChecksumError):
        load_proxy(folders[0])
    with pytest.warns(UserWarning, match="refused the cached proxy"):
        rebuilt = cached_proxy(mug, margin=1e-3, spacing=3e-3)
    assert torch.equal(rebuilt.nodes, created)  # as first was when created
    load_proxy(folders[0])  # verified again
    # no checksums (a write interrupted between the file and its sums): refused, rebuilt
    (folders[0] / "SHA256SUMS").unlink()
    with pytest.raises(DataError):
        load_proxy(folders[0])
    with pytest.warns(UserWarning):
        cached_proxy(mug, margin=1e-3, spacing=3e-3)
    assert (folders[0] / "SHA256SUMS").exists()


def test_saved_under_another_key_is_refused(sphere_proxy, tmp_path):
    _, proxy = sphere_proxy
    save_proxy(proxy, tmp_path / "p", key="abc")
    assert torch.equal(load_proxy(tmp_path / "p", key="abc").nodes, proxy.nodes)
    with pytest.raises(DataError, match="another SDF"):
        load_proxy(tmp_path / "p", key="xyz")
    meta = json.loads(load_proxy(tmp_path / "p").state()[1]["settings"])
    assert meta["spacing"] == proxy.spacing and meta["version"] >= 1


def test_an_uncached_sdf_bakes_without_writing(tmp_path, monkeypatch):
    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))
    proxy = cached_proxy(zoo.Sphere(0.02), margin=1e-3, spacing=1e-3)
    assert proxy.n_baked > 0 and not (tmp_path / "proxies").exists()


# -- lazy baking ----------------------------------------------------------------------------------


def bricks_of(proxy, points: torch.Tensor) -> torch.Tensor:
    """The flat brick indices (N,) of ``points`` (N, 3) in the proxy's region."""
    cell = torch.floor((points.double() - proxy.lo) / proxy.spacing).long()
    brick = cell // BRICK
    nb = proxy.n_bricks
    return (brick[:, 0] * nb[1] + brick[:, 1]) * nb[2] + brick[:, 2]


def probe_points(sdf, n: int, seed: int) -> torch.Tensor:
    """(2n, 3) float32 points: n within 2 mm of the surface of ``sdf`` (sphere-like), n uniform in its bounds grown
    by 1 cm on each side (many far outside the baked region or deep inside)."""
    g = torch.Generator().manual_seed(seed)
    lo, hi = (b.double() for b in sdf.bounds)
    far = lo - 0.01 + (hi - lo + 0.02) * torch.rand(n, 3, generator=g, dtype=torch.float64)
    return torch.cat([shell_points(sdf, n, 2e-3, seed=seed), far.float()])


@pytest.mark.parametrize("sdf", [zoo.Sphere(0.05, center=(0.01, 0.0, -0.02)), zoo.Torus(0.04, 0.012)],
                         ids=["sphere", "torus"])
def test_lazy_reads_equal_eager_reads(sdf):
    eager = bake_proxy(sdf, margin=1e-3, spacing=1e-3)
    lazy = bake_proxy(sdf, margin=1e-3, spacing=1e-3, lazy=True)
    assert lazy.lazy and not eager.lazy and lazy.n_baked == ERROR_BRICKS < eager.n_baked
    assert lazy.error["samples"] > 10_000 and lazy.error["max"] <= 2 * eager.error["max"]
    # coarse to fine down to bricks: the centres far from the surface are not evaluated
    assert int(torch.isfinite(lazy.coarse_value).sum()) < lazy.coarse_value.numel()
    for seed, dtype in ((0, torch.float32), (1, torch.float64)):
        points = probe_points(sdf, 10_000, seed).to(dtype)
        ours, theirs = lazy.read(points), eager.read(points)
        for a, b in zip(ours, theirs):
            assert a.dtype == b.dtype and torch.equal(a, b)
        status = theirs[2]
        assert all(int((status == s).sum()) > 500 for s in (IN_BAND, ABOVE, UNKNOWN))
        assert torch.equal(lazy(points), eager(points))
        assert all(torch.equal(a, b) for a, b in zip(lazy.value_and_grad(points), eager.value_and_grad(points)))
    # everything baked: the same bricks, each with the same cells in band and the same coarse grid
    lazy.bake_all()
    assert lazy.n_pending == 0 and lazy.n_baked == eager.n_baked and not bool((lazy.brick_of == NOT_READY).any())
    assert torch.equal(lazy.coarse_value, eager.coarse_value) and torch.equal(lazy.coarse_grad, eager.coarse_grad)
    bricks = eager.baked_bricks
    assert set(lazy.baked_bricks.tolist()) == set(bricks.tolist())
    cells = BRICK**3
    assert torch.equal(lazy.status.reshape(-1, cells)[lazy.brick_of[bricks]],
                       eager.status.reshape(-1, cells)[eager.brick_of[bricks]])


def test_lazy_bakes_only_the_bricks_read():
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3, lazy=True)
    sample = set(proxy.baked_bricks.tolist())
    assert len(sample) == ERROR_BRICKS and proxy.lazy_bricks == 0
    on_surface = shell_points(sphere, 4000, 0.0, seed=5)
    pending = ~torch.tensor([b in sample for b in bricks_of(proxy, on_surface).tolist()])
    on_surface = on_surface[pending]
    # a few points in one brick: that brick alone
    first = on_surface[:1] + torch.tensor([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, -1e-4, 1e-4]])
    wanted = set(bricks_of(proxy, first).tolist())
    assert len(wanted) == 1
    proxy.read(first)
    assert set(proxy.baked_bricks.tolist()) == sample | wanted and proxy.lazy_bricks == 1
    # far outside the region and deep inside the sphere: no brick there holds band cells, none is baked
    far = torch.tensor([[0.2, 0.0, 0.0], [0.0, -0.3, 0.1], [0.0, 0.0, 0.0], [0.01, 0.02, -0.005]])
    values, _, status = proxy.read(far)
    assert proxy.lazy_bricks == 1 and status.tolist() == [ABOVE, ABOVE, UNKNOWN, UNKNOWN]
    assert bool((values <= sphere(far) + 1e-6).all())
    # many bricks in one read: each of them once, in one batch
    many = on_surface[:300]
    wanted |= set(bricks_of(proxy, many).tolist())
    proxy.read(many)
    assert set(proxy.baked_bricks.tolist()) == sample | wanted and proxy.n_baked == len(sample | wanted)
    assert proxy.lazy_bricks == len(wanted) > 20
    proxy.read(many)  # again: nothing new
    assert proxy.lazy_bricks == len(wanted)
    assert proxy.nodes.numel() == (proxy.n_baked + 1) * 9**3
    # the rows' storage doubles when full: one brick a read grows it a few times, not at every read
    capacities = set()
    for point in on_surface[300:600]:
        proxy.read(point[None])
        capacities.add(proxy._nodes_np.size)
    assert len(capacities) <= 3 and proxy._nodes_np.size <= 2 * proxy.nodes.numel()
    # bake_at: the bricks of the points given, as a read there; bake_all: every brick left
    assert proxy.bake_at(on_surface[600:]) > 0 and proxy.bake_at(on_surface[600:]) == 0
    before = proxy.n_baked
    assert proxy.bake_all() == proxy.n_baked - before > 0 and proxy.n_pending == 0


def test_a_saved_lazy_proxy_reloads_keeps_its_bricks_and_bakes_more(tmp_path):
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3, lazy=True)
    folder = tmp_path / "sphere"
    assert not proxy.flush(force=True)  # no cache folder: nothing to write to
    proxy.attach_cache(folder, key="k")
    assert proxy.flush(force=True) and not proxy.flush()  # written; then nothing new to write
    points = shell_points(sphere, 2000, 1e-3, seed=8)
    proxy.read(points[:1000])
    assert proxy.lazy_bricks > 0 and proxy.flush() and not proxy.flush()
    assert sorted(p.name for p in folder.iterdir()) == sorted([PROXY_FILE, "SHA256SUMS"])
    again = load_proxy(folder, key="k", sdf=sphere)
    assert again.lazy and again.n_baked == proxy.n_baked and again.lazy_bricks == 0
    for name in ("brick_of", "nodes", "status", "coarse_value", "coarse_grad", "baked_bricks"):
        assert np.array_equal(getattr(again, name).numpy(), getattr(proxy, name).numpy(), equal_nan=True), name
    assert again.error == proxy.error and again.error_bound == proxy.error_bound
    assert torch.equal(again(points[:1000]), proxy(points[:1000])) and again.lazy_bricks == 0  # its bricks, kept
    assert all(torch.equal(a, b) for a, b in zip(again.read(points[1000:]), proxy.read(points[1000:])))
    assert again.lazy_bricks > 0  # and more, baked as the first one bakes them
    # loaded without its SDF: what is baked reads, a read that needs a new brick raises
    bare = load_proxy(folder)
    assert torch.equal(bare(points[:1000]), proxy(points[:1000]))
    with pytest.raises(InputError, match="without its SDF"):
        bare(points[1000:])


def test_the_cache_keeps_a_lazy_proxys_bricks_and_refuses_a_corrupt_file(mug, tmp_path, monkeypatch):
    first = cached_proxy(mug, margin=1e-3, spacing=4e-3, cache=tmp_path)
    folder = first.folder
    assert first.lazy and first.n_baked == ERROR_BRICKS and (folder / PROXY_FILE).exists()
    eager_key = proxy_key(mug, {"spacing": 4e-3, "band": first.band, "lipschitz": first.lipschitz, "lazy": False})
    assert first.key != eager_key  # lazy is part of the key
    probe = mug_surface_points(mug, 300)
    values = first(probe)
    baked = first.n_baked
    assert baked > ERROR_BRICKS and first.flush()

    import zoo.proxy

    def no_bake(*args, **kwargs):
        raise AssertionError("baked again")

    monkeypatch.setattr(zoo.proxy, "bake_proxy", no_bake)
    again = cached_proxy(mug, margin=1e-3, spacing=4e-3, cache=tmp_path)  # what first baked, no creation
    assert again.n_baked == baked and again.folder == folder
    assert torch.equal(again(probe), values) and again.lazy_bricks == 0
    lo, hi = (b.double() for b in mug.bounds)
    elsewhere = (lo + (hi - lo) * torch.rand(3000, 3, generator=torch.Generator().manual_seed(4), dtype=torch.float64)).float()
    again(elsewhere)
    assert again.lazy_bricks > 0  # it goes on baking lazily
    monkeypatch.undo()
    zoo.proxy._flush_at_exit()  # what atexit runs: the new bricks written
    assert load_proxy(folder, again.key).n_baked == again.n_baked > baked

    flip_byte(folder / PROXY_FILE, offset=-10)
    with pytest.raises(ChecksumError):
        load_proxy(folder)
    with pytest.warns(UserWarning, match="refused the cached proxy"):
        rebuilt = cached_proxy(mug, margin=1e-3, spacing=4e-3, cache=tmp_path)
    assert rebuilt.n_baked == ERROR_BRICKS  # created afresh, and written
    assert load_proxy(folder, rebuilt.key).n_baked == ERROR_BRICKS


def test_read_numpy_equals_read(sphere_proxy):
    sphere, proxy = sphere_proxy
    points = probe_points(sphere, 2000, seed=9)
    for dtype in (torch.float32, torch.float64):
        p = points.to(dtype)
        ours = proxy.read_numpy(p.numpy())
        for a, b in zip(ours, proxy.read(p)):
            assert np.array_equal(a, b.numpy())
        assert ours[0].dtype == ours[1].dtype == p.numpy().dtype and ours[2].dtype == np.int8
        assert ours[0].shape == (4000,) and ours[1].shape == (4000, 3) and ours[2].shape == (4000,)
        assert ours[1].flags.c_contiguous
    inside = points[:5].numpy()  # all in the region (the one-test path) against the same points among others
    assert all(np.array_equal(a, b[:5]) for a, b in zip(proxy.read_numpy(inside), proxy.read_numpy(points.numpy())))
    as_ints = proxy.read_numpy(np.array([[0, 0, 0], [1, 0, 0]]))  # another dtype: read as float64
    assert as_ints[0].dtype == np.float64 and as_ints[2].tolist() == [UNKNOWN, ABOVE]
    empty = proxy.read_numpy(np.zeros((0, 3), np.float32))
    assert empty[0].shape == (0,) and empty[1].shape == (0, 3) and empty[2].dtype == np.int8
    with pytest.raises(InputError, match="shape"):
        proxy.read_numpy(np.zeros((4, 2)))
    with pytest.raises(InputError, match="finite"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # numpy's, casting NaN to a cell
        proxy.read_numpy(np.array([[np.nan, 0.0, 0.0]]))


# -- the collider on a proxy ----------------------------------------------------------------------


def check_exact(sdf, contacts, sdf_pose) -> None:
    """The contacts' depths are the SDF's at their points, and their normals its unit gradients there."""
    if not len(contacts):
        return
    local = transform_points(invert_pose(torch.as_tensor(sdf_pose, dtype=torch.float64)).to(contacts.points),
                             contacts.points)
    values, grads = sdf.value_and_grad(local)
    assert float((values - contacts.depths).abs().max()) < 1e-6
    rotation_ = torch.as_tensor(sdf_pose, dtype=contacts.normals.dtype)[:3, :3]
    world = torch.nn.functional.normalize(grads, dim=-1) @ rotation_.T
    assert float((world - contacts.normals).norm(dim=-1).max()) < 1e-4


def compare(full, ours, margin: float, close: float, degrees: float = 8.0) -> None:
    """The same contact faces but for depths within ``close`` of the margin; the common ones' depths within ``close``
    and normals within ``degrees``."""
    a = {int(k): i for i, k in enumerate(full.triangles)}
    b = {int(k): i for i, k in enumerate(ours.triangles)}
    for k in set(a) ^ set(b):
        depth = full.depths[a[k]] if k in a else ours.depths[b[k]]
        assert abs(float(depth) - margin) <= close, f"face {k}: depth {float(depth)}, not near the margin"
    common = sorted(set(a) & set(b))
    ia, ib = [a[k] for k in common], [b[k] for k in common]
    if common:
        assert float((full.depths[ia] - ours.depths[ib]).abs().max()) <= close
        assert float((full.normals[ia] * ours.normals[ib]).sum(-1).min()) > math.cos(math.radians(degrees))


def test_sphere_on_plane_as_the_full_collider(sphere_proxy):
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3)
    mesh = plane_mesh()
    full = zoo.CoherentCollider(sphere, mesh, margin=1e-3, method="fw")
    ours = zoo.CoherentCollider(sphere, mesh, margin=1e-3, method="fw", proxy=proxy)
    for step in range(20):
        sdf_pose, mesh_pose = sphere_rolling_over_plane(step)
        a, b = full(sdf_pose, mesh_pose), ours(sdf_pose, mesh_pose)
        scratch = zoo.collide(sphere, mesh, sdf_pose, mesh_pose, margin=1e-3, method="fw")
        assert len(b) > 0 and b.method == "proxy+fw"
        compare(a, b, 1e-3, 2e-5)
        compare(scratch, b, 1e-3, 3e-5)
        check_exact(sphere, b, sdf_pose)
    assert ours.stats.exact_faces > 0 and ours.stats.fallback == 0


@pytest.mark.slow
def test_mug_on_rack_as_the_full_collider_and_collide(mug, mug_proxy):
    """The mugs NeuralSDF on the procedural rack, sliding 0.5 mm and turning 0.005 rad per step: the proxy-screened
    contacts are the full collider's and collide's (amortized), their depths the NeuralSDF's at their points; the
    NeuralSDF answers far fewer points than the full collider asks."""
    from zoo.scenes import load_collision_scene

    scene = load_collision_scene("demo-mug-rack")
    mesh = (np.asarray(scene.mesh.vertices, dtype=np.float32), np.asarray(scene.mesh.faces))
    poses = slide_along_peg(scene.sdf_pose, 5e-4, 0.005)
    margin = scene.margin
    full = zoo.CoherentCollider(mug, mesh, margin=margin, method="amortized")
    ours = zoo.CoherentCollider(mug, mesh, margin=margin, method="amortized", proxy=mug_proxy)
    deferred = zoo.CoherentCollider(mug, mesh, margin=margin, method="amortized", proxy=mug_proxy, deferred=True)
    for step in range(8):
        sdf_pose, mesh_pose = poses(step)
        a, b, c = full(sdf_pose, mesh_pose), ours(sdf_pose, mesh_pose), deferred(sdf_pose, mesh_pose)
        assert len(b) > 50
        # both are within a few 1e-5 of the face's minimum (the full collider's answers up to 3.7e-5 above it, docs/coherence.md;
        # the proxy's minimiser polished by one step where its gap is positive), their points, so normals, 8 degrees
        compare(a, b, margin, 5e-5)
        check_exact(mug, b, sdf_pose)
        if step % 4 == 0:
            # collide's own answers differ from the minimum by up to 3.7e-5 (docs/coherence.md), and so its normals
            compare(zoo.collide(mug, mesh, sdf_pose, mesh_pose, margin=margin, method="amortized"), b, margin, 5e-5)
        # deferred: the proxy's contacts (a superset), and exact_contacts on all of them gives the same as b
        assert set(b.triangles.tolist()) <= set(c.triangles.tolist())
        exact = deferred.exact_contacts(torch.arange(len(c)))
        assert torch.equal(exact.triangles, b.triangles)
        assert torch.allclose(exact.depths, b.depths, atol=1e-6)
        picked = deferred.exact_contacts(torch.tensor([0, len(c) - 1]))  # a few rows, in the order given
        assert len(picked) <= 2 and set(picked.triangles.tolist()) <= set(c.triangles[[0, len(c) - 1]].tolist())
    assert ours.stats.exact_faces < full.stats.vertex_queries


def test_proxy_arguments(mug, mug_proxy):
    mesh = plane_mesh()
    with pytest.raises(InputError, match="coherence"):
        zoo.CoherentCollider(mug, mesh, proxy=mug_proxy, coherence=False)
    with pytest.raises(InputError, match="voxel-fw"):
        zoo.CoherentCollider(mug, mesh, method="voxel-fw", proxy=mug_proxy)
    with pytest.raises(InputError, match="ProxySDF"):
        zoo.CoherentCollider(mug, mesh, proxy=zoo.Sphere(0.1))
    with pytest.raises(InputError, match="exact_contacts"):
        zoo.CoherentCollider(mug, mesh, proxy=mug_proxy, deferred=True).exact_contacts([0])


def test_a_deep_penetration_out_of_band_falls_back_to_the_sdf():
    """A sphere pressed 3 mm into a plane, beyond a 1.5 mm band: the faces whose proxy answer lies out of band are
    solved on the SDF itself, and the contacts are collide's."""
    sphere = zoo.Sphere(0.05)
    proxy = bake_proxy(sphere, margin=1e-3, spacing=1e-3, band=1.5e-3)
    mesh = plane_mesh(max_edge=0.004)
    ours = zoo.CoherentCollider(sphere, mesh, margin=1e-3, method="fw", proxy=proxy)
    sdf_pose = pose(rotation((0, 0, 1), 0.1), (0.001, 0.002, 0.047))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = ours(sdf_pose, None)
    scratch = zoo.collide(sphere, mesh, sdf_pose, None, margin=1e-3, method="fw")
    assert ours.last_stats.fallback > 0
    compare(scratch, b, 1e-3, 5e-5)
    assert float(b.depths.min()) < -2.9e-3
    check_exact(sphere, b, sdf_pose)


def brute_force_minima(sdf, triangles: np.ndarray, per_side: int = 300) -> np.ndarray:
    """The least of ``sdf`` (float64) over a grid of barycentric points ``per_side`` to a side on each triangle
    (T, 3, 3): (T,), the slow reference."""
    i, j = np.meshgrid(np.arange(per_side + 1), np.arange(per_side + 1), indexing="ij")
    keep = i + j <= per_side
    bary = np.stack([i[keep], j[keep], per_side - i[keep] - j[keep]], -1) / per_side  # (G, 3)
    points = torch.from_numpy(np.einsum("gv,tvc->tgc", bary, triangles).reshape(-1, 3))
    with torch.no_grad():
        return sdf(points).reshape(len(triangles), -1).amin(-1).numpy()


def test_faces_deeper_than_the_band_take_the_sdfs_minimum_over_them():
    """Large faces cutting a torus's tube up to 20 mm deep, beyond a 2 mm band (where the proxy holds only a bound):
    the SDF's own descent on them finds each face's minimum, the brute-force one, though the torus is not convex on
    a face that crosses its tube twice."""
    torus = zoo.Torus(0.05, 0.02)
    proxy = bake_proxy(torus, margin=1e-3, spacing=1e-3, band=2e-3)
    vertices, faces = plane_mesh(size=0.16, max_edge=0.04)
    ours = zoo.CoherentCollider(torus, (vertices, faces), margin=1e-3, method="fw", proxy=proxy)
    sdf_pose = pose(rotation((1, 0.3, 0), 0.25), (0.003, -0.002, -0.005))
    b = ours(sdf_pose, None)
    assert ours.last_stats.fallback >= 5 and float(b.depths.min()) < -0.01
    check_exact(torus, b, sdf_pose)
    local = (vertices.astype(np.float64) - sdf_pose[:3, 3]) @ sdf_pose[:3, :3]  # the torus's frame
    truth = brute_force_minima(torus, local[faces[b.triangles.numpy()]])
    deep = truth < -proxy.band
    assert deep.sum() >= 5
    error = np.abs(b.depths.double().numpy()[deep] - truth[deep])
    # on the tube's core circle the torus has a kink, along which a descent zigzags: there within a tenth of the
    # margin (Frank-Wolfe from scratch, zoo.collide's "fw", misses these faces' minima by up to 4.8e-4)
    assert np.median(error) < 1e-6 and error.max() < 1e-4


# -- in a simulation ------------------------------------------------------------------------------


def test_a_simulation_on_a_proxy_follows_the_one_without():
    """A ball (any SDF, its proxy given by name) dropped onto a mesh floor: the same rest, its contacts the SDF's."""
    pytest.importorskip("mujoco")
    import trimesh

    import zoo.sim

    ball = zoo.Sphere(0.03)
    proxy = bake_proxy(ball, margin=1e-3, spacing=1e-3)
    floor = trimesh.creation.box((0.2, 0.2, 0.01))
    ends = {}
    for way, option in (("plain", False), ("proxy", {"ball": proxy})):
        sim = zoo.sim.Simulation(margin=1e-3, proxy=option)
        sim.add_body("ball", sdf=ball, mass=0.1, pose=pose(None, (0.0, 0.0, 0.0352)), joint="free")
        sim.add_body("floor", mesh=floor, joint="fixed")
        sim.step(n=150)
        ends[way] = sim.pose("ball")[:3, 3]
        contacts = sim.contacts
        assert len(contacts) > 0
        check_exact(ball, contacts, sim.pose("ball"))
        stats = sim.collider_stats()
        assert (stats.exact_faces > 0) == (way == "proxy")
        if way == "proxy":
            assert sim.world.proxies == {"ball": proxy}
    assert float(np.linalg.norm(ends["proxy"] - ends["plain"])) < 2e-4
    assert abs(float(ends["proxy"][2]) - 0.035) < 2e-3  # resting on the floor's top (z 0.005) by its radius
    with pytest.raises(InputError, match="not SDF bodies"):
        sim = zoo.sim.Simulation(margin=1e-3, proxy={"floor": proxy})
        sim.add_body("ball", sdf=ball, mass=0.1, pose=pose(None, (0.0, 0.0, 0.0352)), joint="free")
        sim.add_body("floor", mesh=floor, joint="fixed")
        sim.build()


# a simulation of the mug dropped 6 mm onto a fixed ball's mesh (a mesh pair on the proxy), baked lazily, then
# ended three ways: a normal exit, the Simulation dropped before os._exit (no atexit), os._exit with it alive
DROPPED_SIMULATION = """
import gc, os, sys
import numpy as np, torch, trimesh
import zoo, zoo.sim


def at(z):
    pose = np.eye(4)
    pose[2, 3] = z
    return pose


torch.set_num_threads(1)
sim = zoo.sim.Simulation(proxy="lazy")
sim.add_body("ball", mesh=trimesh.creation.icosphere(subdivisions=3, radius=0.03), joint="fixed", pose=at(-0.03))
sim.add_body("mug", sdf=zoo.load("mugs").shape("hoi4d_mug_0001"), mass=0.3, pose=at({height}))
sim.step(30)
print(sim.world.proxies["mug"].n_baked, flush=True)
if sys.argv[1] == "exit":
    sys.exit(0)
if sys.argv[1] == "drop":
    del sim
    gc.collect()
os._exit(0)
"""


@pytest.mark.slow  # three processes of 30 steps each: 20-40 s on 2 shared cores
def test_a_proxy_baked_in_a_dropped_simulation_is_found_whole_in_the_cache_by_the_next_process(mug, tmp_path):
    """A baked brick is never lost: a Simulation dropped before its process ends (os._exit: no atexit) leaves in the
    cache every brick it baked, as a normal exit does; one never dropped (os._exit with it alive) leaves only what its
    creation wrote, which shows what the drop adds."""
    import os
    import subprocess
    import sys

    script = DROPPED_SIMULATION.replace("{height}", "0.05")  # its base (not its bounds' bottom) 6 mm above the ball
    on_disk, baked = {}, {}
    for mode in ("exit", "drop", "alive"):
        cache = tmp_path / mode
        run = subprocess.run([sys.executable, "-c", script, mode], env={**os.environ, "ZOO_CACHE": str(cache)},
                             capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-2000:]
        baked[mode] = int(run.stdout.split()[-1])
        (folder,) = (cache / "proxies").iterdir()
        on_disk[mode] = load_proxy(folder)
    assert baked["exit"] == baked["drop"] == baked["alive"] > ERROR_BRICKS  # the steps baked bricks
    assert on_disk["exit"].n_baked == on_disk["drop"].n_baked == baked["drop"]
    assert on_disk["alive"].n_baked == ERROR_BRICKS  # only the creation's write: os._exit skips the exit's
    for name in ("nodes", "status", "brick_of", "coarse_value", "coarse_grad"):  # NaN: a coarse value not evaluated
        assert np.array_equal(getattr(on_disk["drop"], name).numpy(), getattr(on_disk["exit"], name).numpy(),
                              equal_nan=name.startswith("coarse")), name


@pytest.mark.slow  # the mug's whole bake at 1 mm: 25-40 s on 2 cores
def test_zoo_bake_fills_the_cache_so_that_attach_bakes_nothing(tmp_path, monkeypatch):
    """`zoo bake mugs:SHAPE` writes the shape's whole proxy to the cache; a simulation attached next (proxy baked ahead,
    the default) finds it there and bakes no brick, at attach or in its steps. An unknown shape is a typed error."""
    mujoco = pytest.importorskip("mujoco")
    from typer.testing import CliRunner

    import zoo.sim
    from sdfzoo.cli.main import app, register_commands

    monkeypatch.setenv("ZOO_CACHE", str(tmp_path))
    register_commands()
    result = CliRunner().invoke(app, ["bake", "mugs:hoi4d_mug_0001", "--no-progress"])
    assert result.exit_code == 0, result.output
    (folder,) = (tmp_path / "proxies").iterdir()
    baked = load_proxy(folder)
    assert baked.n_pending == 0 and baked.n_baked > 10_000 and "hoi4d_mug_0001" in result.output

    model = mujoco.MjModel.from_xml_string("""<mujoco><worldbody><geom name="floor" type="box" size="0.1 0.1 0.01"/>
        <body name="mug" pos="0 0 0.06"><freejoint/><geom type="sphere" size="0.04" contype="0" conaffinity="0"/></body>
        </worldbody></mujoco>""")
    world = zoo.sim.attach(model, {"mug": zoo.load("mugs").shape("hoi4d_mug_0001")})
    world.step(mujoco.MjData(model), 5)
    assert world.bake_seconds == 0.0 and world.proxies["mug"].lazy_bricks == 0
    assert world.proxies["mug"].n_baked == baked.n_baked

    with pytest.raises(InputError, match="no shape 'nope'"):
        CliRunner().invoke(app, ["bake", "mugs:nope"], catch_exceptions=False, standalone_mode=False)
