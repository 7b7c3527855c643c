"""Tests of tensormass_torch.mesh.io: meshio round trips and errors."""
import numpy as np
import pytest
import torch

meshio = pytest.importorskip("meshio")

from tensormass_torch.errors import MeshError  # noqa: E402
from tensormass_torch.mesh.beams import beam_mesh, beam_tri_mesh  # noqa: E402
from tensormass_torch.mesh.io import load_mesh, save_mesh  # noqa: E402
from tensormass_torch.mesh.meshes import TetMesh, TriMesh  # noqa: E402

FORMATS = ["vtu", "vtk", "msh", "mesh"]
POINT_DATA_FORMATS = ["vtu", "vtk", "msh"]  # medit stores no point data


def _jittered(mesh, seed=0):
    """The mesh with irrational-looking float64 coordinates (to catch lost digits)."""
    g = torch.Generator().manual_seed(seed)
    v = mesh.vertices + 0.01 * torch.rand(mesh.vertices.shape, generator=g, dtype=mesh.dtype)
    return type(mesh)(v, mesh.elements)


MESHES = {
    "tet": lambda: _jittered(beam_mesh(3, 2, 2, size=(1.5, 1.0, 1.0), dtype=torch.float64)),
    "tri2d": lambda: _jittered(beam_tri_mesh(3, 2, dtype=torch.float64)),
    "tri3d": lambda: _jittered(beam_tri_mesh(3, 2, dtype=torch.float64, dim=3)),
}


def _point_data(mesh):
    v = mesh.num_vertices
    g = torch.Generator().manual_seed(1)
    return {
        "scalar": torch.rand(v, generator=g, dtype=torch.float64),
        "vec3": torch.rand(v, 3, generator=g, dtype=torch.float64),
        "vec2": np.random.default_rng(2).random((v, 2)),
    }


@pytest.mark.parametrize("ext", FORMATS)
@pytest.mark.parametrize("kind", list(MESHES))
def test_round_trip(tmp_path, ext, kind):
    mesh = MESHES[kind]()
    data = _point_data(mesh) if ext in POINT_DATA_FORMATS else {}
    path = tmp_path / f"{kind}.{ext}"
    save_mesh(path, mesh, **data)
    back, point_data = load_mesh(path, with_point_data=True)

    assert type(back) is type(mesh)
    assert back.dtype == torch.float64  # every one of these formats keeps float64
    assert torch.equal(back.elements, mesh.elements)
    if kind == "tri2d":
        # Files store 3-D points: a planar mesh comes back lifted to z = 0.
        assert back.dim == 3 and (back.vertices[:, 2] == 0).all()
        assert torch.equal(back.vertices[:, :2], mesh.vertices)
    else:
        assert torch.equal(back.vertices, mesh.vertices)

    assert set(point_data) == set(data)
    for key, value in data.items():
        expected = torch.as_tensor(value)
        got = point_data[key]
        if key == "vec2":  # padded with a zero third component
            assert got.shape == (mesh.num_vertices, 3) and (got[:, 2] == 0).all()
            got = got[:, :2]
        assert torch.equal(got.reshape(expected.shape), expected), key


@pytest.mark.parametrize("ext", FORMATS)
def test_float32_round_trip(tmp_path, ext):
    mesh = beam_mesh(2, 1, 1, size=(1.0, 0.3, 0.7), dtype=torch.float32)
    path = tmp_path / f"f32.{ext}"
    save_mesh(path, mesh)
    back = load_mesh(path)
    # vtu/vtk/medit keep float32; binary gmsh stores doubles (the values are the same).
    assert back.dtype in (torch.float32, torch.float64)
    if ext != "msh":
        assert back.dtype == torch.float32
    assert torch.allclose(back.vertices.float(), mesh.vertices, rtol=0, atol=1e-7)
    assert torch.equal(back.elements, mesh.elements)


def test_float32_point_data(tmp_path):
    mesh = beam_mesh(1, 1, 1)
    u = torch.rand(mesh.num_vertices, 3)
    save_mesh(tmp_path / "p.vtu", mesh, u=u)
    _, data = load_mesh(tmp_path / "p.vtu", with_point_data=True)
    assert data["u"].dtype == torch.float32 and torch.equal(data["u"], u)


def test_msh_is_gmsh(tmp_path):
    # meshio lists ANSYS first for .msh; the file must be gmsh (keeps point data).
    path = tmp_path / "b.msh"
    save_mesh(path, beam_mesh(1, 1, 1), s=torch.zeros(8))
    assert path.read_bytes().startswith(b"$MeshFormat")


def test_creates_parent_directories(tmp_path):
    path = tmp_path / "a" / "b" / "c.vtu"
    save_mesh(path, beam_mesh(1, 1, 1))
    assert path.exists()
    assert list(path.parent.iterdir()) == [path]  # no temporary file left behind


def test_load_missing_file(tmp_path):
    path = tmp_path / "nope.vtu"
    with pytest.raises(FileNotFoundError, match="nope.vtu"):
        load_mesh(path)


def test_load_only_line_cells(tmp_path):
    path = tmp_path / "lines.vtu"
    points = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])
    meshio.write(str(path), meshio.Mesh(points, [("line", np.array([[0, 1], [1, 2]]))]))
    with pytest.raises(MeshError, match=r"no tetra or triangle cells.*line"):
        load_mesh(path)


def test_load_unreadable_file(tmp_path):
    path = tmp_path / "garbage.vtu"
    path.write_text("this is not a mesh")
    with pytest.raises(MeshError, match="garbage.vtu"):
        load_mesh(path)
    unknown = tmp_path / "x.unknownext"
    unknown.write_text("1 2 3")
    with pytest.raises(MeshError, match="x.unknownext"):
        load_mesh(unknown)


def test_load_prefers_tetra_and_ignores_other_cells(tmp_path):
    path = tmp_path / "mixed.vtu"
    tet = beam_mesh(1, 1, 1, dtype=torch.float64)
    cells = [
        ("triangle", np.array([[0, 1, 2]])),
        ("tetra", tet.elements[:3].numpy()),
        ("line", np.array([[0, 1]])),
        ("tetra", tet.elements[3:].numpy()),
    ]
    meshio.write(str(path), meshio.Mesh(tet.vertices.numpy(), cells))
    back = load_mesh(path)
    assert isinstance(back, TetMesh)
    assert torch.equal(back.elements, tet.elements)


def test_load_triangles_keep_file_dimension(tmp_path):
    tri = beam_tri_mesh(2, 2, dtype=torch.float64)
    # medit stores 2-D points as 2-D: the mesh comes back 2-D.
    path2 = tmp_path / "planar.mesh"
    cells = [("triangle", tri.elements.numpy())]
    meshio.write(str(path2), meshio.Mesh(tri.vertices.numpy(), cells))
    back2 = load_mesh(path2)
    assert isinstance(back2, TriMesh) and back2.dim == 2
    assert torch.equal(back2.vertices, tri.vertices)
    # 3-D points with z == 0 stay 3-D.
    path3 = tmp_path / "flat.vtu"
    pts = np.concatenate([tri.vertices.numpy(), np.zeros((tri.num_vertices, 1))], axis=1)
    meshio.write(str(path3), meshio.Mesh(pts, cells))
    assert load_mesh(path3).dim == 3


def test_load_inverted_needs_orient(tmp_path):
    path = tmp_path / "inv.vtu"
    points = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    meshio.write(str(path), meshio.Mesh(points, [("tetra", np.array([[0, 2, 1, 3]]))]))
    with pytest.raises(MeshError, match=r"inv\.vtu.*inverted.*orient=True"):
        load_mesh(path)
    m = load_mesh(path, orient=True)
    assert (m.signed_measures() > 0).all()


def test_save_bad_point_data_writes_nothing(tmp_path):
    mesh = beam_mesh(1, 1, 1)
    path = tmp_path / "sub" / "bad.vtu"
    with pytest.raises(MeshError, match="'u'"):
        save_mesh(path, mesh, ok=torch.zeros(8), u=torch.zeros(7, 3))
    with pytest.raises(MeshError, match="'w'"):
        save_mesh(path, mesh, w=torch.zeros(8, 4))
    with pytest.raises(MeshError, match="'t'"):
        save_mesh(path, mesh, t=torch.zeros(8, 3, 3))
    with pytest.raises(MeshError, match="'s'.*numeric"):
        save_mesh(path, mesh, s=np.array(["a"] * 8))
    assert not path.exists()


def test_save_point_data_to_medit_is_refused(tmp_path):
    path = tmp_path / "m.mesh"
    with pytest.raises(MeshError, match="point data"):
        save_mesh(path, beam_mesh(1, 1, 1), u=torch.zeros(8, 3))
    assert not path.exists()


def test_save_unknown_extension_and_non_mesh(tmp_path):
    with pytest.raises(MeshError, match="extension"):
        save_mesh(tmp_path / "x.notaformat", beam_mesh(1, 1, 1))
    with pytest.raises(MeshError, match="TetMesh or TriMesh"):
        save_mesh(tmp_path / "x.vtu", torch.zeros(3, 3))
    assert list(tmp_path.iterdir()) == []


def test_save_does_not_modify_the_mesh(tmp_path):
    mesh = beam_tri_mesh(2, 2)
    v, e = mesh.vertices.clone(), mesh.elements.clone()
    data = torch.rand(mesh.num_vertices, 2)
    d = data.clone()
    save_mesh(tmp_path / "t.vtk", mesh, v=data)
    assert torch.equal(mesh.vertices, v) and torch.equal(mesh.elements, e)
    assert torch.equal(data, d)
