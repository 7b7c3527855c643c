"""Tetrahedral meshes of implicit shapes (signed distance functions), made without any download.

    shape = meshgen.rabbit_shape(size=1.0)               # an SDF with its bounding box
    mesh = meshgen.tetrahedralize(shape, cell=0.05)      # TetMesh
    mesh = meshgen.sphere_mesh(0.5, cell=0.05)

The method: the shape's bounding box is filled with a lattice of cubes, each cut into six
tetrahedra (``beam_mesh``'s alternating Kuhn cut: conforming, no preferred direction); the tets
whose centroid lies inside the shape are kept; only the largest face-connected part is kept and
unused lattice nodes are dropped; then the nodes on the boundary are moved onto the surface by a
few Newton steps on the SDF, each move shortened (down to nothing) wherever it would leave a tet
with less than ``min_volume_ratio`` of its lattice volume. The result is positively oriented,
connected, and has no unused vertex.

An SDF here is any function ``points [P, 3] float64 -> values [P]``, negative inside. Exact
distances are not needed (the ellipsoid's is approximate): only the sign and a usable gradient
near the surface matter.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Optional, Tuple

import numpy as np
import torch

from ..errors import MeshError
from .beams import beam_mesh
from .meshes import TetMesh

__all__ = [
    "Shape", "tetrahedralize", "sphere_shape", "capsule_shape", "ellipsoid_shape", "smooth_union",
    "rabbit_shape", "sphere_mesh", "capsule_mesh", "rabbit_mesh",
]

SDF = Callable[[torch.Tensor], torch.Tensor]


@dataclass(frozen=True)
class Shape:
    """An implicit solid: ``sdf(points [P, 3]) -> [P]`` (negative inside) and a box containing it.

    Attributes:
        sdf: the signed distance function (float64 points in, float64 values out).
        lower, upper: corners of a box that contains the solid, 3 floats each.
    """

    sdf: SDF
    lower: Tuple[float, float, float]
    upper: Tuple[float, float, float]

    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        return self.sdf(points)


def _vec3(name: str, value) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.shape != (3,) or not bool(torch.isfinite(t).all()):
        raise MeshError(f"{name} must be 3 finite numbers, got {value!r}")
    return t


def _positive(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise MeshError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


# ---------------------------------------------------------------------------------------------
# Shapes
# ---------------------------------------------------------------------------------------------


def sphere_shape(radius: float, center=(0.0, 0.0, 0.0)) -> Shape:
    """A ball of ``radius`` around ``center`` (exact distance)."""
    radius, c = _positive("radius", radius), _vec3("center", center)
    lo, hi = (c - radius).tolist(), (c + radius).tolist()
    return Shape(lambda p: (p - c.to(p)).norm(dim=-1) - radius, tuple(lo), tuple(hi))


def capsule_shape(radius: float, length: float, center=(0.0, 0.0, 0.0)) -> Shape:
    """Points within ``radius`` of a segment of ``length`` along x centred at ``center`` (exact)."""
    radius, length, c = _positive("radius", radius), _positive("length", length), _vec3("center", center)
    half = torch.tensor([length / 2, 0.0, 0.0], dtype=torch.float64)

    def sdf(p):
        q = p - c.to(p)
        # Distance to the segment [-half, half]: clamp the x coordinate onto it.
        x = q[:, 0].clamp(-length / 2, length / 2)
        return torch.stack((q[:, 0] - x, q[:, 1], q[:, 2]), dim=1).norm(dim=-1) - radius

    ext = half + radius
    ext[1:] = radius
    return Shape(sdf, tuple((c - ext).tolist()), tuple((c + ext).tolist()))


def ellipsoid_shape(radii, center=(0.0, 0.0, 0.0)) -> Shape:
    """An axis-aligned ellipsoid (an approximate distance with the exact zero set and sign)."""
    r, c = _vec3("radii", radii), _vec3("center", center)
    if bool((r <= 0).any()):
        raise MeshError(f"radii must be positive, got {radii!r}")

    def sdf(p):
        q = p - c.to(p)
        k0 = (q / r.to(p)).norm(dim=-1)
        k1 = (q / (r * r).to(p)).norm(dim=-1)
        # k0 (k0 - 1) / k1 is first-order exact at the surface; near the centre use the bound
        # (k0 - 1) * min(r), which has the right sign.
        safe = k1 > 1e-12
        return torch.where(safe, k0 * (k0 - 1) / torch.where(safe, k1, torch.ones_like(k1)),
                           (k0 - 1) * float(r.min()))

    return Shape(sdf, tuple((c - r).tolist()), tuple((c + r).tolist()))


def smooth_union(a: Shape, b: Shape, blend: float) -> Shape:
    """``a`` and ``b`` merged with a fillet of width ~``blend`` (polynomial smooth minimum)."""
    k = _positive("blend", blend)

    def sdf(p):
        da, db = a(p), b(p)
        h = (0.5 + 0.5 * (db - da) / k).clamp(0.0, 1.0)
        return db + (da - db) * h - k * h * (1.0 - h)

    lo = tuple(min(x, y) - k for x, y in zip(a.lower, b.lower))
    hi = tuple(max(x, y) + k for x, y in zip(a.upper, b.upper))
    return Shape(sdf, lo, hi)


def _above(shape: Shape, z: float) -> Shape:
    """``shape`` cut flat by the plane at height ``z`` (only z >= z kept)."""
    return Shape(lambda p: torch.maximum(shape(p), z - p[:, 2]), (shape.lower[0], shape.lower[1], z), shape.upper)


def _moved(shape: Shape, offset) -> Shape:
    o = _vec3("origin", offset)
    return Shape(lambda p: shape(p - o.to(p)), tuple((torch.tensor(shape.lower) + o).tolist()),
                 tuple((torch.tensor(shape.upper) + o).tolist()))


def rabbit_shape(size: float = 1.0, origin=(0.0, 0.0, 0.0)) -> Shape:
    """A rabbit-like body ``size`` long (x), facing +x, sitting on a flat base at ``origin``.

    Smooth unions of ellipsoids: a body, a head, two long ears and a round tail; the base is cut
    flat at z = 0 so that it rests on a floor. About ``1.05 size`` long and ``1.1 size`` high.
    """
    s = _positive("size", size)

    def ell(radii, center):
        return ellipsoid_shape([s * v for v in radii], [s * v for v in center])

    body = ell((0.42, 0.27, 0.28), (0.0, 0.0, 0.24))
    head = ell((0.19, 0.16, 0.16), (0.36, 0.0, 0.58))
    ears = smooth_union(ell((0.06, 0.055, 0.21), (0.33, 0.09, 0.9)), ell((0.06, 0.055, 0.21), (0.33, -0.09, 0.9)),
                        0.02 * s)
    tail = sphere_shape(0.09 * s, (-0.44 * s, 0.0, 0.34 * s))
    shape = smooth_union(smooth_union(smooth_union(body, head, 0.08 * s), ears, 0.06 * s), tail, 0.04 * s)
    return _moved(_above(shape, 0.0), origin)


# ---------------------------------------------------------------------------------------------
# Tetrahedralisation
# ---------------------------------------------------------------------------------------------

# Faces of a tet, as node positions in its row.
_TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def _face_keys(tets: np.ndarray) -> np.ndarray:
    """One int64 key per face of each tet, ``[N, 4]``, equal for the two tets sharing a face."""
    faces = np.sort(tets[:, _TET_FACES], axis=2)  # [N, 4, 3]
    n = int(tets.max()) + 1
    return (faces[..., 0] * n + faces[..., 1]) * n + faces[..., 2]


def _largest_component(tets: np.ndarray) -> np.ndarray:
    """Bool mask ``[N]`` of the tets in the largest face-connected component."""
    keys = _face_keys(tets).reshape(-1)
    owner = np.repeat(np.arange(len(tets)), 4)
    order = np.argsort(keys, kind="stable")
    keys, owner = keys[order], owner[order]
    shared = keys[1:] == keys[:-1]
    a, b = owner[:-1][shared], owner[1:][shared]
    # Union-find with full path compression, vectorised: hook roots onto smaller roots, then
    # flatten the trees; repeat until every shared face joins two tets of one root.
    parent = np.arange(len(tets))
    while True:
        pa, pb = parent[a], parent[b]
        differ = pa != pb
        if not differ.any():
            break
        np.minimum.at(parent, np.maximum(pa, pb)[differ], np.minimum(pa, pb)[differ])
        while True:
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand
    roots, counts = np.unique(parent, return_counts=True)
    return parent == roots[np.argmax(counts)]


def _boundary_nodes(tets: np.ndarray, num_nodes: int) -> np.ndarray:
    """Bool mask ``[V]`` of the nodes on faces that belong to one tet only."""
    keys = _face_keys(tets).reshape(-1)
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    single = (counts[inverse] == 1).reshape(-1, 4)
    on = np.zeros(num_nodes, dtype=bool)
    on[tets[:, _TET_FACES][single].reshape(-1)] = True
    return on


def _signed_volumes(x: torch.Tensor, tets: torch.Tensor) -> torch.Tensor:
    """Signed volumes ``[N]`` of ``tets [N, 4]`` at positions ``x [V, 3]``."""
    a, b, c, d = (x[tets[:, i]] for i in range(4))
    return (torch.cross(b - a, c - a, dim=1) * (d - a)).sum(dim=1) / 6.0


def _project(sdf: SDF, x: torch.Tensor, step: float, iterations: int) -> torch.Tensor:
    """Newton steps x -= f(x) grad f / |grad f|^2 toward the zero set, ``[k, 3]``."""
    eye = torch.eye(3, dtype=x.dtype) * step
    for _ in range(iterations):
        f = sdf(x)
        grad = torch.stack([(sdf(x + eye[i]) - sdf(x - eye[i])) / (2 * step) for i in range(3)], dim=1)
        norm2 = (grad * grad).sum(dim=1).clamp_min(1e-24)
        x = x - (f / norm2).unsqueeze(1) * grad
    return x


def _snap(sdf: SDF, x: torch.Tensor, tets: torch.Tensor, boundary: torch.Tensor, cell: float,
          min_volume_ratio: float, iterations: int):
    """Boundary nodes moved onto the surface, keeping every tet above ``min_volume_ratio`` of
    its lattice volume. Returns the new positions ``[V, 3]`` and a mask ``[N]`` of the tets to
    keep: a tet whose four nodes all lie on the surface is flattened by the snap (it spans a
    nearly flat piece of the surface) and is dropped instead, which loses almost no volume."""
    ids = boundary.nonzero().flatten()
    target = _project(sdf, x[ids], 1e-3 * cell, iterations)
    move = target - x[ids]
    # A node may move at most one cell: further means the projection found another sheet.
    move[move.norm(dim=1) > cell] = 0.0
    floor = min_volume_ratio * _signed_volumes(x, tets)  # [N]
    y = x.clone()
    y[ids] += move
    keep = ~((_signed_volumes(y, tets) < floor) & boundary[tets].all(dim=1))
    tets_kept = tets[keep]
    floor = floor[keep]
    fraction = torch.ones(len(ids), dtype=x.dtype)
    slot = torch.full((x.shape[0],), -1, dtype=torch.long)
    slot[ids] = torch.arange(len(ids))
    for attempt in range(12):
        y = x.clone()
        y[ids] += fraction.unsqueeze(1) * move
        bad = _signed_volumes(y, tets_kept) < floor
        if not bool(bad.any()):
            return y, keep
        nodes = slot[tets_kept[bad].reshape(-1)]
        nodes = torch.unique(nodes[nodes >= 0])
        # Halve the offending moves; after a few halvings give them up entirely.
        fraction[nodes] = 0.0 if attempt >= 8 else fraction[nodes] * 0.5
    return x, torch.ones_like(keep)  # unreachable in practice: with every move given up, the lattice is valid


def _connected_part(x: torch.Tensor, tets: np.ndarray):
    """The largest face-connected part, its unused vertices dropped: ``([V', 3], [N', 4])``."""
    tets = tets[_largest_component(tets)]
    used, remap = np.unique(tets, return_inverse=True)
    return x[torch.from_numpy(used)], torch.from_numpy(remap.reshape(-1, 4).astype(np.int64))


def tetrahedralize(shape: Shape, cell: float, *, snap: bool = True, min_volume_ratio: float = 0.25,
                   snap_iterations: int = 4, dtype: Optional[torch.dtype] = None) -> TetMesh:
    """A tetrahedral mesh of the solid ``shape`` with lattice spacing ``cell``.

    Args:
        shape: a :class:`Shape` (an SDF and a box containing the solid).
        cell: edge of the lattice cubes (each cut into 6 tets), > 0.
        snap: move boundary nodes onto the surface (else the result is a staircase of cubes).
        min_volume_ratio: a snapped tet keeps at least this fraction of its lattice volume.
        snap_iterations: Newton steps of the projection onto the surface.
        dtype: vertex dtype of the result (default float64; the work is done in float64).

    Returns:
        a :class:`TetMesh`: positively oriented, face-connected (the largest part), with no
        unused vertex, validated.

    Raises:
        MeshError: bad arguments, or no tet of the lattice has its centroid inside (``cell``
        too large for the shape).
    """
    cell = _positive("cell", cell)
    if not 0 <= min_volume_ratio < 1:
        raise MeshError(f"min_volume_ratio must lie in [0, 1), got {min_volume_ratio!r}")
    lower = torch.tensor(shape.lower, dtype=torch.float64) - cell
    upper = torch.tensor(shape.upper, dtype=torch.float64) + cell
    counts = torch.ceil((upper - lower) / cell).long().clamp_min(1)
    if int(counts.prod()) > 20_000_000:
        raise MeshError(f"cell {cell:g} is too small for a box of {(upper - lower).tolist()}: "
                        f"{counts.tolist()} cubes")
    lattice = beam_mesh(*counts.tolist(), size=(counts * cell).tolist(), origin=lower.tolist(),
                        dtype=torch.float64)
    x, tets = lattice.vertices, lattice.elements
    inside = shape(x[tets].mean(dim=1)) < 0
    if not bool(inside.any()):
        raise MeshError(f"no lattice tet lies inside the shape: cell {cell:g} is too large for it")
    x, tets = _connected_part(x, tets[inside].numpy())
    if snap:
        boundary = torch.from_numpy(_boundary_nodes(tets.numpy(), x.shape[0]))
        x, keep = _snap(shape.sdf, x, tets, boundary, cell, min_volume_ratio, snap_iterations)
        x, tets = _connected_part(x, tets[keep].numpy())
    mesh = TetMesh(x, tets)  # validates: no degenerate or inverted tet
    return mesh if dtype is None else mesh.to(dtype=dtype)


# ---------------------------------------------------------------------------------------------
# Ready-made bodies
# ---------------------------------------------------------------------------------------------


def sphere_mesh(radius: float, center=(0.0, 0.0, 0.0), cell: Optional[float] = None, **kwargs) -> TetMesh:
    """A ball (default ``cell = radius / 4``); ``kwargs`` go to :func:`tetrahedralize`."""
    shape = sphere_shape(radius, center)
    return tetrahedralize(shape, cell if cell is not None else radius / 4, **kwargs)


def capsule_mesh(radius: float, length: float, center=(0.0, 0.0, 0.0), cell: Optional[float] = None,
                 **kwargs) -> TetMesh:
    """A capsule along x (default ``cell = radius / 3``)."""
    shape = capsule_shape(radius, length, center)
    return tetrahedralize(shape, cell if cell is not None else radius / 3, **kwargs)


def rabbit_mesh(size: float = 1.0, cell: Optional[float] = None, origin=(0.0, 0.0, 0.0), **kwargs) -> TetMesh:
    """The rabbit-like body of :func:`rabbit_shape` (default ``cell = 0.08 size``)."""
    shape = rabbit_shape(size, origin)
    return tetrahedralize(shape, cell if cell is not None else 0.08 * size, **kwargs)
