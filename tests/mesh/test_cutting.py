"""Cutting a mesh along a blade (``mesh.cutting``): the faces the blade crosses part, the nodes on
them split so that each element keeps n distinct nodes; a blade through the whole section leaves
two pieces, a partial one a crack whose front stays joined; a blade that crosses nothing raises."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.errors import MeshError
from tensormass_torch.mesh import cutting
from tensormass_torch.mesh.topology import element_pieces


def pieces(elements: torch.Tensor, num_nodes: int) -> int:
    """How many pieces (sets of elements joined through shared nodes) a mesh has."""
    labels = torch.arange(num_nodes)
    n = elements.shape[1]
    while True:
        low = labels[elements].min(1).values.repeat_interleave(n)
        updated = labels.clone().scatter_reduce_(0, elements.reshape(-1), low, reduce="amin")
        updated = updated[updated]
        if torch.equal(updated, labels):
            return int(torch.unique(labels[elements.reshape(-1)]).numel())
        labels = updated


def plane_blade(x, y_high=2.0):
    return cutting.Blade.swept((x, -1, -1), (x, y_high, -1), (x, -1, 2), (x, y_high, 2))


def check_valid(result, mesh):
    e = result.elements
    ordered = torch.sort(e, 1).values
    assert bool((ordered[:, 1:] != ordered[:, :-1]).all()), "an element with a repeated node"
    assert torch.equal(result.parents[e], mesh.elements), "an element re-pointed to another node's copy"
    vertices = mesh.vertices[result.parents]
    tm.TetMesh(vertices, e) if e.shape[1] == 4 else tm.TriMesh(vertices, e)  # checked: no inverted element


def test_a_blade_through_the_whole_section_leaves_two_pieces():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, plane_blade(0.51))
    assert result.cut_first.numel() == 8  # 2 x 2 hex faces at x = 0.5, two triangles each
    assert result.new_nodes == 9  # the 3 x 3 nodes of the plane x = 0.5, each copied once
    check_valid(result, mesh)
    assert pieces(mesh.elements, mesh.num_vertices) == 1 and pieces(result.elements, result.parents.numel()) == 2


def test_a_partial_blade_leaves_a_crack_whose_front_stays_joined():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, plane_blade(0.51, y_high=0.2))
    assert result.cut_first.numel() == 4
    assert result.new_nodes == 3  # the row y = 0 of the plane; the front y = 0.25 is not split
    check_valid(result, mesh)
    assert pieces(result.elements, result.parents.numel()) == 1


def test_membranes_tear_along_edges():
    mesh = tm.beam_tri_mesh(6, 3, size=(1.2, 0.6), dim=3, dtype=torch.float64)
    blade = cutting.Blade.swept((0.61, -1, -1), (0.61, 2, -1), (0.61, -1, 1), (0.61, 2, 1))
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blade)
    assert result.new_nodes == 4  # the column x = 0.6 of 4 nodes
    check_valid(result, mesh)
    assert pieces(result.elements, result.parents.numel()) == 2


def test_the_blade_cuts_the_deformed_shape():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    moved = mesh.vertices + torch.tensor([0.25, 0.0, 0.0], dtype=torch.float64)  # the body slid by 0.25
    at_rest = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, plane_blade(0.76))
    slid = cutting.cut(mesh.elements, mesh.num_vertices, moved, plane_blade(0.76))
    assert not torch.equal(at_rest.cut_first, slid.cut_first)  # other faces: those now under the blade


def test_removed_elements_join_nothing():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    removed = torch.zeros(mesh.elements.shape[0], dtype=torch.bool)
    removed[:5] = True
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, plane_blade(0.51), removed)
    assert torch.equal(result.elements[:5], mesh.elements[:5])  # left as they were
    assert not bool(torch.isin(result.cut_first, torch.arange(5)).any())


@pytest.mark.parametrize("blade,message", [
    (cutting.Blade.swept((5, -1, -1), (5, 2, -1), (5, -1, 2), (5, 2, 2)), "crosses no interior face"),
])
def test_a_blade_that_crosses_nothing_raises(blade, message):
    mesh = tm.beam_mesh(2, 1, 1, dtype=torch.float64)
    with pytest.raises(MeshError, match=message):
        cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blade)


def test_bad_blades_raise():
    with pytest.raises(MeshError, match=r"blade vertices must be a float tensor \[B, 3\]"):
        cutting.Blade(torch.zeros(3, 2), torch.tensor([[0, 1, 2]]))
    with pytest.raises(MeshError, match="must index the 3 blade vertices"):
        cutting.Blade(torch.zeros(3, 3), torch.tensor([[0, 1, 3]]))
    with pytest.raises(MeshError, match="must be finite"):
        cutting.Blade(torch.full((3, 3), float("nan")), torch.tensor([[0, 1, 2]]))


def test_element_pieces_counts_what_a_cut_parts():
    mesh = tm.beam_mesh(4, 1, 1, dtype=torch.float64)
    pieces = element_pieces(mesh.elements, mesh.num_vertices)
    assert torch.equal(pieces, torch.zeros_like(pieces))
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices,
                         tm.Blade.swept((0.51, -1, -1), (0.51, 2, -1), (0.51, -1, 2), (0.51, 2, 2)))
    pieces = element_pieces(result.elements, result.parents.shape[0])
    left = mesh.vertices[mesh.elements].mean(1)[:, 0] < 0.5
    assert torch.equal(pieces, (~left).long())  # numbered in the order of their first elements
