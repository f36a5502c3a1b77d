"""Lipschitz lower bounds of an SDF over triangles, shared by collision's broad phase and the amortized search.

With an L-Lipschitz SDF f, a value at one point bounds f everywhere within reach of it:
f(q) >= f(p) - L |q - p|. The culls of :mod:`zoo.collision` and :mod:`zoo.amortized` drop a triangle
(or a cell of one) only when such a bound proves it stays above what is asked for.
"""

from __future__ import annotations

import torch

LIPSCHITZ = 1.0  # the bound the culls assume of the SDF (an exact SDF is 1-Lipschitz)


def rounding_slack(value_size: torch.Tensor, reach: torch.Tensor, coordinate_size: torch.Tensor) -> torch.Tensor:
    """How far below a bound to stay so that rounding never culls what exact arithmetic would keep: (...,).

    f, the distances and the coordinates are rounded to their dtype, so a threshold keeps a few ulps
    of the largest magnitude involved: ``value_size`` |f|, ``reach`` the distance bounded over,
    ``coordinate_size`` the largest coordinate (all (...,); the epsilon is that of the coordinates' dtype).
    """
    return 16 * torch.finfo(coordinate_size.dtype).eps * (value_size + reach + coordinate_size)


def cell_lower_bounds(cells: torch.Tensor, values: torch.Tensor, lipschitz: float = LIPSCHITZ) -> torch.Tensor:
    """A lower bound (C,) of an L-Lipschitz SDF over each triangle (C, 3, 3) from its vertex values (C, 3).

    The larger of two bounds: ``max_i f_i - L * reach_i`` (reach_i: the longest edge at vertex i,
    the farthest any point of the triangle is from it) and ``min_i f_i - L * R`` (R: the radius of
    the smallest ball holding the triangle, circumradius or half the longest edge, which is the
    farthest any point of the triangle is from its nearest vertex). Rounding slack is subtracted.
    """
    reach, radius = triangle_reach(cells)
    by_vertex = (values - lipschitz * reach).amax(dim=-1)
    by_ball = values.amin(dim=-1) - lipschitz * radius
    bound = torch.maximum(by_vertex, by_ball)
    return bound - rounding_slack(values.abs().amax(dim=-1), reach.amax(dim=-1), cells.abs().amax(dim=(1, 2)))


def triangle_reach(cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For triangles (C, 3, 3): how far any point of each lies from each vertex at most (C, 3) (the longest edge at
    it), and the radius (C,) of the smallest ball holding it (circumradius, or half the longest edge where the
    triangle is not acute: the farthest any point lies from its nearest vertex). Rigid motions leave both unchanged."""
    e = torch.stack([(cells[:, 1] - cells[:, 2]).norm(dim=-1), (cells[:, 2] - cells[:, 0]).norm(dim=-1),
                     (cells[:, 0] - cells[:, 1]).norm(dim=-1)], dim=-1)  # (C, 3): edge k opposite vertex k
    reach = torch.stack([torch.maximum(e[:, 1], e[:, 2]), torch.maximum(e[:, 0], e[:, 2]), torch.maximum(e[:, 0], e[:, 1])], dim=-1)
    longest = e.amax(dim=-1)
    twice_area = torch.linalg.cross(cells[:, 1] - cells[:, 0], cells[:, 2] - cells[:, 0], dim=-1).norm(dim=-1)
    not_acute = 2 * longest.square() >= e.square().sum(dim=-1)  # longest^2 >= the other two's squares summed
    circumradius = e.prod(dim=-1) / (2 * twice_area).clamp_min(torch.finfo(cells.dtype).tiny)
    return reach, torch.where(not_acute, 0.5 * longest, circumradius)
