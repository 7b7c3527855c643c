"""Structured grids: :func:`beam_mesh` (hexahedra cut into tetrahedra) and :func:`beam_tri_mesh`
(quads cut into triangles), the benchmark beams."""
from __future__ import annotations

import itertools
import math
import numbers
from typing import Optional, Sequence, Tuple

import numpy as np
import torch

from ..errors import MeshError
from .meshes import TetMesh, TriMesh

__all__ = ["beam_mesh", "beam_tri_mesh"]

# ---------------------------------------------------------------------------------------------

# Corners of the unit cube (quad) are numbered a + 2 b + 4 c for local coordinates (a, b, c).


def _corner_id(p: Sequence[int]) -> int:
    return sum(int(bit) << axis for axis, bit in enumerate(p))


def _oriented(simplex: list, coords: np.ndarray) -> list:
    """``simplex`` (corner ids) with its last two corners swapped if its measure is negative."""
    x = coords[simplex]
    if np.linalg.det(x[1:] - x[0]) < 0:
        simplex = simplex[:-2] + [simplex[-1], simplex[-2]]
    return simplex


def _hex_templates() -> np.ndarray:
    """``[8, 6, 4]`` corner ids of the 6 positive tets of a cube, per mirror configuration.

    Configuration ``m = mx + 2 my + 4 mz``: the Kuhn split (the 6 monotone paths from corner
    (0,0,0) to (1,1,1) along the axes, i.e. all tets share the main diagonal) in a frame
    mirrored along the axes whose bit is set. Every face of the cube is cut along the diagonal
    that joins its (mirrored) lowest and highest corners, which depends only on the mirror bits
    of the two axes spanning that face: two cells that share a face agree on those bits when
    the mirror of axis x depends only on i (and so on), so the grid stays conforming.
    """
    coords = np.array([[(c >> axis) & 1 for axis in range(3)] for c in range(8)], float)
    templates = []
    for m in range(8):
        mirror = np.array([(m >> axis) & 1 for axis in range(3)])
        tets = []
        for perm in itertools.permutations(range(3)):
            p = np.zeros(3, dtype=int)
            path = [p.copy()]
            for axis in perm:
                p[axis] = 1
                path.append(p.copy())
            tet = [_corner_id(q ^ mirror) for q in path]
            tets.append(_oriented(tet, coords))
        templates.append(tets)
    return np.array(templates, dtype=np.int64)


def _quad_templates() -> np.ndarray:
    """``[4, 2, 3]`` corner ids of the 2 positive triangles of a quad, per mirror configuration.

    The quad is cut along the diagonal from its (mirrored) corner (0,0) to (1,1); mirroring in
    exactly one of x, y switches to the other diagonal.
    """
    coords = np.array([[(c >> axis) & 1 for axis in range(2)] for c in range(4)], float)
    templates = []
    for m in range(4):
        mirror = np.array([(m >> axis) & 1 for axis in range(2)])
        paths = ([(0, 0), (1, 0), (1, 1)], [(0, 0), (0, 1), (1, 1)])
        tris = [_oriented([_corner_id(np.array(q) ^ mirror) for q in path], coords)
                for path in paths]
        templates.append(tris)
    return np.array(templates, dtype=np.int64)


_HEX_TEMPLATES = _hex_templates()
_QUAD_TEMPLATES = _quad_templates()
_CUTS = ("alternating", "uniform")


def _check_counts(**counts) -> Tuple[int, ...]:
    out = []
    for name, n in counts.items():
        if isinstance(n, bool) or not isinstance(n, numbers.Integral) or n <= 0:
            raise MeshError(f"{name} must be a positive int (got {n!r})")
        out.append(int(n))
    return tuple(out)


def _check_vector(name: str, value, length: int, positive: bool) -> Tuple[float, ...]:
    try:
        vals = tuple(float(x) for x in value)
    except (TypeError, ValueError) as exc:
        raise MeshError(f"{name} must be {length} numbers (got {value!r})") from exc
    if len(vals) != length:
        raise MeshError(f"{name} must be {length} numbers (got {value!r})")
    if not all(math.isfinite(x) for x in vals):
        raise MeshError(f"{name} must be finite (got {value!r})")
    if positive and not all(x > 0 for x in vals):
        raise MeshError(f"{name} must be positive (got {value!r})")
    return vals


def _check_grid_options(cut: str, dtype, device) -> Tuple[torch.dtype, torch.device]:
    if cut not in _CUTS:
        raise MeshError(f"cut must be one of {_CUTS} (got {cut!r})")
    dtype = torch.get_default_dtype() if dtype is None else dtype
    if not isinstance(dtype, torch.dtype) or not dtype.is_floating_point:
        raise MeshError(f"dtype must be a floating torch dtype (got {dtype!r})")
    return dtype, torch.device("cpu" if device is None else device)


def _axis_coords(n: int, start: float, length: float, dtype, device) -> torch.Tensor:
    """``n + 1`` evenly spaced coordinates ``[n + 1]`` from start to start + length.

    Computed in float64 (on the host: it is tiny) so the end points are exact, then cast.
    """
    t = torch.arange(n + 1, dtype=torch.float64) / n
    return (start + length * t).to(dtype=dtype, device=device)


def _parity(idx: torch.Tensor) -> torch.Tensor:
    return idx & 1


def beam_mesh(
    nx: int,
    ny: int,
    nz: int,
    size: Sequence[float] = (1.0, 1.0, 1.0),
    origin: Sequence[float] = (0.0, 0.0, 0.0),
    cut: str = "alternating",
    dtype: Optional[torch.dtype] = None,
    device=None,
) -> TetMesh:
    """A box of ``nx * ny * nz`` hexahedra, each cut into 6 tetrahedra.

    The box spans ``origin .. origin + size``. Nodes ``[(nx+1)(ny+1)(nz+1), 3]`` are numbered
    ``i + (nx+1) * (j + (ny+1) * k)``; tets ``[6 nx ny nz, 4]`` come cell by cell (cell
    ``i + nx * (j + ny * k)`` owns tets ``6 c .. 6 c + 5``), all with positive volume. The mesh
    is conforming: a face shared by two cells is cut along the same diagonal by both.

    Args:
        nx, ny, nz: number of cells along x, y, z (positive ints).
        size: box lengths ``(Lx, Ly, Lz)``, positive.
        origin: the box's lowest corner.
        cut: ``"uniform"`` -- every hex split the same way (Kuhn/Freudenthal split, all six tets
            around the cell's main diagonal). It is anisotropic: every cell's long diagonals
            point the same way, which biases the stiffness of the beam (it bends differently
            in +x/+y than in the mirrored directions).
            ``"alternating"`` (default) -- the same split mirrored in x, y, z according to the
            parity of the cell index ``i``, ``j``, ``k``; still conforming, with no preferred
            direction.
        dtype: floating dtype of the vertices (default ``torch.get_default_dtype()``).
        device: device of both tensors (default CPU).

    Raises:
        MeshError: on non-positive counts or sizes, a non-finite origin, an unknown ``cut``.
    """
    nx, ny, nz = _check_counts(nx=nx, ny=ny, nz=nz)
    size = _check_vector("size", size, 3, positive=True)
    origin = _check_vector("origin", origin, 3, positive=False)
    dtype, device = _check_grid_options(cut, dtype, device)

    # Vertices: meshgrid over (z, y, x) so that x varies fastest, as the numbering requires.
    axes = [_axis_coords(n, o, s, dtype, device) for n, o, s in zip((nx, ny, nz), origin, size)]
    zz, yy, xx = torch.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    vertices = torch.stack((xx, yy, zz), dim=-1).reshape(-1, 3)

    # Cells, in the element order i + nx * (j + ny * k).
    k, j, i = torch.meshgrid(
        *(torch.arange(n, device=device) for n in (nz, ny, nx)), indexing="ij"
    )
    i, j, k = i.reshape(-1), j.reshape(-1), k.reshape(-1)
    base = i + (nx + 1) * (j + (ny + 1) * k)  # node id of each cell's corner (0, 0, 0)  [C]
    if cut == "alternating":
        config = _parity(i) + 2 * _parity(j) + 4 * _parity(k)
    else:
        config = torch.zeros_like(base)

    # Node offset of local corner a + 2b + 4c from the cell's base node.
    sx, sy = 1, nx + 1
    sz = (nx + 1) * (ny + 1)
    offsets = torch.tensor(
        [a * sx + b * sy + c * sz for c in (0, 1) for b in (0, 1) for a in (0, 1)],
        dtype=torch.int64, device=device,
    )
    templates = torch.as_tensor(_HEX_TEMPLATES, device=device)  # [8, 6, 4]
    tets = base[:, None, None] + offsets[templates[config]]  # [C, 6, 4]
    return TetMesh._trusted(vertices, tets.reshape(-1, 4))


def beam_tri_mesh(
    nx: int,
    ny: int,
    size: Sequence[float] = (1.0, 1.0),
    origin: Sequence[float] = (0.0, 0.0),
    cut: str = "alternating",
    dim: int = 2,
    dtype: Optional[torch.dtype] = None,
    device=None,
) -> TriMesh:
    """A rectangle of ``nx * ny`` quads, each cut into 2 counter-clockwise triangles.

    Nodes ``[(nx+1)(ny+1), dim]`` are numbered ``i + (nx+1) * j``; triangles ``[2 nx ny, 3]``
    come quad by quad (quad ``i + nx * j`` owns triangles ``2 q`` and ``2 q + 1``).

    Args:
        nx, ny: number of quads along x and y (positive ints).
        size: ``(Lx, Ly)``, positive.  origin: the lowest corner.
        cut: ``"uniform"`` -- every quad cut along the same diagonal (anisotropic);
            ``"alternating"`` (default) -- the diagonal switches with the parity of ``i + j``
            (a criss-cross pattern with no preferred direction).
        dim: 2 for ``[V, 2]`` vertices, 3 for the same mesh lifted to ``z = 0``.
        dtype, device: as :func:`beam_mesh`.
    """
    nx, ny = _check_counts(nx=nx, ny=ny)
    size = _check_vector("size", size, 2, positive=True)
    origin = _check_vector("origin", origin, 2, positive=False)
    if dim not in (2, 3) or isinstance(dim, bool):
        raise MeshError(f"dim must be 2 or 3 (got {dim!r})")
    dtype, device = _check_grid_options(cut, dtype, device)

    ax = _axis_coords(nx, origin[0], size[0], dtype, device)
    ay = _axis_coords(ny, origin[1], size[1], dtype, device)
    yy, xx = torch.meshgrid(ay, ax, indexing="ij")
    columns = [xx, yy] + ([torch.zeros_like(xx)] if dim == 3 else [])
    vertices = torch.stack(columns, dim=-1).reshape(-1, dim)

    j, i = torch.meshgrid(*(torch.arange(n, device=device) for n in (ny, nx)), indexing="ij")
    i, j = i.reshape(-1), j.reshape(-1)
    base = i + (nx + 1) * j  # [Q]
    if cut == "alternating":
        config = _parity(i) + 2 * _parity(j)
    else:
        config = torch.zeros_like(base)

    offsets = torch.tensor([a + b * (nx + 1) for b in (0, 1) for a in (0, 1)],
                           dtype=torch.int64, device=device)
    templates = torch.as_tensor(_QUAD_TEMPLATES, device=device)  # [4, 2, 3]
    tris = base[:, None, None] + offsets[templates[config]]  # [Q, 2, 3]
    return TriMesh._trusted(vertices, tris.reshape(-1, 3))
