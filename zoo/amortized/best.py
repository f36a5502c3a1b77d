"""The best answer found so far for each triangle of a solve: one object the search, the vertex test
and the network's answers all offer candidates to."""

from __future__ import annotations

import torch
from torch.nn import functional as F


class BestSoFar:
    """Per triangle (M rows): the lowest normalised-frame value found so far, the barycentrics where it was
    found, and whether it is the caller's ``known`` point (whose value is returned as given).

    Attributes:
        value: (M,) lowest value, ``inf`` where there is no candidate yet.
        bary: (M, 3) where; the centroid until a candidate arrives.
        from_known: (M,) bool, the row's best is the known point.
    """

    def __init__(self, m: int, dtype: torch.dtype, device):
        self.value = torch.full((m,), float("inf"), dtype=dtype, device=device)
        self.bary = torch.full((m, 3), 1 / 3, dtype=dtype, device=device)
        self.from_known = torch.zeros(m, dtype=torch.bool, device=device)

    def set_vertices(self, rows: torch.Tensor, corner: torch.Tensor, values: torch.Tensor) -> None:
        """Rows ``rows`` (R,) take their corner ``corner`` (R,) 0-2 with value ``values`` (R,), whatever they held."""
        self.value[rows] = values
        self.bary[rows] = F.one_hot(corner, 3).to(self.bary)

    def forget_values(self, rows: torch.Tensor) -> None:
        """Rows ``rows`` keep their barycentrics but no value: any later candidate beats them."""
        self.value[rows] = float("inf")

    def place(self, rows: torch.Tensor, bary: torch.Tensor) -> None:
        """Rows ``rows`` (R,) take ``bary`` (R, 3) as their answer, not evaluated (their values are not touched)."""
        self.bary[rows] = bary

    def offer_known(self, bary: torch.Tensor, values: torch.Tensor, allowed: torch.Tensor) -> None:
        """The caller's known point per row, (M, 3) and (M,): taken where ``allowed`` (M,) and lower."""
        better = (values < self.value) & allowed
        self.value = torch.where(better, values, self.value)
        self.bary = torch.where(better.unsqueeze(-1), bary, self.bary)
        self.from_known = better

    def offer(self, rows: torch.Tensor, values: torch.Tensor, bary: torch.Tensor) -> None:
        """Candidates (rows (Q,), values (Q,), bary (Q, 3)): where one beats its row's best, the row takes it
        (of several equal winners for a row, the first in order)."""
        if rows.numel() == 0:
            return
        new = self.value.clone().scatter_reduce_(0, rows, values, "amin")
        improved = new < self.value
        if not bool(improved.any()):
            return
        win = (values == new[rows]) & improved[rows]
        first = torch.full(self.value.shape, rows.numel(), dtype=torch.int64, device=rows.device)
        first.scatter_reduce_(0, rows[win], win.nonzero().squeeze(-1), "amin")
        changed = improved.nonzero().squeeze(-1)
        self.bary[changed] = bary[first[changed]]
        self.value.copy_(new)
        self.from_known[changed] = False
