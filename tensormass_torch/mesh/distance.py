"""Distances to triangle surfaces: the closest point of a triangle, and signed distance grids of
closed surfaces (what a tool of any shape presses with).

A :class:`SignedDistanceGrid` samples the signed distance phi (negative inside) of a closed,
consistently wound triangle surface at the nodes of a regular grid that covers the surface with
a margin; between nodes phi is the trilinear interpolant, so it is smooth inside each cell and
its gradient and Hessian are exact derivatives of the same interpolant (a penalty on it has
forces that are exactly minus its energy's gradient). The inside is decided by the angle-weighted
pseudonormal of the nearest feature (a face's normal, or the angle-weighted sum of the normals
of the faces at the nearest edge or vertex), which is right for every point of a closed surface
where one triangle's side is not (a point nearest to an edge or a corner). Outside the grid phi
is continued by the distance to it, which is at least the margin: a point there is never in
contact.

The grid's accuracy is that of trilinear interpolation: exact on flat parts away from edges,
within a fraction of the spacing near edges and corners (a corner is rounded over a cell).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import numpy as np
import torch

from ..errors import MeshError
from .topology import expand_ranges

#: point-triangle evaluations per batch when building a grid (bounds the temporary memory)
PAIRS_PER_BATCH = 1 << 22


def closest_weights(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """Barycentric weights ``[..., 3]`` of the point of triangle (a, b, c) closest to p (all
    ``[..., 3]``): the projection onto the triangle's plane where it falls inside, else the
    nearest of the closest points of the three edges (a degenerate triangle: its edges)."""
    tiny = torch.finfo(p.dtype).tiny
    ab, ac, ap = b - a, c - a, p - a
    d00, d01, d11 = (ab * ab).sum(-1), (ab * ac).sum(-1), (ac * ac).sum(-1)
    d20, d21 = (ap * ab).sum(-1), (ap * ac).sum(-1)
    denom = d00 * d11 - d01 * d01
    safe = torch.where(denom > 0, denom, torch.ones_like(denom))
    wb = (d11 * d20 - d01 * d21) / safe
    wc = (d00 * d21 - d01 * d20) / safe
    wa = 1.0 - wb - wc
    inside = (denom > 1e-12 * d00 * d11) & (wa >= 0) & (wb >= 0) & (wc >= 0)

    def on_edge(start, end):
        e = end - start
        t = ((p - start) * e).sum(-1) / torch.clamp((e * e).sum(-1), min=tiny)
        t = torch.clamp(t, 0.0, 1.0)
        return t, ((p - start - t[..., None] * e) ** 2).sum(-1)

    t_ab, d_ab = on_edge(a, b)
    t_ac, d_ac = on_edge(a, c)
    t_bc, d_bc = on_edge(b, c)
    zero = torch.zeros_like(t_ab)
    w_ab = torch.stack([1 - t_ab, t_ab, zero], -1)
    w_ac = torch.stack([1 - t_ac, zero, t_ac], -1)
    w_bc = torch.stack([zero, 1 - t_bc, t_bc], -1)
    w_edge = torch.where((d_ab <= d_ac)[..., None], w_ab, w_ac)
    w_edge = torch.where((d_bc < torch.minimum(d_ab, d_ac))[..., None], w_bc, w_edge)
    return torch.where(inside[..., None], torch.stack([wa, wb, wc], -1), w_edge)


def closest_point(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """From p to triangle (a, b, c) (all ``[..., 3]``): the closest point's weights w ``[..., 3]``,
    p minus that point ``[..., 3]``, its length d ``[...]`` and the triangle's unit normal
    (b - a) x (c - a) ``[..., 3]`` (outward for an outward-wound surface). The difference is taken
    from the triangle's corner, (p - a) - w_b (b - a) - w_c (c - a) (the weights sum to 1): its
    rounding is the triangle's size's, not the coordinates' (a pair a micrometre apart a metre from
    the origin keeps its direction in float32)."""
    w = closest_weights(p, a, b, c)
    ab, ac = b - a, c - a
    diff = (p - a) - (w[..., 1:2] * ab + w[..., 2:3] * ac)
    normal = torch.linalg.cross(ab, ac)
    normal = normal / torch.clamp(torch.linalg.vector_norm(normal, dim=-1, keepdim=True),
                                  min=torch.finfo(p.dtype).tiny)
    return w, diff, torch.linalg.vector_norm(diff, dim=-1), normal


def _corner_angles(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    """The triangles' interior angles ``[F, 3]`` at a, b, c."""
    def angle(p, q, r):  # at p
        u, v = q - p, r - p
        return torch.atan2(torch.linalg.vector_norm(torch.linalg.cross(u, v), dim=-1), (u * v).sum(-1))

    return torch.stack([angle(a, b, c), angle(b, c, a), angle(c, a, b)], dim=-1)


def _box_gaps(lower: torch.Tensor, upper: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
    """The distance ``[B, F]`` between boxes [lower, upper] ``[B, 3]`` and [low, high] ``[F, 3]``."""
    gap = torch.clamp(torch.maximum(low[None] - upper[:, None], lower[:, None] - high[None]), min=0.0)
    return torch.linalg.vector_norm(gap, dim=-1)


def surface_signed_distances(points: torch.Tensor, vertices: torch.Tensor, triangles: torch.Tensor,
                             block: int = 4) -> torch.Tensor:
    """The signed distance ``[nx, ny, nz]`` (negative inside) from the nodes of a regular grid
    ``points [nx, ny, nz, 3]`` to a closed, outward-wound surface (``vertices [V, 3]``,
    ``triangles [F, 3]``).

    Exact distance to the nearest triangle; its sign is the side of the angle-weighted
    pseudonormal of the nearest feature (Baerentzen and Aanaes: the normal where the nearest
    point is inside a face, the sum of the faces' normals where it is on an edge or a vertex,
    each face weighted by its angle there), which is correct for any point of a closed surface.
    The grid is taken in blocks of ``block^3`` nodes, and a block meets only the triangles whose
    boxes are within an upper bound of its nodes' distance (the nearest triangle's first vertex
    from the block's centre plus its half diagonal), and a node only those whose bounding spheres
    are no farther than the nearest one's far side: a few triangles each, not all of them."""
    shape = points.shape[:3]
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    angles = _corner_angles(a, b, c)
    low, high = torch.minimum(torch.minimum(a, b), c), torch.maximum(torch.maximum(a, b), c)
    # blocks of nodes: their ids [nb, block^3] (-1 past the grid's end) and boxes
    counts = [-(-n // block) for n in shape]
    ids = torch.arange(math.prod(shape), device=points.device).reshape(shape)
    padded = torch.full([n * block for n in counts], -1, dtype=torch.int64, device=points.device)
    padded[:shape[0], :shape[1], :shape[2]] = ids
    members = (padded.reshape(counts[0], block, counts[1], block, counts[2], block)
               .permute(0, 2, 4, 1, 3, 5).reshape(-1, block ** 3))
    flat = points.reshape(-1, 3)
    corners = flat[torch.clamp(members, min=0)]
    valid = members >= 0
    big = torch.finfo(points.dtype).max
    lower = torch.where(valid[..., None], corners, big).amin(1)
    upper = torch.where(valid[..., None], corners, -big).amax(1)
    centre, half = 0.5 * (lower + upper), 0.5 * torch.linalg.vector_norm(upper - lower, dim=-1)
    # candidate (block, triangle) pairs, by rows of blocks so that [rows, F] stays bounded
    pair_blocks, pair_triangles = [], []
    rows_per_batch = max(1, PAIRS_PER_BATCH // max(a.shape[0], 1))
    for start in range(0, members.shape[0], rows_per_batch):
        rows = slice(start, start + rows_per_batch)
        bound = (torch.linalg.vector_norm(centre[rows, None] - a[None], dim=-1).amin(1) + half[rows])
        near = _box_gaps(lower[rows], upper[rows], low, high) <= bound[:, None]
        blk, tri = torch.nonzero(near, as_tuple=True)
        pair_blocks.append(blk + start)
        pair_triangles.append(tri)
    pair_blocks, pair_triangles = torch.cat(pair_blocks), torch.cat(pair_triangles)
    # node-triangle pairs: every node of a block with each of its block's triangles
    node = members[pair_blocks].reshape(-1)
    tri = pair_triangles.repeat_interleave(block ** 3)
    keep = node >= 0
    node, tri = node[keep], tri[keep]
    node, tri = _within_reach(flat, node, tri, *_spheres(a, b, c))
    return _signed_from_pairs(flat, node, tri, a, b, c, angles, half.amax()).reshape(shape)


def _spheres(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """The triangles' bounding spheres about their centroids: centres ``[F, 3]``, radii ``[F]``."""
    centroid = (a + b + c) / 3.0
    return centroid, torch.linalg.vector_norm(torch.stack([a, b, c]) - centroid, dim=-1).amax(0)


def _within_reach(points: torch.Tensor, node: torch.Tensor, tri: torch.Tensor, centroid: torch.Tensor,
                  radius: torch.Tensor):
    """The point-triangle pairs (``node [P]`` into ``points [N, 3]``, ``tri [P]``) that may hold
    each point's nearest point: the triangle's bounding sphere no farther than the nearest
    sphere's far side (an upper bound of the point's distance). Every triangle as near as the
    nearest is kept, so the side's vote is unchanged."""
    to_centroid = torch.linalg.vector_norm(points[node] - centroid[tri], dim=-1)
    reach = torch.full((points.shape[0],), torch.finfo(points.dtype).max, dtype=points.dtype, device=points.device)
    reach.scatter_reduce_(0, node, to_centroid + radius[tri], "amin")
    keep = to_centroid - radius[tri] <= reach[node]
    return node[keep], tri[keep]


def _signed_from_pairs(points: torch.Tensor, node: torch.Tensor, tri: torch.Tensor, a: torch.Tensor, b: torch.Tensor,
                       c: torch.Tensor, angles: torch.Tensor, slack) -> torch.Tensor:
    """The signed distance ``[N]`` of each of ``points [N, 3]`` to the nearest of its candidate
    triangles: the pairs (``node [P]``, ``tri [P]``, every point's nearest triangle among them) of
    triangles ``a, b, c [F, 3]`` with corner ``angles [F, 3]``; its sign the side of the
    angle-weighted pseudonormal of the nearest feature (the pairs as near as the nearest, to
    rounding, vote with their normals weighted by their angle at a shared corner). ``slack``: a
    length added to the rounding's scale (the candidates' search bound). A point without any pair
    gets the dtype's largest value."""
    big = torch.finfo(points.dtype).max
    distance = torch.empty(node.shape[0], dtype=points.dtype, device=points.device)
    along = torch.empty_like(distance)  # the pair's vote for the side: weight x normal . (p - q)
    for start in range(0, node.shape[0], PAIRS_PER_BATCH):
        part = slice(start, start + PAIRS_PER_BATCH)
        t = tri[part]
        w, diff, d, normal = closest_point(points[node[part]], a[t], b[t], c[t])
        at_corner = w >= 1.0 - 1e-9  # [P, 3]: the nearest point is that corner
        weight = torch.where(at_corner.any(-1), (angles[t] * at_corner).sum(-1), torch.ones_like(d))
        distance[part], along[part] = d, weight * (normal * diff).sum(-1)
    nearest = torch.full((points.shape[0],), big, dtype=points.dtype, device=points.device)
    nearest.scatter_reduce_(0, node, distance, "amin")
    # the faces sharing the nearest point are those as near, to the rounding of the distances,
    # which scales with the coordinates (two faces compute their shared edge's distance
    # differently by a few ulps of them), not with the distance: a point beside a crease, nearly
    # in one face's plane, would otherwise take that face's side alone
    scale = points[node].abs().amax(-1) + distance + slack
    tie = distance <= nearest[node] + 32 * torch.finfo(points.dtype).eps * scale
    side = torch.zeros_like(nearest).index_add_(0, node[tie], along[tie])
    return torch.where(side < 0, -nearest, nearest)


def signed_distances_to_surfaces(points: torch.Tensor, surfaces: torch.Tensor, vertices: torch.Tensor,
                                 triangles: torch.Tensor, triangle_surface: torch.Tensor) -> torch.Tensor:
    """The signed distance ``[N]`` (negative inside) from each of ``points [N, 3]`` to its own closed,
    outward-wound surface ``surfaces [N]`` (int64) among several: the triangles ``[F, 3]`` of
    ``vertices [V, 3]`` with their surface ``triangle_surface [F]`` (int64). Exact, as
    :func:`surface_signed_distances` (the nearest triangle of the point's surface, the side of the
    angle-weighted pseudonormal of the nearest feature): every triangle of a point's surface
    bounded by its sphere, the exact distance taken to those that may be nearest; points taken in
    batches of at most ``PAIRS_PER_BATCH`` point-triangle pairs (one host read of the surfaces'
    sizes). A point whose surface has no triangle gets the dtype's largest value.
    What checks of many bodies inside each other need (``sim.diagnostics.interpenetration``): one
    call for all of them."""
    if points.shape[0] == 0:
        return points.new_zeros(0)
    order = torch.argsort(triangle_surface, stable=True)
    triangles, triangle_surface = triangles[order], triangle_surface[order]
    count = max(int(surfaces.max()), int(triangle_surface.max()) if triangle_surface.numel() else 0) + 1
    per_surface = torch.bincount(triangle_surface, minlength=count)
    first = torch.cumsum(per_surface, 0) - per_surface  # each surface's first triangle
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    angles, spheres = _corner_angles(a, b, c), _spheres(a, b, c)
    pairs = per_surface[surfaces]  # [N] each point's triangles
    ends = torch.cumsum(pairs, 0).cpu()
    signed = torch.empty(points.shape[0], dtype=points.dtype, device=points.device)
    start = 0
    while start < points.shape[0]:  # batches of whole points
        done = int(ends[start - 1]) if start else 0
        stop = max(start + 1, int(torch.searchsorted(ends, done + PAIRS_PER_BATCH, right=True)))
        part = slice(start, stop)
        node, tri = expand_ranges(first[surfaces[part]], pairs[part])  # every triangle of its surface
        node, tri = _within_reach(points[part], node, tri, *spheres)
        signed[part] = _signed_from_pairs(points[part], node, tri, a, b, c, angles, 0.0)
        start = stop
    return signed


def check_closed(triangles: np.ndarray, what: str = "surface") -> None:
    """Raise a MeshError unless every edge of ``triangles [F, 3]`` joins exactly two triangles
    that run along it in opposite directions (a closed, consistently wound surface)."""
    directed = triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2).astype(np.int64)
    undirected, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    open_edges = undirected[counts != 2]
    if len(open_edges):
        shown = ", ".join(f"({i}, {j})" for i, j in open_edges[:3].tolist())
        raise MeshError(f"{what} is not closed: {len(open_edges)} edges are not shared by exactly two triangles "
                        f"(e.g. {shown})")
    _, counts = np.unique(directed, axis=0, return_counts=True)
    if bool((counts != 1).any()):
        raise MeshError(f"{what} is not consistently wound: {int((counts != 1).sum())} edges run the same way in "
                        "both their triangles (flip the triangles of one side)")


@dataclass(frozen=True)
class SignedDistanceGrid:
    """The signed distance of a closed surface sampled on a regular grid (see the module).

    Attributes:
        values: ``[nx, ny, nz]`` phi at the grid nodes (negative inside).
        lower: the first node's position ``[3]``.
        spacing: the distance between neighbouring nodes.
    """

    values: torch.Tensor
    lower: torch.Tensor
    spacing: float

    @property
    def upper(self) -> torch.Tensor:
        """The last node's position ``[3]``."""
        return self.lower + self.spacing * (torch.tensor(self.values.shape, dtype=self.lower.dtype,
                                                         device=self.lower.device) - 1)

    def to(self, dtype=None, device=None) -> "SignedDistanceGrid":
        """This grid with its tensors in ``dtype`` on ``device`` (None keeps each)."""
        return SignedDistanceGrid(self.values.to(dtype=dtype, device=device),
                                  self.lower.to(dtype=dtype, device=device), self.spacing)

    def sample(self, q: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """phi ``[V]``, its gradient ``[V, 3]`` and Hessian ``[V, 3, 3]`` at points ``q [V, 3]``
        (the trilinear interpolant's; outside the grid, phi at the nearest point of the grid's
        box plus the distance to it, its gradient the direction from that point, no Hessian)."""
        shape = torch.tensor(self.values.shape, device=q.device)
        cells = (q - self.lower) / self.spacing
        inside_box = torch.clamp(torch.minimum(cells, (shape - 1).to(q.dtype)), min=0.0)
        corner = torch.minimum(torch.floor(inside_box).to(torch.int64), shape - 2)  # [V, 3]
        t = inside_box - corner.to(q.dtype)  # [V, 3] in [0, 1]
        # the 8 corners' values c[V, 2, 2, 2] (x, y, z offsets)
        offsets = torch.tensor([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], device=q.device)
        idx = corner[:, None, :] + offsets  # [V, 8, 3]
        flat = (idx[..., 0] * shape[1] + idx[..., 1]) * shape[2] + idx[..., 2]
        c = self.values.reshape(-1)[flat].reshape(-1, 2, 2, 2)
        weights = torch.stack([1.0 - t, t], dim=1)  # [V, 2 (offset), 3 (axis)]
        slopes = torch.tensor([-1.0, 1.0], dtype=q.dtype, device=q.device)[None, :, None].expand_as(weights)
        wx, wy, wz = weights[:, :, 0], weights[:, :, 1], weights[:, :, 2]
        sx, sy, sz = slopes[:, :, 0], slopes[:, :, 1], slopes[:, :, 2]

        def contract(fx, fy, fz):
            return torch.einsum("vabc,va,vb,vc->v", c, fx, fy, fz)

        phi = contract(wx, wy, wz)
        h = self.spacing
        grad = torch.stack([contract(sx, wy, wz), contract(wx, sy, wz), contract(wx, wy, sz)], dim=-1) / h
        hxy, hxz, hyz = contract(sx, sy, wz) / h**2, contract(sx, wy, sz) / h**2, contract(wx, sy, sz) / h**2
        zero = torch.zeros_like(hxy)
        hessian = torch.stack([torch.stack([zero, hxy, hxz], -1), torch.stack([hxy, zero, hyz], -1),
                               torch.stack([hxz, hyz, zero], -1)], dim=-2)
        # beyond the box: continued by the distance to it (>= the margin: never in contact)
        out = ((cells < 0) | (cells > (shape - 1).to(q.dtype))).any(-1)  # (not |beyond| > 0: rounding)
        # (ones where inside: no norm of a zero vector, whose derivatives are not finite)
        beyond = torch.where(out[:, None], q - (self.lower + h * inside_box), torch.ones_like(q))
        gap = torch.linalg.vector_norm(beyond, dim=-1)
        direction = beyond / gap[:, None]
        phi = torch.where(out, phi + gap, phi)
        grad = torch.where(out[:, None], direction, grad)
        hessian = torch.where(out[:, None, None], torch.zeros_like(hessian), hessian)
        return phi, grad, hessian


def signed_distance_grid(vertices, triangles, *, resolution: int = 48, spacing: Optional[float] = None,
                         margin: float = 0.0, device=None, what: str = "surface") -> SignedDistanceGrid:
    """The :class:`SignedDistanceGrid` of a closed triangle surface (float64).

    Args:
        vertices: ``[V, 3]`` (a tensor or an array).
        triangles: ``[F, 3]`` node ids: a closed, consistently wound surface (checked).
        resolution: grid cells along the surface's longest side (ignored where ``spacing`` is
            given).
        spacing: the grid's spacing.
        margin: how far past the surface's bounding box the grid reaches, besides two cells (a
            contact thickness: points within it of the surface are on the grid).
        device: where to compute and keep the grid (default: the CPU).
        what: how errors name the surface.

    The surface may be wound either way (consistently): its enclosed volume's sign tells which.

    Raises:
        MeshError: the surface is not closed, is wound inconsistently, or has no volume.
    """
    vertices = torch.as_tensor(vertices, dtype=torch.float64, device=device)
    faces = np.asarray(torch.as_tensor(triangles).cpu(), dtype=np.int64)
    check_closed(faces, what)
    triangles = torch.as_tensor(faces, device=vertices.device)
    low, high = vertices.amin(0), vertices.amax(0)
    extent = float((high - low).max())
    if spacing is None:
        if not isinstance(resolution, int) or isinstance(resolution, bool) or resolution < 2:
            raise MeshError(f"{what}: resolution must be an integer >= 2, got {resolution!r}")
        spacing = extent / resolution
    if not (isinstance(spacing, (int, float)) and math.isfinite(spacing) and spacing > 0):
        raise MeshError(f"{what}: grid spacing must be a positive finite number, got {spacing!r}")
    pad = float(margin) + 2.0 * spacing
    lower = low - pad
    counts = [int(math.ceil(float(n))) + 1 for n in ((high + pad - lower) / spacing).tolist()]
    if math.prod(counts) > 1 << 27:
        raise MeshError(f"{what}: a grid of {counts} nodes is too large; give a coarser spacing or resolution")
    axes = [lower[i] + spacing * torch.arange(counts[i], dtype=torch.float64, device=vertices.device)
            for i in range(3)]
    points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
    a, b, c = (vertices[triangles[:, i]] for i in range(3))
    volume = float((a * torch.linalg.cross(b, c)).sum()) / 6.0  # enclosed volume, signed by the winding
    if abs(volume) <= 1e-9 * extent ** 3:
        raise MeshError(f"{what} encloses no volume (a flat or doubled surface)")
    if volume < 0:  # wound inward: turn it outward
        triangles = triangles[:, [0, 2, 1]]
    values = surface_signed_distances(points.reshape(*counts, 3), vertices, triangles)
    return SignedDistanceGrid(values, lower, float(spacing))
