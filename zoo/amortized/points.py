"""The point table of the amortized search: every point evaluated once, found again by a bit-packed key.

A mesh shares each vertex among about six triangles, and a subdivided triangle's grid points are
shared between its cells, between the steps of the search and, along the mesh's edges, between
neighbouring triangles: the table evaluates each (features and distance) the first time it is
asked for and answers from its rows after.
"""

from __future__ import annotations

import torch

from ..errors import InputError

# Point keys hold a triangle or an edge index below 2^29 and grid coordinates below 2^16, under a tag bit.
KEY_ROW_BITS = 29
TAG_EDGE = 1 << 62
TAG_FACE = 1 << 61


class PointTable:
    """Every point the search has evaluated: normalised coordinates, features and distances.

    Rows 0..U-1 are the mesh's distinct vertices; grid points of subdivided triangles follow,
    found by an int64 key: a point on a mesh edge by (the edge, and the reduced fraction along it
    from its lower-numbered vertex), so neighbouring triangles share it; any other grid point by
    (its triangle, its grid coordinates).
    """

    def __init__(self, shape, vertices_n: torch.Tensor, faces: torch.Tensor, values_for: torch.Tensor,
                 given: torch.Tensor | None = None):
        """``values_for``: vertex rows whose distances are needed now; ``given``: (U,) normalised-frame
        distances at the vertices known already (NaN where not), which are not queried again."""
        if 3 * faces.shape[0] >= 1 << KEY_ROW_BITS:  # each triangle, and each edge, must fit a key
            raise InputError(f"solve_mesh takes fewer than {(1 << KEY_ROW_BITS) // 3} triangles at once, got {faces.shape[0]}: "
                             "split the mesh")
        self.shape = shape
        self.faces = faces
        self.n_vertices = vertices_n.shape[0]
        self._face_edges: torch.Tensor | None = None  # (M, 3) edge indices, taken when a grid point first needs them
        self.coords = vertices_n
        self.f = torch.full(vertices_n.shape[:1], float("nan"), dtype=vertices_n.dtype, device=vertices_n.device)
        self.has_f = torch.zeros(vertices_n.shape[0], dtype=torch.bool, device=vertices_n.device)
        if given is not None:
            self.has_f = ~torch.isnan(given)
            self.f = torch.where(self.has_f, given, self.f)
        # code-cloud features, taken where the decoder or the network needs them (rows with given values may need neither)
        self.z: torch.Tensor | None = None
        self.has_z = torch.zeros(vertices_n.shape[0], dtype=torch.bool, device=vertices_n.device)
        self.keys = torch.zeros(0, dtype=torch.int64, device=vertices_n.device)  # sorted
        self.slots = torch.zeros(0, dtype=torch.int64, device=vertices_n.device)
        # gradients at vertex rows only (the vertex test of solve_mesh), NaN until asked for
        self.grad = torch.full_like(vertices_n, float("nan"))
        self.ensure_values(values_for)

    def features(self, rows: torch.Tensor) -> torch.Tensor:
        """Code-cloud features (..., C) at the int rows ``rows`` (...), computed where new."""
        need = torch.unique(rows.reshape(-1))
        need = need[~self.has_z[need]]
        if need.numel():
            z = features_at(self.shape, self.coords[need])
            if self.z is None:
                self.z = z.new_zeros((self.coords.shape[0], z.shape[-1]))
            self.z[need] = z
            self.has_z[need] = True
        return self.z[rows]

    def ensure_values(self, rows: torch.Tensor) -> None:
        """Distances at the vertex rows ``rows`` (the decoder on the features already computed)."""
        rows = torch.unique(rows)
        rows = rows[~self.has_f[rows]]
        if rows.numel():
            self.f[rows] = distances_from_features(self.shape, self.coords[rows], self.features(rows))
            self.has_f[rows] = True

    def gradients(self, rows: torch.Tensor) -> torch.Tensor:
        """Normalised-frame SDF gradients (R, 3) at the vertex rows ``rows`` (R,): one value-and-gradient
        query per distinct vertex not asked for before."""
        need = torch.unique(rows)
        need = need[torch.isnan(self.grad[need, 0])]
        if need.numel():
            with torch.no_grad():
                f, g = self.shape.normalised.value_and_grad(self.coords[need])
            self.grad[need] = torch.as_tensor(g).to(self.grad)
            self.f[need] = torch.as_tensor(f).reshape(-1).to(self.f)
            self.has_f[need] = True
        return self.grad[rows]

    def lowest_vertices(self, vertex_rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Each triangle's lowest corner, from its corner rows (R, 3): value (R,), which corner 0-2 (R,), its row (R,)."""
        self.ensure_values(vertex_rows.reshape(-1))
        value, corner = self.f[vertex_rows].min(dim=-1)
        return value, corner, vertex_rows.gather(1, corner.unsqueeze(1)).squeeze(1)

    def grid_points(self, rows: torch.Tensor, ij: torch.Tensor, n) -> torch.Tensor:
        """Row indices (Q,) of the grid points (i, j) (Q, 2) of triangles ``rows`` (Q,) at their levels ``n``
        (an int, or (Q,): a triangle keeps one level); evaluated if new."""
        i, j = ij[:, 0], ij[:, 1]
        n = torch.as_tensor(n, dtype=i.dtype, device=i.device).expand_as(i)
        out = torch.empty_like(i)
        face = self.faces[rows]  # (Q, 3)
        corner = torch.full_like(i, -1)
        corner = torch.where((i == 0) & (j == 0), 0, corner)
        corner = torch.where(i == n, 1, corner)
        corner = torch.where(j == n, 2, corner)
        is_corner = corner >= 0
        out[is_corner] = face[is_corner].gather(1, corner[is_corner].unsqueeze(1)).squeeze(1)
        rest = (~is_corner).nonzero().squeeze(-1)
        if rest.numel() == 0:
            return out
        i, j, n, face, r = i[rest], j[rest], n[rest], face[rest], rows[rest]
        # a point on an edge: (a, b, t) with t the fraction from a to b, t = num / n
        on01, on02, on12 = j == 0, i == 0, (i + j == n)
        edge = on01 | on02 | on12
        a = torch.where(on12, face[:, 1], face[:, 0])
        b = torch.where(on01, face[:, 1], face[:, 2])
        num = torch.where(on01, i, j)
        swap = a > b
        a, b, num = torch.where(swap, b, a), torch.where(swap, a, b), torch.where(swap, n - num, num)
        den = n
        g = torch.gcd(num, den).clamp_min(1)
        num, den = num // g, den // g
        edge_id = self.face_edges()[r].gather(1, torch.where(on01, 0, torch.where(on02, 1, 2)).unsqueeze(1)).squeeze(1)
        edge_key = TAG_EDGE | (edge_id << 32) | (num << 16) | den
        face_key = TAG_FACE | (r << 32) | (i << 16) | j
        key = torch.where(edge, edge_key, face_key)
        # coordinates: along the edge from the canonical end, else barycentric in the triangle
        t = (num.to(self.coords.dtype) / den.to(self.coords.dtype)).unsqueeze(-1)
        va, vb = self.coords[a], self.coords[b]
        along = va + t * (vb - va)
        w = torch.stack([n - i - j, i, j], dim=-1).to(self.coords.dtype) / n.unsqueeze(-1).to(self.coords.dtype)  # (Q, 3)
        inside = torch.einsum("qv,qvc->qc", w, self.coords[face])
        xyz = torch.where(edge.unsqueeze(-1), along, inside)
        out[rest] = self._lookup_or_add(key, xyz)
        return out

    def face_edges(self) -> torch.Tensor:
        """Each triangle's edges (M, 3) as indices of the mesh's distinct edges: its edges 0-1, 0-2 and 1-2."""
        if self._face_edges is None:
            f = self.faces
            ends = torch.stack([f[:, [0, 1]], f[:, [0, 2]], f[:, [1, 2]]], dim=1)  # (M, 3, 2)
            code = ends.amin(dim=-1) * self.n_vertices + ends.amax(dim=-1)
            self._face_edges = torch.unique(code, return_inverse=True)[1]
        return self._face_edges

    def _lookup_or_add(self, key: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        uniq, first_inverse = torch.unique(key, return_inverse=True)
        slot = torch.empty_like(uniq)
        if self.keys.numel():
            pos = torch.searchsorted(self.keys, uniq).clamp_max(self.keys.numel() - 1)
            found = self.keys[pos] == uniq
            slot[found] = self.slots[pos[found]]
        else:
            found = torch.zeros_like(uniq, dtype=torch.bool)
        missing = (~found).nonzero().squeeze(-1)
        if missing.numel():
            # one representative query per missing key
            rep = torch.full((uniq.numel(),), key.numel(), dtype=torch.int64, device=key.device)
            rep.scatter_reduce_(0, first_inverse, torch.arange(key.numel(), device=key.device), "amin")
            p = xyz[rep[missing]]
            z = features_at(self.shape, p)
            f = distances_from_features(self.shape, p, z)
            start = self.coords.shape[0]
            new_slots = torch.arange(start, start + missing.numel(), device=key.device)
            self.coords = torch.cat([self.coords, p])
            if self.z is None:  # no row had features yet: zeros (has_z False) for the rows before
                self.z = z.new_zeros((start, z.shape[-1]))
            self.z = torch.cat([self.z, z])
            self.has_z = torch.cat([self.has_z, torch.ones(missing.numel(), dtype=torch.bool, device=key.device)])
            self.f = torch.cat([self.f, f])
            self.has_f = torch.cat([self.has_f, torch.ones(missing.numel(), dtype=torch.bool, device=key.device)])
            slot[missing] = new_slots
            keys = torch.cat([self.keys, uniq[missing]])
            slots = torch.cat([self.slots, new_slots])
            order = torch.argsort(keys)
            self.keys, self.slots = keys[order], slots[order]
        return slot[first_inverse]


def features_at(shape, points: torch.Tensor) -> torch.Tensor:
    """The shape's code-cloud features (N, C) at normalised points (N, 3), in their dtype."""
    with torch.no_grad():
        return torch.as_tensor(shape.features(points)).to(points)


def distances_from_features(shape, points: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """Normalised-frame distances at ``points``: the shape's decoder on features already computed
    where it offers one (``distances_from_features``), else a plain query of ``shape.normalised``."""
    with torch.no_grad():
        fast = getattr(shape, "distances_from_features", None)
        if callable(fast):
            return torch.as_tensor(fast(points, features)).to(points)
        return torch.as_tensor(shape.normalised(points)).reshape(-1).to(points)
