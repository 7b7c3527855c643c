"""Tests of tensormass_torch.mesh.meshes: construction, validation, geometry, structured grids."""
import time

import numpy as np
import pytest
import torch

from tensormass_torch.errors import MeshError
from tensormass_torch.mesh.beams import beam_mesh, beam_tri_mesh
from tensormass_torch.mesh.meshes import Mesh, TetMesh, TriMesh

# The unit tet and two unit right triangles, all positively oriented.
TET_V = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
TET_E = [[0, 1, 2, 3]]
TRI_V = [[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]]
TRI_E = [[0, 1, 2], [1, 3, 2]]


# ---------------------------------------------------------------------------------------------
# Construction and conversions
# ---------------------------------------------------------------------------------------------


def test_tet_attributes_and_repr():
    m = TetMesh(TET_V, TET_E)
    assert m.kind == "tet" and m.nodes_per_element == 4 and m.dim == 3
    assert m.num_vertices == 4 and m.num_elements == 1
    assert m.vertices.shape == (4, 3) and m.elements.shape == (1, 4)
    assert m.elements.dtype == torch.int64
    assert m.device == torch.device("cpu") and m.dtype == torch.get_default_dtype()
    r = repr(m)
    dtype = str(torch.get_default_dtype())
    for part in ("TetMesh", "'tet'", "num_vertices=4", "num_elements=1", "dim=3", dtype, "cpu"):
        assert part in r


def test_tri_attributes():
    m2 = TriMesh(TRI_V, TRI_E)
    assert (m2.kind, m2.nodes_per_element, m2.dim) == ("tri", 3, 2)
    m3 = TriMesh([v + [0.0] for v in TRI_V], TRI_E)
    assert m3.dim == 3 and m3.vertices.shape == (4, 3)


def test_base_class_is_abstract():
    with pytest.raises(TypeError):
        Mesh(TET_V, TET_E)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_kept_for_float_tensors(dtype):
    m = TetMesh(torch.tensor(TET_V, dtype=dtype), torch.tensor(TET_E))
    assert m.dtype == dtype


def test_dtype_rules_for_numpy_lists_and_ints():
    assert TetMesh(np.array(TET_V), TET_E).dtype == torch.float64  # numpy float64 stays
    assert TetMesh(np.array(TET_V, np.float32), TET_E).dtype == torch.float32
    assert TetMesh(TET_V, TET_E).dtype == torch.get_default_dtype()  # lists: default
    ints = torch.tensor(TET_V).to(torch.int32)
    assert TetMesh(ints, TET_E).dtype == torch.get_default_dtype()  # ints: default
    assert TetMesh(np.array(TET_V).astype(np.int64), TET_E).dtype == torch.get_default_dtype()
    big_endian = np.array(TET_V, dtype=">f8")  # as meshio's VTK reader returns them
    assert TetMesh(big_endian, np.array(TET_E, ">i4")).dtype == torch.float64


@pytest.mark.parametrize("make", [
    lambda: torch.tensor(TET_E, dtype=torch.int32),
    lambda: torch.tensor(TET_E, dtype=torch.int16),
    lambda: np.array(TET_E, dtype=np.uint8),
    lambda: np.array(TET_E, dtype=np.int32),
    lambda: TET_E,
    lambda: (tuple(TET_E[0]),),
])
def test_elements_any_integer_type(make):
    m = TetMesh(TET_V, make())
    assert m.elements.dtype == torch.int64 and m.elements.tolist() == TET_E


def test_inputs_are_copied_not_aliased():
    v = torch.tensor(TET_V)
    e = torch.tensor(TET_E)
    m = TetMesh(v, e)
    v[0, 0] = 5.0
    e[0, 0] = 3
    assert m.vertices[0, 0] == 0.0 and m.elements[0, 0] == 0


def test_to_dtype_and_device():
    m = TetMesh(TET_V, TET_E)
    m64 = m.to(dtype=torch.float64)
    assert isinstance(m64, TetMesh) and m64 is not m
    assert m64.dtype == torch.float64 and m.dtype == torch.float32
    assert torch.equal(m64.elements, m.elements)
    assert m.to(device="cpu").device == torch.device("cpu")
    with pytest.raises(MeshError, match="floating"):
        m.to(dtype=torch.int32)


# ---------------------------------------------------------------------------------------------
# Geometry and topology
# ---------------------------------------------------------------------------------------------


def test_signed_measures():
    tet = TetMesh(torch.tensor(TET_V, dtype=torch.float64), TET_E)
    assert torch.allclose(tet.signed_measures(), torch.tensor([1 / 6], dtype=torch.float64))
    tri = TriMesh(torch.tensor(TRI_V, dtype=torch.float64), TRI_E)
    assert torch.allclose(tri.signed_measures(), torch.full((2,), 0.5, dtype=torch.float64))
    # Triangles in 3-D: unsigned area (a clockwise one is still positive).
    v3 = torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, 3.0]], dtype=torch.float64)
    tri3 = TriMesh(v3, [[0, 2, 1]])
    assert torch.allclose(tri3.signed_measures(), torch.tensor([3.0], dtype=torch.float64))


def test_reoriented_flips_negative_elements_only():
    v = torch.tensor(TET_V + [[1.0, 1.0, 1.0]])
    e = torch.tensor([[0, 2, 1, 3], [1, 2, 3, 4]])  # first inverted
    e_before = e.clone()
    m = TetMesh(v, e, check=False)
    assert (m.signed_measures() < 0).tolist() == [True, (m.signed_measures()[1] < 0).item()]
    r = m.reoriented()
    assert isinstance(r, TetMesh)
    assert (r.signed_measures() > 0).all()
    assert r.elements[0].tolist() == [0, 2, 3, 1]  # last two nodes swapped
    assert torch.equal(e, e_before) and torch.equal(m.elements, e_before)  # nothing in place


def test_orient_true_flips_silently():
    e = torch.tensor([[0, 1, 3, 2]])
    m = TetMesh(TET_V, e, orient=True)
    assert m.elements.tolist() == [[0, 1, 2, 3]]
    assert e.tolist() == [[0, 1, 3, 2]]
    t = TriMesh(TRI_V, [[0, 2, 1], [1, 3, 2]], orient=True)
    assert (t.signed_measures() > 0).all()


def test_unused_vertices():
    v = TET_V + [[5.0, 5.0, 5.0], [6.0, 5.0, 5.0]]
    m = TetMesh(v, TET_E)
    assert m.unused_vertices().tolist() == [4, 5]
    assert m.unused_vertices().dtype == torch.int64
    assert TetMesh(TET_V, TET_E).unused_vertices().numel() == 0


def test_edges_unique_sorted():
    tri = TriMesh(TRI_V, TRI_E)
    assert tri.edges().tolist() == [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]]
    tet = TetMesh(TET_V, [[3, 1, 2, 0]], orient=True)
    assert tet.edges().tolist() == [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]
    assert tet.edges().dtype == torch.int64


# ---------------------------------------------------------------------------------------------
# Validation: each error names the problem (and ids); inputs stay unchanged
# ---------------------------------------------------------------------------------------------


def _bad_nan():
    v = torch.tensor(TET_V)
    v[2, 1] = float("nan")
    return TetMesh, v, torch.tensor(TET_E)


def _bad_inf():
    v = torch.tensor(TET_V)
    v[3, 0] = float("inf")
    return TetMesh, v, torch.tensor(TET_E)


def _tet(elements, v=TET_V, dtype=None):
    e = torch.as_tensor(elements) if dtype is None else torch.tensor(elements, dtype=dtype)
    return TetMesh, torch.tensor(v), e


def _tri(elements, v=TRI_V):
    return TriMesh, torch.tensor(v), torch.as_tensor(elements)


CASES = {
    # name: (builder -> (cls, vertices, elements), regex the message must match)
    "tet vertices 2-D": (lambda: (TetMesh, torch.tensor(TRI_V), torch.tensor(TET_E)), r"\[V, 3\]"),
    "vertices rank 1": (lambda: (TetMesh, torch.zeros(12), torch.tensor(TET_E)), r"shape"),
    "tri vertices width 4": (
        lambda: (TriMesh, torch.zeros(4, 4), torch.tensor(TRI_E)), r"\[V, 2\] or \[V, 3\]"),
    "complex vertices": (
        lambda: (TetMesh, torch.tensor(TET_V, dtype=torch.complex64), torch.tensor(TET_E)),
        r"floating"),
    "bool vertices": (
        lambda: (TetMesh, torch.ones(4, 3, dtype=torch.bool), torch.tensor(TET_E)), r"floating"),
    "string vertices": (
        lambda: (TetMesh, np.array([["a", "b", "c"]] * 4), torch.tensor(TET_E)), r"vertices"),
    "nan": (_bad_nan, r"NaN or inf.*: 2$"),
    "inf": (_bad_inf, r"NaN or inf.*: 3$"),
    "elements rank": (lambda: _tet([0, 1, 2, 3]), r"\[N, 4\]"),
    "elements width": (lambda: _tet([[0, 1, 2]]), r"\[N, 4\]"),
    "tri elements width": (lambda: _tri(TET_E), r"\[N, 3\]"),
    "float elements": (lambda: _tet(TET_E, dtype=torch.float32), r"elements must be integers"),
    "float list elements": (lambda: (TetMesh, torch.tensor(TET_V), [[0.0, 1.0, 2.0, 3.0]]),
                            r"elements must be integers"),
    "bool elements": (lambda: _tet(TET_E, dtype=torch.bool), r"elements must be integers"),
    "negative index": (lambda: _tet([[0, 1, 2, 3], [0, 1, 2, -1]]), r"outside \[0, 4\): 1 "),
    "index too large": (lambda: _tet([[0, 1, 2, 4]]), r"outside \[0, 4\): 0 "),
    "repeated node": (lambda: _tet([[0, 1, 2, 3], [0, 1, 1, 3]]), r"repeating a node: 1 "),
    "no vertices": (lambda: (TetMesh, torch.zeros(0, 3), torch.zeros(0, 4, dtype=torch.long)),
                    r"empty mesh"),
    "no elements": (lambda: _tet(torch.zeros(0, 4, dtype=torch.long)), r"empty mesh"),
    "empty lists": (lambda: (TriMesh, [], []), r"empty mesh"),
    "mixed devices": (lambda: (TetMesh, torch.zeros(4, 3, device="meta"), torch.tensor(TET_E)),
                      r"mixed devices"),
    "degenerate tet": (lambda: _tet(TET_E, v=TET_V[:3] + [[1.0, 1.0, 0.0]]),
                       r"degenerate \(zero-volume\) elements: 0 "),
    "degenerate tri": (lambda: _tri([[0, 1, 2]], v=[[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]),
                       r"degenerate \(zero-area\) elements: 0 "),
    "degenerate tri 3d": (lambda: _tri([[0, 1, 2]], v=[[0.0, 0, 0], [1.0, 1, 1], [2.0, 2, 2]]),
                          r"degenerate"),
    "inverted tet": (lambda: _tet([[0, 2, 1, 3]]),
                     r"inverted elements \(negative volume\): 0; pass orient=True.*reoriented\(\)"),
    "inverted tri 2d": (lambda: _tri([[0, 1, 2], [1, 2, 3]]),
                        r"inverted elements \(negative area\): 1;.*orient=True"),
}


@pytest.mark.parametrize("name", list(CASES))
def test_validation_errors(name):
    build, pattern = CASES[name]
    cls, v, e = build()
    v_before = v.clone() if isinstance(v, torch.Tensor) and v.device.type != "meta" else None
    e_before = e.clone() if isinstance(e, torch.Tensor) else None
    with pytest.raises(MeshError, match=pattern):
        cls(v, e)
    if v_before is not None:
        assert torch.equal(v, v_before) or (torch.isnan(v) == torch.isnan(v_before)).all()
    if e_before is not None:
        assert torch.equal(e, e_before)


def test_mesherror_is_valueerror():
    with pytest.raises(ValueError):
        TetMesh(TET_V, [[0, 1, 2, 7]])


def test_id_lists_are_truncated():
    # 15 tets, all inverted: the message lists 10 ids then "... (5 more)".
    m = beam_mesh(1, 1, 1)
    v = m.vertices
    e = m.elements[:, [0, 1, 3, 2]]
    e = torch.cat([e, e, e[:3]])
    with pytest.raises(MeshError, match=r"0, 1, 2, 3, 4, 5, 6, 7, 8, 9, \.\.\. \(5 more\)"):
        TetMesh(v, e)


def test_degenerate_is_relative_to_mesh_size():
    # A tiny but well-shaped tet is fine: the threshold scales with h^3.
    v = torch.tensor(TET_V, dtype=torch.float64) * 1e-5
    TetMesh(v, TET_E)
    # A sliver far below 1e-12 h^3 is refused.
    v = torch.tensor(TET_V, dtype=torch.float64)
    v[3, 2] = 1e-14
    with pytest.raises(MeshError, match="degenerate"):
        TetMesh(v, TET_E)


def test_check_false_skips_data_checks_but_not_shapes():
    m = TetMesh(TET_V, [[0, 2, 1, 3]], check=False)  # inverted, accepted
    assert m.signed_measures()[0] < 0
    with pytest.raises(MeshError, match="integers"):
        TetMesh(TET_V, [[0.0, 1.0, 2.0, 3.0]], check=False)


def test_inverted_tri_in_3d_is_not_an_error():
    v = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]
    TriMesh(v, [[0, 2, 1]])  # no sign in 3-D


# ---------------------------------------------------------------------------------------------
# Structured grids
# ---------------------------------------------------------------------------------------------


def _face_counts(elements: torch.Tensor, face_slots) -> tuple:
    """Unique sorted faces ``[F, k]`` and how many elements hold each ``[F]``."""
    faces = torch.cat([elements[:, list(s)] for s in face_slots]).sort(dim=1).values
    return torch.unique(faces, dim=0, return_counts=True)


TET_FACES = ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))
TRI_EDGES = ((0, 1), (0, 2), (1, 2))


def _on_box_boundary(points: torch.Tensor, lo, hi, atol=1e-9) -> torch.Tensor:
    """``[F, k, d]`` -> ``[F]``: all k points on one common face of the box."""
    lo = torch.tensor(lo, dtype=points.dtype)
    hi = torch.tensor(hi, dtype=points.dtype)
    on_lo = ((points - lo).abs() < atol).all(dim=1)  # [F, d]
    on_hi = ((points - hi).abs() < atol).all(dim=1)
    return (on_lo | on_hi).any(dim=1)


@pytest.mark.parametrize("cut", ["alternating", "uniform"])
@pytest.mark.parametrize("n", [(1, 1, 1), (2, 3, 4), (5, 2, 3)])
def test_beam_mesh_counts_volume_conformity(cut, n):
    nx, ny, nz = n
    size, origin = (2.0, 0.5, 0.75), (-1.0, 3.0, 0.5)
    m = beam_mesh(nx, ny, nz, size=size, origin=origin, cut=cut, dtype=torch.float64)
    assert isinstance(m, TetMesh)
    assert m.num_vertices == (nx + 1) * (ny + 1) * (nz + 1)
    assert m.num_elements == 6 * nx * ny * nz
    vol = m.signed_measures()
    assert (vol > 0).all()
    assert torch.allclose(vol.sum(), torch.tensor(size[0] * size[1] * size[2], dtype=torch.float64))
    # Every tet of a cell has volume cell / 6 (a Kuhn split).
    cell = size[0] * size[1] * size[2] / (nx * ny * nz)
    assert torch.allclose(vol, torch.full_like(vol, cell / 6))
    assert m.unused_vertices().numel() == 0
    TetMesh(m.vertices, m.elements)  # passes the full validation

    # Conformity: interior faces shared by exactly 2 tets, boundary faces by 1, and every
    # face held once lies on the box surface (a mismatched cut would leave them inside).
    faces, counts = _face_counts(m.elements, TET_FACES)
    assert counts.max() <= 2
    lo = origin
    hi = tuple(o + s for o, s in zip(origin, size))
    boundary = _on_box_boundary(m.vertices[faces], lo, hi)
    assert torch.equal(boundary, counts == 1)
    assert int((counts == 1).sum()) == 4 * (nx * ny + ny * nz + nx * nz)
    # Edges: grid lines + one diagonal per grid face + one per cell (a second diagonal on
    # some face would mean a non-conforming cut).
    axis_edges = nx * (ny + 1) * (nz + 1) + (nx + 1) * ny * (nz + 1) + (nx + 1) * (ny + 1) * nz
    grid_faces = nx * ny * (nz + 1) + nx * (ny + 1) * nz + (nx + 1) * ny * nz
    num_edges = m.edges().shape[0]
    assert num_edges == axis_edges + grid_faces + nx * ny * nz
    # Euler characteristic of a ball: V - E + F - T = 1.
    assert m.num_vertices - num_edges + faces.shape[0] - m.num_elements == 1


def test_beam_mesh_numbering_and_bounds():
    nx, ny, nz = 3, 2, 4
    m = beam_mesh(nx, ny, nz, size=(3.0, 2.0, 4.0), origin=(1.0, 2.0, 3.0), dtype=torch.float64)
    i, j, k = 2, 1, 3
    node = i + (nx + 1) * (j + (ny + 1) * k)
    assert m.vertices[node].tolist() == [1.0 + i, 2.0 + j, 3.0 + k]
    assert m.vertices.min(0).values.tolist() == [1.0, 2.0, 3.0]
    assert m.vertices.max(0).values.tolist() == [4.0, 4.0, 7.0]
    # The 6 tets of cell c use the 8 corners of that cell only.
    c = 1 + nx * (1 + ny * 2)
    corners = m.vertices[m.elements[6 * c: 6 * c + 6].reshape(-1)]
    assert corners.min(0).values.tolist() == [2.0, 3.0, 5.0]
    assert corners.max(0).values.tolist() == [3.0, 4.0, 6.0]


def test_beam_mesh_cuts_differ():
    a = beam_mesh(2, 2, 2, cut="alternating")
    u = beam_mesh(2, 2, 2, cut="uniform")
    assert torch.equal(a.elements[:6], u.elements[:6])  # cell (0, 0, 0) is not mirrored
    assert not torch.equal(a.elements, u.elements)
    # Every Kuhn tet holds its cell's long diagonal (its longest edge). Uniform: the same
    # diagonal direction (+,+,+) in every cell; alternating: mirrored directions as well.
    def diagonal_directions(m):
        x = m.vertices[m.elements]  # [N, 4, 3]
        d = x[:, :, None] - x[:, None, :]  # [N, 4, 4, 3]
        flat = d.reshape(len(x), 16, 3)
        longest = flat.norm(dim=-1).argmax(dim=1)
        v = flat[torch.arange(len(x)), longest]
        return torch.sign(v * torch.sign(v[:, :1]))  # normalised to point towards +x
    assert (diagonal_directions(u) == 1).all()
    dirs = {tuple(r) for r in diagonal_directions(a).tolist()}
    assert dirs == {(1.0, 1.0, 1.0), (1.0, -1.0, 1.0), (1.0, 1.0, -1.0), (1.0, -1.0, -1.0)}


def test_beam_mesh_dtype_device():
    m = beam_mesh(2, 1, 1, dtype=torch.float64, device="cpu")
    assert m.dtype == torch.float64 and m.device == torch.device("cpu")
    assert m.elements.dtype == torch.int64
    assert beam_mesh(1, 1, 1).dtype == torch.get_default_dtype()


@pytest.mark.parametrize("kwargs, pattern", [
    (dict(nx=0, ny=1, nz=1), "nx must be a positive int"),
    (dict(nx=1, ny=-2, nz=1), "ny must be a positive int"),
    (dict(nx=1, ny=1, nz=1.5), "nz must be a positive int"),
    (dict(nx=True, ny=1, nz=1), "nx must be a positive int"),
    (dict(nx=1, ny=1, nz=1, size=(1.0, 0.0, 1.0)), "size must be positive"),
    (dict(nx=1, ny=1, nz=1, size=(1.0, 1.0)), "size must be 3 numbers"),
    (dict(nx=1, ny=1, nz=1, origin=(0.0, float("nan"), 0.0)), "origin must be finite"),
    (dict(nx=1, ny=1, nz=1, cut="diagonal"), "cut must be one of"),
    (dict(nx=1, ny=1, nz=1, dtype=torch.int32), "dtype"),
])
def test_beam_mesh_bad_arguments(kwargs, pattern):
    with pytest.raises(MeshError, match=pattern):
        beam_mesh(**kwargs)


def test_beam_mesh_accepts_numpy_ints():
    assert beam_mesh(np.int64(2), np.int32(1), 1).num_elements == 12


def test_beam_mesh_paper_size_builds():
    t0 = time.perf_counter()
    m = beam_mesh(80, 32, 20, size=(4.0, 1.6, 1.0))
    elapsed = time.perf_counter() - t0
    print(f"beam_mesh(80, 32, 20): {m.num_elements} tets in {elapsed * 1e3:.1f} ms")
    assert m.num_elements == 307_200
    assert (m.signed_measures() > 0).all()


@pytest.mark.parametrize("cut", ["alternating", "uniform"])
@pytest.mark.parametrize("n", [(1, 1), (3, 2), (4, 5)])
def test_beam_tri_mesh(cut, n):
    nx, ny = n
    size, origin = (3.0, 0.5), (1.0, -2.0)
    m = beam_tri_mesh(nx, ny, size=size, origin=origin, cut=cut, dtype=torch.float64)
    assert isinstance(m, TriMesh) and m.dim == 2
    assert m.num_vertices == (nx + 1) * (ny + 1) and m.num_elements == 2 * nx * ny
    area = m.signed_measures()
    assert (area > 0).all()
    assert torch.allclose(area.sum(), torch.tensor(size[0] * size[1], dtype=torch.float64))
    TriMesh(m.vertices, m.elements)  # full validation passes
    # Edge sharing: interior edges held by 2 triangles, boundary edges by 1, on the boundary.
    edges, counts = _face_counts(m.elements, TRI_EDGES)
    assert counts.max() <= 2
    hi = (origin[0] + size[0], origin[1] + size[1])
    boundary = _on_box_boundary(m.vertices[edges], origin, hi)
    assert torch.equal(boundary, counts == 1)
    assert int((counts == 1).sum()) == 2 * (nx + ny)
    assert edges.shape[0] == m.edges().shape[0] == nx * (ny + 1) + (nx + 1) * ny + nx * ny


def test_beam_tri_mesh_alternates_diagonal():
    u = beam_tri_mesh(2, 1, cut="uniform")
    a = beam_tri_mesh(2, 1, cut="alternating")
    # Quad 1 (i = 1): the uniform cut uses diagonal (1, 5), the alternating one (2, 4).
    def diagonals(m):
        e = m.edges().tolist()
        return [d for d in ([1, 5], [2, 4]) if d in e]
    assert diagonals(u) == [[1, 5]]
    assert diagonals(a) == [[2, 4]]


def test_beam_tri_mesh_dim3():
    m2 = beam_tri_mesh(3, 2, size=(3.0, 2.0))
    m3 = beam_tri_mesh(3, 2, size=(3.0, 2.0), dim=3)
    assert m3.dim == 3 and m3.vertices.shape == (12, 3)
    assert torch.equal(m3.vertices[:, :2], m2.vertices)
    assert (m3.vertices[:, 2] == 0).all()
    assert torch.equal(m3.elements, m2.elements)
    assert torch.allclose(m3.signed_measures(), m2.signed_measures())


@pytest.mark.parametrize("kwargs, pattern", [
    (dict(nx=0, ny=1), "nx must be a positive int"),
    (dict(nx=1, ny=1, size=(1.0, -1.0)), "size must be positive"),
    (dict(nx=1, ny=1, dim=4), "dim must be 2 or 3"),
    (dict(nx=1, ny=1, cut="x"), "cut must be one of"),
])
def test_beam_tri_mesh_bad_arguments(kwargs, pattern):
    with pytest.raises(MeshError, match=pattern):
        beam_tri_mesh(**kwargs)
