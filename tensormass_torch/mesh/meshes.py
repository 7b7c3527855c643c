"""Simplicial meshes: tetrahedra (:class:`TetMesh`) and triangles (:class:`TriMesh`).

A mesh holds two tensors and nothing else:

* ``vertices`` -- floating ``[V, d]`` rest positions (``d = 3`` for tetrahedra, 2 or 3 for
  triangles);
* ``elements`` -- int64 ``[N, n]`` node ids (``n = 4`` for tetrahedra, 3 for triangles), on the
  same device as the vertices.

Construction validates the input (shapes, dtypes, indices, degenerate and inverted elements)
and raises :class:`~tensormass_torch.errors.MeshError` naming the offending ids. Meshes are
treated as immutable: every method that changes something returns a new mesh, and the caller's
tensors are copied, never modified.
"""
from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch

from ..errors import InvertedElementsError, MeshError

__all__ = ["Mesh", "TetMesh", "TriMesh"]

# Relative threshold of the degeneracy test: |measure| <= _DEGENERATE_TOL * h^d.
_DEGENERATE_TOL = 1e-12
# How many offending ids an error message lists before summarising the rest.
_MAX_IDS = 10


# ---------------------------------------------------------------------------------------------
# Small helpers
# ---------------------------------------------------------------------------------------------


def _format_ids(ids: torch.Tensor) -> str:
    """``[k]`` integer tensor -> "3, 7, 12" (at most ``_MAX_IDS`` ids, then "... (k more)")."""
    ids = ids.reshape(-1).tolist()
    text = ", ".join(str(i) for i in ids[:_MAX_IDS])
    if len(ids) > _MAX_IDS:
        text += f", ... ({len(ids) - _MAX_IDS} more)"
    return text


def _shape_str(t: torch.Tensor) -> str:
    return "[" + ", ".join(str(s) for s in t.shape) + "]"


def _native_numpy(arr: np.ndarray) -> np.ndarray:
    """A contiguous, native-byte-order view/copy of ``arr``.

    torch.as_tensor refuses big-endian arrays (meshio's VTK reader returns them) and arrays
    with negative strides, so both are normalised here.
    """
    if arr.dtype.byteorder not in ("=", "|"):
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return np.ascontiguousarray(arr)


def _to_tensor(data, what: str, device=None) -> torch.Tensor:
    """Convert a tensor / numpy array / nested list to a tensor, without copying yet."""
    if isinstance(data, torch.Tensor):
        return data
    if isinstance(data, np.ndarray):
        data = _native_numpy(data)
    try:
        return torch.as_tensor(data, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise MeshError(f"{what} could not be converted to a tensor: {exc}") from exc


def _is_empty_sequence(data) -> bool:
    return isinstance(data, (list, tuple)) and len(data) == 0


def _as_vertices(data, dim_hint: int) -> torch.Tensor:
    """Vertices as a fresh, contiguous floating tensor ``[V, d]`` (a copy of the input).

    Floating tensors and numpy arrays keep their dtype; integer input (and Python lists of
    ints) is converted to ``torch.get_default_dtype()``.
    """
    if _is_empty_sequence(data):
        # torch.as_tensor([]) has shape [0]; give it the expected rank so the
        # "empty mesh" check, not the shape check, reports it.
        return torch.empty((0, dim_hint), dtype=torch.get_default_dtype())
    t = _to_tensor(data, "vertices")
    if t.dtype == torch.bool or t.is_complex():
        raise MeshError(f"vertices must be floating point (got {t.dtype})")
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype())
        if not t.is_floating_point():  # a non-floating default dtype cannot happen, but be plain
            raise MeshError(f"vertices must be floating point (got {t.dtype})")
        return t.contiguous()
    # A copy: the mesh must not alias (and so never modify) the caller's storage.
    return t.clone(memory_format=torch.contiguous_format)


def _as_elements(data, nodes_per_element: int, device: torch.device) -> torch.Tensor:
    """Elements as a fresh, contiguous int64 tensor ``[N, n]`` (a copy of the input).

    Torch tensors stay on their device (so mixed devices can be detected); numpy arrays and
    lists are created on ``device`` (the vertices' device).
    """
    if _is_empty_sequence(data):
        return torch.empty((0, nodes_per_element), dtype=torch.int64, device=device)
    t = _to_tensor(data, "elements", device=None if isinstance(data, torch.Tensor) else device)
    if t.is_floating_point() or t.is_complex() or t.dtype == torch.bool:
        # Even integral floats are refused: float ids above 2^24 (float32) are silently wrong.
        raise MeshError(f"elements must be integers (got {t.dtype})")
    if t.dtype == torch.int64:
        return t.clone(memory_format=torch.contiguous_format)
    return t.to(torch.int64).contiguous()


# Local edges of a simplex with n nodes, as node-slot pairs.
_LOCAL_EDGES = {
    4: ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)),
    3: ((0, 1), (0, 2), (1, 2)),
}


def _mean_edge_length(vertices: torch.Tensor, elements: torch.Tensor) -> torch.Tensor:
    """Mean length of the elements' edges (each element counts all its edges) -> scalar."""
    pairs = torch.tensor(_LOCAL_EDGES[elements.shape[1]], device=elements.device)
    a = vertices[elements[:, pairs[:, 0]]]  # [N, e, d]
    b = vertices[elements[:, pairs[:, 1]]]
    return torch.linalg.vector_norm(b - a, dim=-1).mean()


# ---------------------------------------------------------------------------------------------
# Mesh classes
# ---------------------------------------------------------------------------------------------


class Mesh:
    """Base class of :class:`TetMesh` and :class:`TriMesh` (not instantiated directly).

    Attributes:
        vertices: floating ``[V, d]`` rest positions.
        elements: int64 ``[N, n]`` node ids, on ``vertices.device``.
        kind: ``"tet"`` or ``"tri"``.
        nodes_per_element: ``n`` (4 or 3).
    """

    kind: str = ""
    nodes_per_element: int = 0
    _allowed_dims: Tuple[int, ...] = ()
    _measure_name: str = "measure"

    def __init__(self, vertices, elements, *, orient: bool = False, check: bool = True):
        if type(self) is Mesh:
            raise TypeError("Mesh is a base class: build a TetMesh or a TriMesh")
        v = _as_vertices(vertices, self._allowed_dims[-1])
        self._check_vertex_shape(v)
        e = _as_elements(elements, self.nodes_per_element, v.device)
        self._check_element_shape(e)
        if e.device != v.device:
            raise MeshError(
                f"mixed devices: vertices are on {v.device} and elements on {e.device}; "
                "move both to the same device"
            )
        self._vertices = v
        self._elements = e
        if check:
            self._check_data()
        if orient:
            self._elements = self._flip_negative(self._elements)
        elif check:
            self._check_orientation()

    # -- construction without validation (internal: results of already valid meshes) -------

    @classmethod
    def _trusted(cls, vertices: torch.Tensor, elements: torch.Tensor) -> "Mesh":
        """Wrap tensors that are already known to be valid (no copy, no check)."""
        mesh = cls.__new__(cls)
        mesh._vertices = vertices
        mesh._elements = elements
        return mesh

    # -- structural checks (always run: the object is meaningless without them) --------------

    def _check_vertex_shape(self, v: torch.Tensor) -> None:
        dims = " or ".join(f"[V, {d}]" for d in self._allowed_dims)
        if v.dim() != 2 or v.shape[1] not in self._allowed_dims:
            raise MeshError(
                f"{type(self).__name__} vertices must have shape {dims} (got {_shape_str(v)})"
            )

    def _check_element_shape(self, e: torch.Tensor) -> None:
        n = self.nodes_per_element
        if e.dim() != 2 or e.shape[1] != n:
            raise MeshError(
                f"{type(self).__name__} elements must have shape [N, {n}] (got {_shape_str(e)})"
            )

    # -- data checks (check=True) -------------------------------------------------------------

    def _check_data(self) -> None:
        v, e = self._vertices, self._elements
        num_v, num_e = v.shape[0], e.shape[0]
        if num_v == 0 or num_e == 0:
            raise MeshError(f"empty mesh: {num_v} vertices and {num_e} elements")

        bad_v = (~torch.isfinite(v)).any(dim=1).nonzero().flatten()
        if bad_v.numel():
            raise MeshError(f"vertices with NaN or inf coordinates: {_format_ids(bad_v)}")

        out = ((e < 0) | (e >= num_v)).any(dim=1).nonzero().flatten()
        if out.numel():
            first = int(out[0])
            raise MeshError(
                f"elements with node indices outside [0, {num_v}): {_format_ids(out)} "
                f"(element {first} = {e[first].tolist()})"
            )

        # A repeated node shows up as two equal neighbours once each row is sorted.
        s = e.sort(dim=1).values
        rep = (s[:, 1:] == s[:, :-1]).any(dim=1).nonzero().flatten()
        if rep.numel():
            first = int(rep[0])
            raise MeshError(
                f"elements repeating a node: {_format_ids(rep)} "
                f"(element {first} = {e[first].tolist()})"
            )

        with torch.no_grad():
            measure = self.signed_measures().abs()
            h = _mean_edge_length(v, e)
            d = 3 if self.kind == "tet" else 2
            tol = _DEGENERATE_TOL * h**d
            degenerate = (measure <= tol).nonzero().flatten()
        if degenerate.numel():
            raise MeshError(
                f"degenerate (zero-{self._measure_name}) elements: {_format_ids(degenerate)} "
                f"(|{self._measure_name}| <= {_DEGENERATE_TOL:g} * h^{d}, "
                f"h = mean edge length = {float(h):.6g})"
            )

    def _has_orientation(self) -> bool:
        """Tetrahedra and planar triangles have a sign; triangles in 3-D do not."""
        return self.kind == "tet" or self.dim == 2

    def _check_orientation(self) -> None:
        if not self._has_orientation():
            return
        with torch.no_grad():
            inverted = (self.signed_measures() < 0).nonzero().flatten()
        if inverted.numel():
            ids = _format_ids(inverted)
            raise InvertedElementsError(
                f"inverted elements (negative {self._measure_name}): {ids}; "
                "pass orient=True to flip them, or build with check=False and call "
                "mesh.reoriented()", ids
            )

    def _flip_negative(self, elements: torch.Tensor) -> torch.Tensor:
        """``elements`` with the last two nodes of every negative element swapped (a copy)."""
        if not self._has_orientation():
            return elements.clone()
        with torch.no_grad():
            negative = self.signed_measures() < 0  # [N]
        perm = list(range(self.nodes_per_element))
        perm[-2], perm[-1] = perm[-1], perm[-2]
        # torch.where, not masked assignment: no host sync and never touches the input.
        return torch.where(negative[:, None], elements[:, perm], elements)

    # -- properties ----------------------------------------------------------------------------

    @property
    def vertices(self) -> torch.Tensor:
        """Rest positions ``[V, d]``."""
        return self._vertices

    @property
    def elements(self) -> torch.Tensor:
        """Node ids ``[N, n]``, int64."""
        return self._elements

    @property
    def dim(self) -> int:
        """Spatial dimension ``d`` of the vertices (3 for tets, 2 or 3 for triangles)."""
        return int(self._vertices.shape[1])

    @property
    def num_vertices(self) -> int:
        return int(self._vertices.shape[0])

    @property
    def num_elements(self) -> int:
        return int(self._elements.shape[0])

    @property
    def device(self) -> torch.device:
        return self._vertices.device

    @property
    def dtype(self) -> torch.dtype:
        return self._vertices.dtype

    # -- geometry and topology ---------------------------------------------------------------

    def signed_measures(self) -> torch.Tensor:
        """Per-element measure ``[N]`` (subclasses define the sign convention)."""
        raise NotImplementedError

    def reoriented(self) -> "Mesh":
        """A new mesh with every negative element flipped (its last two nodes swapped).

        Triangles in 3-D have no sign and are returned unchanged (as a copy).
        """
        return type(self)._trusted(self._vertices, self._flip_negative(self._elements))

    def to(self, device=None, dtype: Optional[torch.dtype] = None) -> "Mesh":
        """A new mesh on ``device`` with vertices of floating ``dtype`` (None keeps either).

        Tensors that need no conversion are shared with this mesh (meshes are never modified).
        """
        if dtype is not None and not dtype.is_floating_point:
            raise MeshError(f"mesh dtype must be floating point (got {dtype})")
        v = self._vertices.to(device=device, dtype=dtype)
        e = self._elements.to(device=v.device)
        return type(self)._trusted(v, e)

    def unused_vertices(self) -> torch.Tensor:
        """Ids of the vertices no element references, int64 ``[k]`` (sorted)."""
        used = torch.zeros(self.num_vertices, dtype=torch.bool, device=self.device)
        used[self._elements.reshape(-1)] = True
        return (~used).nonzero().flatten()

    def edges(self) -> torch.Tensor:
        """Unique undirected edges ``[Ed, 2]`` int64, ``i < j``, sorted lexicographically."""
        pairs = torch.tensor(_LOCAL_EDGES[self.nodes_per_element], device=self.device)
        a = self._elements[:, pairs[:, 0]].reshape(-1)
        b = self._elements[:, pairs[:, 1]].reshape(-1)
        lo, hi = torch.minimum(a, b), torch.maximum(a, b)
        # One int64 key per edge: a 1-D unique is much faster than unique(dim=0), and sorting
        # the keys sorts the pairs lexicographically.
        n = max(self.num_vertices, 1)
        keys = torch.unique(lo * n + hi)
        return torch.stack((keys // n, keys % n), dim=1)

    def __repr__(self) -> str:
        return (
            f"{type(self).__name__}(kind={self.kind!r}, num_vertices={self.num_vertices}, "
            f"num_elements={self.num_elements}, dim={self.dim}, dtype={self.dtype}, "
            f"device={self.device})"
        )


class TetMesh(Mesh):
    """Tetrahedral mesh: vertices ``[V, 3]`` float, tets ``[N, 4]`` int64.

    Args:
        vertices: ``[V, 3]`` tensor, numpy array or nested list. A floating tensor keeps its
            dtype and device, a floating numpy array its dtype; integers and lists get
            ``torch.get_default_dtype()``. Always copied.
        tets: ``[N, 4]`` integer node ids (any integer dtype; floats are refused). Numpy
            arrays and lists are put on the vertices' device. Always copied.
        orient: flip (swap the last two nodes of) tets with negative volume instead of
            raising.
        check: validate the data (finite coordinates, index range, repeated nodes, empty
            mesh, degenerate and inverted tets). Shapes, dtypes and devices are always
            checked.

    Raises:
        MeshError: naming the problem and the offending vertex or element ids.
    """

    kind = "tet"
    nodes_per_element = 4
    _allowed_dims = (3,)
    _measure_name = "volume"

    def __init__(self, vertices, tets, *, orient: bool = False, check: bool = True):
        super().__init__(vertices, tets, orient=orient, check=check)

    def signed_measures(self) -> torch.Tensor:
        """Signed volumes ``[N]``: ``det[X1 - X0, X2 - X0, X3 - X0] / 6``."""
        x = self._vertices[self._elements]  # [N, 4, 3]
        e1, e2, e3 = (x[:, k] - x[:, 0] for k in (1, 2, 3))
        return (torch.linalg.cross(e1, e2) * e3).sum(dim=-1) / 6


class TriMesh(Mesh):
    """Triangle mesh: vertices ``[V, 2]`` or ``[V, 3]`` float, triangles ``[N, 3]`` int64.

    Planar (``[V, 2]``) triangles have a sign (counter-clockwise is positive) and are checked
    for inversion like tets; triangles in 3-D have none (their measure is the unsigned area).
    Arguments and errors as :class:`TetMesh`.
    """

    kind = "tri"
    nodes_per_element = 3
    _allowed_dims = (2, 3)
    _measure_name = "area"

    def __init__(self, vertices, triangles, *, orient: bool = False, check: bool = True):
        super().__init__(vertices, triangles, orient=orient, check=check)

    def signed_measures(self) -> torch.Tensor:
        """Areas ``[N]``: signed in 2-D (``cross(X1 - X0, X2 - X0) / 2``), unsigned in 3-D."""
        x = self._vertices[self._elements]  # [N, 3, d]
        e1, e2 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]
        if self.dim == 2:
            return (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) / 2
        return torch.linalg.vector_norm(torch.linalg.cross(e1, e2), dim=-1) / 2
