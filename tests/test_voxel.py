"""VoxelSDF against independent references: scipy's trilinear interpolator, analytic SDFs,
finite differences, and a linear field that trilinear interpolation must reproduce exactly."""

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

import zoo
from zoo.errors import InputError
from zoo.sdf import SDFBase, check_sdf
from zoo.voxel import VoxelSDF


class HalfSpace(SDFBase):
    """f(x) = n . x - offset: linear, so trilinear interpolation of it is exact."""

    def __init__(self, normal=(0.3, -0.5, 0.8), offset=0.05):
        n = torch.tensor(normal, dtype=torch.float64)
        self.normal = n / n.norm()
        self.offset = offset
        self.bounds = (torch.full((3,), -0.3), torch.full((3,), 0.4))

    def _distance(self, points):
        return points @ self.normal.to(points) - self.offset


class Counting:
    """Wraps an SDF and records the size of every batch it is called with."""

    def __init__(self, sdf):
        self.sdf, self.bounds, self.batches = sdf, sdf.bounds, []

    def __call__(self, points):
        self.batches.append(points.shape[0])
        return self.sdf(points)

    def value_and_grad(self, points):
        return self.sdf.value_and_grad(points)


def points_in_box(voxel, n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    lo, hi = voxel.lo.to(dtype), voxel.hi.to(dtype)
    return lo + torch.rand(n, 3, generator=g, dtype=dtype) * (hi - lo)


def scipy_interpolant(voxel):
    """An independent trilinear interpolant over the same samples."""
    axes = [np.linspace(voxel.lo[i].item(), voxel.hi[i].item(), voxel.shape[i]) for i in range(3)]
    return RegularGridInterpolator(axes, voxel.values.double().numpy(), method="linear")


def test_samples_are_the_sdf_on_the_grid():
    sphere = zoo.Sphere(0.25, center=(0.02, -0.01, 0.03))
    v = VoxelSDF(sphere, resolution=(5, 7, 9), padding=0.1)
    axes = [torch.linspace(v.lo[i].item(), v.hi[i].item(), v.shape[i], dtype=torch.float64) for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1)
    assert v.values.shape == (5, 7, 9) and v.values.dtype == torch.float32
    torch.testing.assert_close(v.values.double(), sphere(grid.reshape(-1, 3)).reshape(5, 7, 9), atol=1e-6, rtol=0)
    # padding is a fraction of the longest side of the bounds, added on every side
    torch.testing.assert_close(v.lo, sphere.bounds[0].double() - 0.1 * 0.5, atol=1e-6, rtol=0)


def test_values_match_scipy_trilinear_inside_the_grid():
    v = VoxelSDF(zoo.Torus(), resolution=(17, 23, 11))
    p = points_in_box(v, 2000)
    expected = torch.from_numpy(scipy_interpolant(v)(p.numpy()))
    torch.testing.assert_close(v(p), expected, atol=1e-9, rtol=0)


def test_linear_field_is_reproduced_exactly_with_its_gradient():
    plane = HalfSpace()
    v = VoxelSDF(plane, resolution=6, padding=0.0)
    p = points_in_box(v, 1000, seed=1)
    d, g = v.value_and_grad(p)
    torch.testing.assert_close(d, plane(p), atol=1e-6, rtol=0)  # float32 samples
    torch.testing.assert_close(g, plane.normal.expand_as(g), atol=1e-5, rtol=0)


def test_error_shrinks_with_resolution():
    torus = zoo.Torus()
    errors = []
    for n in (12, 24, 48):
        v = VoxelSDF(torus, resolution=n)
        p = points_in_box(v, 4000, seed=2, dtype=torch.float32)
        errors.append((v(p) - torus(p)).abs().max().item())
        assert errors[-1] < v.spacing.max().item()  # never worse than one cell of a 1-Lipschitz field
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 0.6 * errors[0] / 2  # at least about linear convergence


def test_gradient_is_the_derivative_of_the_interpolant():
    v = VoxelSDF(zoo.Sphere(0.25, center=(0.05, 0.0, -0.02)), resolution=20)
    p = points_in_box(v, 500, seed=3)
    _, g = v.value_and_grad(p)
    h = 1e-7  # far smaller than a cell, so both sides lie in the same cell almost surely
    fd = torch.stack([(v(p + h * e) - v(p - h * e)) / (2 * h) for e in torch.eye(3, dtype=p.dtype)], -1)
    torch.testing.assert_close(g, fd, atol=1e-5, rtol=0)


def test_outside_the_grid_clamps_and_adds_the_distance_to_the_box():
    sphere = zoo.Sphere(0.25)
    v = VoxelSDF(sphere, resolution=16)
    g = torch.Generator().manual_seed(4)
    p = (torch.rand(500, 3, generator=g, dtype=torch.float64) - 0.5) * 4  # mostly outside
    q = np.clip(p.numpy(), v.lo.numpy(), v.hi.numpy())
    expected = scipy_interpolant(v)(q) + np.linalg.norm(p.numpy() - q, axis=1)
    d, grad = v.value_and_grad(p)
    torch.testing.assert_close(d, torch.from_numpy(expected), atol=1e-9, rtol=0)
    # still a sensible distance far away: an upper bound on the true one, up to one cell
    assert bool((d >= sphere(p) - v.spacing.max()).all())
    far = (p.abs() > 1.5).any(-1)
    assert bool(((d - sphere(p))[far] < 0.6).all())
    h = 1e-7
    fd = torch.stack([(v(p + h * e) - v(p - h * e)) / (2 * h) for e in torch.eye(3, dtype=p.dtype)], -1)
    torch.testing.assert_close(grad, fd, atol=1e-5, rtol=0)


def test_follows_the_sdf_protocol_and_keeps_dtypes():
    v = VoxelSDF(zoo.Sphere(0.25), resolution=8)
    check_sdf(v)
    assert isinstance(v, zoo.SDF)
    lo, hi = v.bounds
    assert lo.shape == hi.shape == (3,) and bool((lo < -0.25).all() & (hi > 0.25).all())
    for dtype in (torch.float32, torch.float64):
        d, g = v.value_and_grad(torch.zeros(4, 3, dtype=dtype))
        assert d.dtype == g.dtype == dtype and v(torch.zeros(4, 3, dtype=dtype)).dtype == dtype
    # a voxel grid of a voxel grid is an SDF too, and samples it exactly at its own grid points
    coarse = VoxelSDF(v, resolution=4)
    check_sdf(coarse)
    lo, hi = coarse.bounds
    axes = [torch.linspace(float(lo[i]), float(hi[i]), 4) for i in range(3)]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    torch.testing.assert_close(coarse(grid), v(grid), atol=1e-5, rtol=0)


def test_build_is_chunked_and_chunking_does_not_change_the_grid():
    counted = Counting(zoo.Torus())
    v = VoxelSDF(counted, resolution=(10, 11, 12), chunk=100)
    assert max(counted.batches) <= 100 and sum(counted.batches) == 10 * 11 * 12
    torch.testing.assert_close(v.values, VoxelSDF(zoo.Torus(), resolution=(10, 11, 12)).values)


def test_memory_bytes_counts_the_float32_samples():
    assert VoxelSDF(zoo.Sphere(), resolution=8).memory_bytes == 8**3 * 4
    assert VoxelSDF(zoo.Sphere(), resolution=(2, 3, 4)).memory_bytes == 2 * 3 * 4 * 4


def test_too_large_a_grid_is_refused_before_allocating():
    with pytest.raises(InputError, match=r"needs 32\.00 GiB.*lower the resolution or raise max_bytes"):
        VoxelSDF(zoo.Sphere(), resolution=2048)
    with pytest.raises(InputError, match="max_bytes"):
        VoxelSDF(zoo.Sphere(), resolution=16, max_bytes=1000)
    assert VoxelSDF(zoo.Sphere(), resolution=16, max_bytes=16**3 * 4).memory_bytes == 16**3 * 4


@pytest.mark.parametrize("resolution", [1, 0, -3, 2.5, "64", (4, 4), (4, 4, 1), True, None])
def test_bad_resolution_is_an_input_error(resolution):
    with pytest.raises(InputError, match="resolution"):
        VoxelSDF(zoo.Sphere(), resolution=resolution)


def test_bad_arguments_are_input_errors():
    with pytest.raises(InputError, match="not an SDF"):
        VoxelSDF(object())
    with pytest.raises(InputError, match="lo < hi"):
        VoxelSDF(zoo.Sphere(), bounds=([0, 0, 0], [1, 0, 1]))
    with pytest.raises(InputError, match="padding"):
        VoxelSDF(zoo.Sphere(), padding=-0.1)
    with pytest.raises(InputError, match="NaN"):
        VoxelSDF(zoo.Sphere(), resolution=4)(torch.tensor([[0.0, float("nan"), 0.0]]))


def test_truncation_clamps_the_stored_values():
    v = VoxelSDF(zoo.Sphere(0.25), resolution=9, truncation=0.1)
    assert v.values.min().item() == pytest.approx(-0.1) and v.values.max().item() == pytest.approx(0.1)


def test_the_grid_shows_its_progress_only_when_asked(capsys):
    """zoo.collide builds the grid of "voxel-fw" on first use, the command's longest silent step: inside
    zoo.progress.shown() (as the `zoo` command runs) a bar counts its chunks; a library call stays quiet."""
    from zoo.progress import shown

    VoxelSDF(zoo.Torus(), resolution=12, chunk=100)
    assert "VoxelSDF" not in capsys.readouterr().out
    with shown():
        VoxelSDF(zoo.Torus(), resolution=12, chunk=100)
    out = capsys.readouterr().out
    assert "VoxelSDF 12x12x12 grid" in out and "18/18" in out  # ceil(1728 / 100) chunks, all done
    VoxelSDF(zoo.Torus(), resolution=12, chunk=100, progress=True)
    assert "18/18" in capsys.readouterr().out


def test_state_round_trips_through_a_tensors_only_file(tmp_path):
    """A grid saved as its state (tensors and numbers, no pickled object) loads back with weights_only=True and
    answers exactly as the original, inside and outside its box; a malformed state is refused."""
    grid = VoxelSDF(zoo.Torus(major=0.3, minor=0.1), resolution=(17, 19, 11), padding=0.1, truncation=0.2)
    torch.save(grid.state(), tmp_path / "grid.pt")
    loaded = VoxelSDF.from_state(torch.load(tmp_path / "grid.pt", weights_only=True))
    points = torch.rand(500, 3, generator=torch.Generator().manual_seed(0)) * 1.6 - 0.8  # some outside the box
    for a, b in zip(grid.value_and_grad(points), loaded.value_and_grad(points)):
        assert torch.equal(a, b)
    assert loaded.resolution == (17, 19, 11) and loaded.truncation == 0.2 and loaded.padding == 0.1
    assert all(torch.equal(a, b) for a, b in zip(grid.bounds, loaded.bounds))
    with pytest.raises(InputError, match="samples"):
        VoxelSDF.from_state({**grid.state(), "values": torch.zeros(4, 4)})
