"""The scalpel (``tm.Scalpel``, ``Simulator.add_scalpel``, scene files' ``[[cuts]]``): its path,
its bad input, the built-in ``cut`` scene (a slab cut through a strip per step: two pieces, the
far one on the floor), and what a run writes after topology changes (frames without the removed
elements, the split nodes apart)."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import element_pieces
from tensormass_torch.sim import builtin
from tensormass_torch.sim.output import FrameWriter
from tensormass_torch.sim.scene_file import load_scene

EDGES = [[[0.0, -1.0, 0.0], [0.0, -1.0, 1.0]], [[0.0, 1.0, 0.0], [0.0, 1.0, 1.0]]]


def pieces(elements: torch.Tensor, num_nodes: int) -> int:
    """Connected pieces of a mesh (elements joined through shared nodes)."""
    return int(element_pieces(elements, num_nodes).max()) + 1


def test_the_edge_moves_linearly_between_keyframes_and_sweeps_nothing_outside_them():
    scalpel = tm.Scalpel("b", times=[1.0, 2.0, 4.0], edges=[*EDGES, EDGES[0]])
    torch.testing.assert_close(scalpel.edge(1.5), torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
                                                               dtype=torch.float64))
    torch.testing.assert_close(scalpel.edge(3.0), torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
                                                               dtype=torch.float64))
    torch.testing.assert_close(scalpel.edge(0.0), torch.tensor(EDGES[0], dtype=torch.float64))  # clamped
    assert scalpel.blade(0.0, 0.9) is None and scalpel.blade(4.0, 5.0) is None
    blade = scalpel.blade(0.5, 1.5)  # from the first keyframe on
    torch.testing.assert_close(blade.vertices[[0, 1]], torch.tensor(EDGES[0], dtype=torch.float64))
    still = tm.Scalpel("b", times=[0.0, 1.0], edges=[EDGES[0], EDGES[0]])
    assert still.blade(0.2, 0.4) is None


@pytest.mark.parametrize("kwargs,message", [
    (dict(times=[0.0], edges=EDGES[:1]), "at least 2"),
    (dict(times=[1.0, 0.0], edges=EDGES), "increase strictly"),
    (dict(times=[0.0, 1.0], edges=EDGES[:1]), r"\[K, 2, 3\]"),
    (dict(times=[0.0, float("nan")], edges=EDGES), "finite")])
def test_bad_scalpels_are_one_error(kwargs, message):
    with pytest.raises(tm.SceneError, match=message):
        tm.Scalpel(0, **kwargs)


def test_a_simulator_refuses_a_scalpel_on_no_body_or_a_flat_one():
    flat = tm.beam_tri_mesh(3, 2)  # 2-D
    sim = tm.Simulator([tm.Body(flat, tm.Material(young=1e4, poisson=0.3, density=1.0), fixed=[0], name="f")])
    for scalpel, message in [(tm.Scalpel("g", [0, 1], EDGES), "no body named"),
                             (tm.Scalpel(0, [0, 1], EDGES), "2-D"), ("scalpel", "tm.Scalpel")]:
        with pytest.raises(tm.SceneError, match=message):
            sim.add_scalpel(scalpel)
    assert sim.scalpels == []


def test_the_built_in_cut_scene_parts_the_slab_and_the_far_piece_lands_on_the_floor():
    scene = builtin.cut(resolution=1, dtype=torch.float64)
    sim = scene.simulator
    nodes = sim.bodies[0].mesh.num_vertices
    sim.step(scene.steps)
    mesh = sim.mesh(0)
    assert mesh.num_vertices > nodes and pieces(mesh.elements, mesh.num_vertices) == 2
    far = sim.positions(0)[mesh.vertices[:, 0] > 0.5]
    assert float(far[:, 2].min()) < -0.45  # on the floor (z = -0.5), not through it
    assert float(far[:, 2].min()) > -0.52
    assert len(sim.scalpels) == 1  # the cuts rebuilt the simulator around the body: the scalpel stays


def test_a_scene_file_scalpel_cuts_its_body():
    scene = load_scene("scenes/cut.toml", dtype="float64")
    sim = scene.simulator
    assert len(sim.scalpels) == 1 and sim.scalpels[0].body == "ball"
    assert sim.ptr[1] - sim.used_nodes[0] == tm.sim.simulator.MIN_SPARE_NODES  # room for cuts from the start
    model = sim.model
    sim.step(scene.steps)
    mesh = sim.mesh("ball")
    assert pieces(mesh.elements, mesh.num_vertices) == 2
    assert sim.model is model  # every cut in place


def test_a_scene_file_sets_a_body_s_spare_rows_and_refuses_bad_ones(tmp_path):
    body = ('[[bodies]]\nname = "b"\nmesh = { generator = "beam", cells = [4, 1, 1] }\n'
            'material = { model = "hooke", young = 1e4, poisson = 0.3, density = 1.0 }\nfixed = { nodes = [0] }\n')
    path = tmp_path / "room.toml"
    path.write_text(body + "spare_nodes = 7\n")
    sim = load_scene(path).simulator
    assert sim.ptr[1] - sim.used_nodes[0] == 7
    for value, message in (("-1", "must be >= 0"), ("2.5", "must be an integer"), ('"x"', "must be an integer")):
        path.write_text(body + f"spare_nodes = {value}\n")
        with pytest.raises(tm.SceneError, match=r"bodies\[0\]\.spare_nodes: " + message):
            load_scene(path)


@pytest.mark.parametrize("cut,message", [
    ('body = "nobody"\ntimes = [0, 1]\nedges = [[[0,0,0],[0,0,1]], [[0,1,0],[0,1,1]]]', r"cuts\[0\]\.body: .*no body"),
    ('times = [1, 0]\nedges = [[[0,0,0],[0,0,1]], [[0,1,0],[0,1,1]]]', r"cuts\[0\]\.times: .*increase"),
    ('times = [0, 1]\nedges = [[[0,0,0],[0,0,1]]]', r"cuts\[0\]\.edges: must be a list of 2 edges"),
    ('times = [0, 1]\nedges = [[[0,0,0],[0,0]], [[0,1,0],[0,1,1]]]', r"cuts\[0\]\.edges: entry 0 point 1"),
    ('times = [0, 1]\nedges = [[[0,0,0],[0,0,1]], [[0,1,0],[0,1,1]]]\nspeed = 2', r"cuts\[0\]\.speed: unknown key")])
def test_bad_cuts_in_a_scene_file_name_the_key(tmp_path, cut, message):
    path = tmp_path / "bad.toml"
    path.write_text('[[bodies]]\nname = "b"\nmesh = { generator = "beam", cells = [4, 1, 1] }\n'
                    'material = { model = "hooke", young = 1e4, poisson = 0.3, density = 1.0 }\n'
                    'fixed = { nodes = [0] }\n\n[[cuts]]\n' + cut + "\n")
    with pytest.raises(tm.SceneError, match=message):
        load_scene(path)


def test_frames_show_the_changed_topology(tmp_path):
    meshio = pytest.importorskip("meshio")
    mesh = tm.beam_mesh(4, 1, 1, dtype=torch.float64)
    sim = tm.Simulator([tm.Body(mesh, tm.Material(young=1e4, poisson=0.3, density=1.0),
                                fixed=mesh.vertices[:, 0] == 0)])
    sim.remove_elements(0, [0, 1])
    before = pieces(sim.mesh(0).elements, mesh.num_vertices)
    sim.cut(0, tm.Blade.swept((0.51, -1, -1), (0.51, 2, -1), (0.51, -1, 2), (0.51, 2, 2)))
    FrameWriter(tmp_path, "f").write(sim)
    frame = meshio.read(tmp_path / "f_0_00000.vtu")
    cells = frame.cells_dict["tetra"]
    assert len(cells) == mesh.num_elements - 2 and len(frame.points) == sim.bodies[0].mesh.num_vertices
    assert pieces(torch.as_tensor(cells), len(frame.points)) == before + 1  # the cut parted the beam
