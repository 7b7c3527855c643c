"""The contact op family (``ops.contact``: ``contact_count_candidates``, ``contact_fill_candidates``,
the broad phase of the contact between bodies): the ops' candidates equal their pure-torch
reference, in its order (the narrow phase then sees the same pairs), on the hash of a real pile
of bodies, with points and with swept boxes, float32 and float64, with and without same-body
pairs; the candidate set equals a brute-force oracle (every pair of boxes that meet, once);
CUDA equals the CPU; bad arguments raise naming them and write nothing."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces
from tensormass_torch.ops import contact, library

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def pile_boxes(dtype, device, swept: bool, seed: int = 0):
    """The broad phase's inputs for 8 blocks in two offset columns, shaken: (cell, triangle boxes
    grown by the reach, triangle bodies, vertex boxes (the same tensor twice for points), vertex
    bodies)."""
    gen = torch.Generator().manual_seed(seed)
    block = tm.beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=torch.float64)
    faces = boundary_faces(block.elements)
    positions, triangles, vertex_object, triangle_object = [], [], [], []
    nodes = block.vertices.shape[0]
    for body in range(8):
        offset = torch.tensor([0.21 * (body % 2) + 0.03 * (body // 2), 0.0, 0.09 * (body // 2)], dtype=torch.float64)
        positions.append(block.vertices + offset + 0.01 * torch.randn(nodes, 3, generator=gen, dtype=torch.float64))
        triangles.append(faces + body * nodes)
        triangle_object.append(torch.full((faces.shape[0],), body))
    x = torch.cat(positions).to(dtype)
    triangles = torch.cat(triangles)
    vertices = torch.unique(triangles)
    node_object = torch.arange(8).repeat_interleave(nodes)
    vertex_object = node_object[vertices]
    triangle_object = torch.cat(triangle_object)
    reach = 0.02
    corners = x[triangles]
    low, high = corners.amin(1), corners.amax(1)
    cell = (high - low).amax() + 2 * reach
    points = x[vertices]
    if swept:
        motion = 0.04 * torch.rand(points.shape, generator=gen, dtype=torch.float64).to(dtype) - 0.02
        point_low, point_high = torch.minimum(points, points + motion), torch.maximum(points, points + motion)
    else:
        point_low = point_high = points
    point_low, point_high = (point_low.to(device), point_high.to(device)) if swept else (point_low.to(device),) * 2
    return (cell.to(device), (low - reach).to(device), (high + reach).to(device), triangle_object.to(device),
            point_low, point_high, vertex_object.to(device))


def brute_force(low, high, triangle_object, point_low, point_high, vertex_object, same_body):
    """Every (vertex, triangle) whose boxes meet, bodies differing unless same_body: a sorted set."""
    meet = ((point_low[:, None] <= high[None]) & (point_high[:, None] >= low[None])).all(-1)
    if not same_body:
        meet &= vertex_object[:, None] != triangle_object[None]
    vertex, triangle = meet.nonzero(as_tuple=True)
    return sorted(zip(vertex.tolist(), triangle.tolist()))


@pytest.mark.parametrize("swept", [False, True])
@pytest.mark.parametrize("same_body", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("device", DEVICES)
def test_candidates_equal_the_reference_in_order_and_a_brute_force_search(swept, same_body, dtype, device):
    cell, low, high, triangle_object, point_low, point_high, vertex_object = pile_boxes(dtype, device, swept)
    if not swept:
        assert point_low is point_high
    native = contact.candidate_pairs(cell, low, high, triangle_object, point_low, point_high, vertex_object,
                                     same_body)
    reference = contact.candidate_pairs(cell, low, high, triangle_object, point_low, point_high, vertex_object,
                                        same_body, native=False)
    assert len(native[0]) > 100  # the pile's columns touch: a test with candidates
    for ours, theirs in zip(native, reference):
        assert torch.equal(ours, theirs)
    found = sorted(zip(native[0].tolist(), native[1].tolist()))
    assert len(set(found)) == len(found)  # each pair once
    assert found == brute_force(low.cpu(), high.cpu(), triangle_object.cpu(), point_low.cpu(), point_high.cpu(),
                                vertex_object.cpu(), same_body)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("swept", [False, True])
def test_cuda_candidates_equal_the_cpu(swept):
    on_cpu = pile_boxes(torch.float32, "cpu", swept, seed=4)
    on_cuda = pile_boxes(torch.float32, "cuda", swept, seed=4)
    for ours, theirs in zip(contact.candidate_pairs(*on_cuda, False), contact.candidate_pairs(*on_cpu, False)):
        assert torch.equal(ours.cpu(), theirs)


def test_bad_arguments_raise_naming_them_and_write_nothing():
    args, _ = contact._example_fill("cpu", torch.float64)
    args = list(args)
    vertex, triangle = args[-2], args[-1]
    vertex.fill_(-7)
    triangle.fill_(-7)
    fill = library.op("contact_fill_candidates")
    count = library.op("contact_count_candidates")
    for position, wrong, name in [
        (4, args[4].int(), "query_vertex"),
        (5, args[5][:, :2].contiguous(), "query_cells"),
        (10, args[10].float(), "low"),
        (1, args[1].t(), "point_low"),
        (12, args[12][:-1], "triangle_object"),
    ]:
        bad = list(args)
        bad[position] = wrong
        with pytest.raises(RuntimeError, match=name):
            fill(*bad)
        with pytest.raises(RuntimeError, match=name):
            count(*bad[:14])
    short = list(args)
    short[-1] = triangle[:-1].clone() if len(triangle) else torch.zeros(1, dtype=torch.int64)
    with pytest.raises(RuntimeError, match="triangle"):
        fill(*short)
    assert bool((vertex == -7).all()) and bool((triangle == -7).all())
