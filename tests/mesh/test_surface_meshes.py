"""tm.tetrahedralize: volume meshes from closed triangle surfaces (TetGen; fTetWild where
installed), from every input it takes, and its errors."""
import sys
from pathlib import Path

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.errors import MeshError
from tensormass_torch.sim.scene_file import load_scene

pytest.importorskip("tetgen")


def box_surface(size=(0.4, 0.2, 0.1)):
    """The boundary triangles of a beam mesh: a closed surface ``(vertices [V, 3], triangles [F, 3])``."""
    mesh = tm.beam_mesh(4, 2, 1, size=size, dtype=torch.float64)
    faces = mesh.elements[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3)
    key, inverse, counts = torch.unique(torch.sort(faces, dim=1).values, dim=0, return_inverse=True,
                                        return_counts=True)
    boundary = faces[counts[inverse] == 1]
    return mesh.vertices, boundary


def volume(mesh) -> float:
    return float(mesh.to(dtype=torch.float64).signed_measures().sum())


def test_a_closed_surface_becomes_a_positive_volume_mesh():
    vertices, triangles = box_surface()
    mesh = tm.tetrahedralize((vertices, triangles))
    assert isinstance(mesh, tm.TetMesh) and mesh.dtype == torch.float32
    assert float(mesh.signed_measures().min()) > 0
    assert mesh.unused_vertices().numel() == 0
    assert volume(mesh) == pytest.approx(0.4 * 0.2 * 0.1, rel=1e-5)


def test_max_volume_refines():
    surface = box_surface()
    coarse = tm.tetrahedralize(surface, dtype=torch.float64)
    fine = tm.tetrahedralize(surface, max_volume=1e-5, dtype=torch.float64)
    assert fine.num_elements > 4 * coarse.num_elements
    assert volume(fine) == pytest.approx(volume(coarse), rel=1e-9)


def test_a_trimesh_a_file_and_a_pair_give_the_same_solid(tmp_path):
    vertices, triangles = box_surface()
    path = tmp_path / "box.stl"
    tm.save_mesh(path, tm.TriMesh(vertices, triangles, check=False))
    for surface in ((vertices, triangles), tm.TriMesh(vertices, triangles, check=False), path, str(path)):
        assert volume(tm.tetrahedralize(surface)) == pytest.approx(0.008, rel=1e-5)


def test_an_open_surface_is_refused_with_the_way_out():
    vertices, triangles = box_surface()
    with pytest.raises(MeshError, match=r"not closed \(\d+ edges.*method='ftetwild'"):
        tm.tetrahedralize((vertices, triangles[1:]))


@pytest.mark.parametrize("kwargs,message", [
    ({"method": "gmsh"}, "unknown tetrahedralize method 'gmsh'"),
    ({"max_volum": 1.0}, "no option 'max_volum'"),
    ({"max_volume": -1.0}, "max_volume must be a positive number"),
    ({"min_dihedral": 80}, "min_dihedral must be in"),
    ({"method": "ftetwild", "max_volume": 1.0}, "method 'ftetwild' takes no option 'max_volume'"),
])
def test_bad_options_are_named(kwargs, message):
    with pytest.raises(MeshError, match=message):
        tm.tetrahedralize(box_surface(), **kwargs)


@pytest.mark.parametrize("surface,message", [
    ("missing.stl", "surface file not found"),
    ((torch.zeros(3, 3), torch.zeros(4, 3, dtype=torch.long)), r"V >= 4"),
    ((torch.rand(5, 3), torch.tensor([[0, 1, 2], [0, 1, 9], [1, 2, 3], [0, 2, 3]])), "outside"),
    ((torch.full((5, 3), float("nan")), torch.zeros(4, 3, dtype=torch.long)), "finite"),
    (42, "surface must be"),
])
def test_malformed_surfaces_are_named(surface, message):
    with pytest.raises(MeshError, match=message):
        tm.tetrahedralize(surface)


def test_a_missing_package_says_how_to_install_it(monkeypatch):
    monkeypatch.setitem(sys.modules, "tetgen", None)  # what an absent package looks like to import
    with pytest.raises(MeshError, match=r"needs the tetgen package: pip install tetgen"):
        tm.tetrahedralize(box_surface())


def test_ftetwild_meshes_an_open_surface():
    pytest.importorskip("pytetwild")
    vertices, triangles = box_surface()
    mesh = tm.tetrahedralize((vertices, triangles[1:]), method="ftetwild", edge_length=0.1)
    assert float(mesh.signed_measures().min()) > 0


def write_scene(folder: Path, mesh_table: str) -> Path:
    path = folder / "s.toml"
    path.write_text(f"steps = 2\n[[bodies]]\nmesh = {mesh_table}\n"
                    "material = { model = \"corotational\", young = 1e5, poisson = 0.3 }\n")
    return path


def test_the_scene_file_key(tmp_path):
    vertices, triangles = box_surface()
    tm.save_mesh(tmp_path / "box.stl", tm.TriMesh(vertices, triangles, check=False))
    scene = load_scene(write_scene(tmp_path, '{ surface = "box.stl", max_volume = 1e-5, scale = 2.0 }'))
    mesh = scene.simulator.bodies[0].mesh
    assert volume(mesh) == pytest.approx(8 * 0.008, rel=1e-5)
    scene.simulator.step(2)
    with pytest.raises(tm.SceneError, match=r"bodies\[0\]\.mesh\.edge_length: is an option of method 'ftetwild'"):
        load_scene(write_scene(tmp_path, '{ surface = "box.stl", edge_length = 0.1 }'))
    with pytest.raises(tm.SceneError, match=r"bodies\[0\]\.mesh\.surface: surface file not found"):
        load_scene(write_scene(tmp_path, '{ surface = "nope.stl" }'))
    with pytest.raises(tm.SceneError, match=r"give exactly one of 'file'.*'surface'.*got file, surface"):
        load_scene(write_scene(tmp_path, '{ surface = "box.stl", file = "box.stl" }'))
