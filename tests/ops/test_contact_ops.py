"""The contact op family (``ops.contact``: ``contact_count_candidates``, ``contact_fill_candidates``,
the broad phase of the contact between bodies): the ops' candidates equal their pure-torch
reference, in its order (the narrow phase then sees the same pairs), on the hash of a real pile
of bodies, with points and with swept boxes, float32 and float64, with and without same-body
pairs, with and without the own body's entries skipped (``triangle_first``); the candidate set
equals a brute-force oracle (every pair of boxes that meet, once); CUDA equals the CPU; bad
arguments raise naming them and write nothing."""
from __future__ import annotations

import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces
from tensormass_torch.ops import contact, library
from tests.conftest import shaken_pile_contact

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


def first_triangles(triangle_object):
    """Where each body's triangles start ``[B + 1]`` (triangles in body order)."""
    return torch.searchsorted(triangle_object, torch.arange(int(triangle_object.max()) + 2,
                                                            device=triangle_object.device))


@pytest.mark.parametrize("skip_own", [False, True])
@pytest.mark.parametrize("swept", [False, True])
@pytest.mark.parametrize("same_body", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("device", DEVICES)
def test_candidates_equal_the_reference_in_order_and_a_brute_force_search(skip_own, swept, same_body, dtype,
                                                                           device):
    cell, low, high, triangle_object, point_low, point_high, vertex_object = pile_boxes(dtype, device, swept)
    if not swept:
        assert point_low is point_high
    native = contact.candidate_pairs(cell, low, high, triangle_object, point_low, point_high, vertex_object,
                                     same_body, triangle_first=first_triangles(triangle_object) if skip_own else None)
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
@pytest.mark.parametrize("skip_own", [False, True])
@pytest.mark.parametrize("swept", [False, True])
def test_cuda_candidates_equal_the_cpu(swept, skip_own):
    on_cpu = pile_boxes(torch.float32, "cpu", swept, seed=4)
    on_cuda = pile_boxes(torch.float32, "cuda", swept, seed=4)
    first = first_triangles(on_cpu[3]) if skip_own else None
    ours = contact.candidate_pairs(*on_cuda, False, triangle_first=None if first is None else first.cuda())
    for mine, theirs in zip(ours, contact.candidate_pairs(*on_cpu, False, triangle_first=first)):
        assert torch.equal(mine.cpu(), theirs)


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
        (8, args[8][:-1], "query_order"),
        (11, args[11].float(), "low"),
        (1, args[1].t(), "point_low"),
        (13, args[13][:-1], "triangle_object"),
        (15, torch.tensor([0, 6, 12], dtype=torch.int32), "triangle_first"),
        (15, torch.zeros(2, 3, dtype=torch.int64), "triangle_first"),
    ]:
        bad = list(args)
        bad[position] = wrong
        with pytest.raises(RuntimeError, match=name):
            fill(*bad)
        with pytest.raises(RuntimeError, match=name):
            count(*bad[:16])
    short = list(args)
    short[-1] = triangle[:-1].clone() if len(triangle) else torch.zeros(1, dtype=torch.int64)
    with pytest.raises(RuntimeError, match="triangle"):
        fill(*short)
    assert bool((vertex == -7).all()) and bool((triangle == -7).all())


def pile_state(dtype, device, self_contact: bool = False):
    """A SurfaceContact over 8 shaken blocks in two offset columns, its positions and velocities."""
    return shaken_pile_contact(dtype, device, tm.Contact(self_contact=self_contact))


@pytest.mark.parametrize("swept", [False, True])
@pytest.mark.parametrize("self_contact", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("device", DEVICES)
def test_nearest_pairs_equal_the_reference(swept, self_contact, dtype, device):
    """The narrow phase op keeps the reference's pairs, in its order, with its sides, weights and
    distances (to rounding: the op fuses what the reference does in separate kernels)."""
    surface, x, v = pile_state(dtype, device, self_contact)
    motion = surface._motion(x, v, 0.01) if swept else None
    vertex, triangle = surface.candidates(x, v if swept else None, 0.01 if swept else 0.0, motion)
    spread = body_step = None
    if swept:
        spread, body_step = torch.linalg.vector_norm(motion[0], dim=-1), motion[1]
    args = (x, surface.vertices, surface.vertex_object, surface.triangles, surface.triangle_object, vertex, triangle,
            spread, body_step, surface.reach)
    ours = contact.nearest_pairs(*args)
    theirs = contact.nearest_pairs(*args, native=False)
    assert len(ours[0]) > 50  # the blocks touch: pairs to compare
    assert torch.equal(ours[0], theirs[0]) and torch.equal(ours[1], theirs[1])
    assert torch.equal(ours[6], theirs[6])  # the sides
    tol = dict(rtol=0, atol=1e-5 if dtype == torch.float32 else 1e-12)
    for a, b in zip(ours[2:6], theirs[2:6]):
        torch.testing.assert_close(a, b, **tol)


@pytest.mark.parametrize("swept", [False, True])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("device", DEVICES)
def test_the_fill_takes_the_counts_choice_bit_for_bit(swept, dtype, device):
    """The count's ``chosen`` (a vertex's one pair: its candidate and side; none; several) is the
    reference's, and the fill that takes it writes, bit for bit, what the fill that walks every
    vertex's run again (``chosen`` -2 everywhere) writes."""
    surface, x, v = pile_state(dtype, device)
    motion = surface._motion(x, v, 0.01) if swept else None
    vertex, triangle = surface.candidates(x, v if swept else None, 0.01 if swept else 0.0, motion)
    spread = body_step = None
    if swept:
        spread, body_step = torch.linalg.vector_norm(motion[0], dim=-1), motion[1]
    first = torch.searchsorted(vertex, torch.arange(len(surface.vertices) + 1, device=device))
    args = (x, surface.vertices, surface.vertex_object, surface.triangles, surface.triangle_object, first, triangle,
            spread, body_step, surface.reach)
    counts, chosen = library.op("contact_count_nearest")(*args)
    ref_counts, ref_chosen = contact._ref_contact_count_nearest(*args)
    assert torch.equal(counts, ref_counts) and torch.equal(chosen, ref_chosen)
    assert int((chosen >= 0).sum()) > 20 and int((chosen == -1).sum()) > 20  # one pair and none, both met
    offsets = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    fills = []
    for choice in (chosen, torch.full_like(chosen, -2)):
        outputs = (torch.full((total,), -1, dtype=torch.int64, device=device), torch.full((total,), -1, device=device),
                   *(torch.full((total, 3), math.nan, dtype=dtype, device=device) for _ in range(2)),
                   torch.full((total,), math.nan, dtype=dtype, device=device),
                   torch.full((total, 3), math.nan, dtype=dtype, device=device),
                   torch.full((total,), math.nan, dtype=dtype, device=device))
        library.op("contact_fill_nearest")(*args, offsets, choice, *outputs)
        fills.append(outputs)
    for taken, walked in zip(*fills):
        assert torch.equal(taken, walked)


def test_a_vertex_near_too_many_bodies_takes_the_reference():
    """Twelve tiny bodies around one vertex (more than the kernel's slots) and a vertex on each
    side of it near two of them: the count reports the crowded one (-1), and nearest_pairs gives
    the reference's pairs, in its order: the op's for the others, the reference's for it alone."""
    x = [[0.0, 0.0, 0.0]]
    triangles, triangle_object = [], []
    for body in range(12):
        angle = 2 * math.pi * body / 12
        centre = torch.tensor([0.05 * math.cos(angle), 0.05 * math.sin(angle), 0.0])
        base = len(x)
        x += (centre + torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]])).tolist()
        triangles.append([base, base + 1, base + 2])
        triangle_object.append(body + 1)
    x += [[0.06, 0.0, 0.01], [-0.06, 0.0, 0.01]]
    x = torch.tensor(x, dtype=torch.float64)
    triangles = torch.tensor(triangles)
    vertices = torch.tensor([len(x) - 2, 0, len(x) - 1])
    vertex_object = torch.tensor([0, 0, 0])
    candidate_vertex = torch.tensor([0, 0] + [1] * 12 + [2, 2])
    candidate_triangle = torch.tensor([0, 1] + list(range(12)) + [5, 6])
    args = (x, vertices, vertex_object, triangles, torch.tensor(triangle_object), candidate_vertex,
            candidate_triangle, None, None, 0.2)
    counts, chosen = library.op("contact_count_nearest")(x, vertices, vertex_object, triangles,
                                                         torch.tensor(triangle_object), torch.tensor([0, 2, 14, 16]),
                                                         candidate_triangle, None, None, 0.2)
    assert counts.tolist() == [2, -1, 2] and chosen.tolist() == [-2, -1, -2]
    ours = contact.nearest_pairs(*args)
    theirs = contact.nearest_pairs(*args, native=False)
    assert ours[0].tolist() == [0, 0] + [1] * 12 + [2, 2]
    for a, b in zip(ours[:2] + ours[6:], theirs[:2] + theirs[6:]):  # the pairs and their sides
        assert torch.equal(a, b)
    for a, b in zip(ours[2:6], theirs[2:6]):  # (the op fuses what the reference rounds apart)
        torch.testing.assert_close(a, b, rtol=0, atol=1e-12)


def test_nearest_bad_arguments_raise_naming_them():
    args = list(contact._example_nearest_inputs("cpu", torch.float64))
    count = library.op("contact_count_nearest")
    for position, wrong, name in [(1, args[1].int(), "vertices"), (3, args[3][:, :2].contiguous(), "triangles"),
                                  (5, args[5][:-1], "first"), (7, args[7][:-1], "spread"),
                                  (0, args[0].float(), "spread")]:
        bad = list(args)
        bad[position] = wrong
        with pytest.raises(RuntimeError, match=name):
            count(*bad)
    bad = list(args)
    bad[9] = -1.0
    with pytest.raises(RuntimeError, match="reach"):
        count(*bad)
    fill_args = list(contact._example_fill_nearest("cpu", torch.float64)[0])
    written = [t.clone() for t in fill_args[12:]]
    fill_args[11] = fill_args[11][:-1]  # chosen
    with pytest.raises(RuntimeError, match="chosen"):
        library.op("contact_fill_nearest")(*fill_args)
    assert all(torch.equal(a, b) for a, b in zip(fill_args[12:], written))


@pytest.mark.parametrize("friction", [0.0, 0.4])
@pytest.mark.parametrize("device", DEVICES)
def test_pair_product_equals_the_reference_and_the_pairs_matrix(friction, device):
    """The pairs' product as the op equals its tensor-op reference and the assembled
    sum over pairs of J^T (a u u^T + b P_t) J, on a shaken pile's pairs (float64)."""
    from tensormass_torch.physics.body_contact import PairStiffness

    surface, x, v = pile_state(torch.float64, device)
    pairs = surface.detect(x, v, 0.01)
    assert len(pairs) > 20
    pairs.friction = None if friction == 0 else torch.full_like(pairs.gap, friction)
    product = PairStiffness()
    product.load(pairs, 2.0, 0.5)
    dx = torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64).to(device)
    args = (dx, product.nodes, product.coef, product.direction, product.normal, product.friction, product.order,
            product.offsets)
    ours = contact.pair_product(*args, product.vector.clone())
    theirs = contact.pair_product(*args, product.vector.clone(), native=False)
    torch.testing.assert_close(ours, theirs, rtol=1e-12, atol=1e-12)
    # added to another product in place (accumulate): that product plus it, the nodes no pair
    # touches left as they were, bit for bit, by the op and the reference alike
    other = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64).to(device)
    for native in (True, False):
        target = other.clone()
        added = contact.pair_product(*args, product.vector.clone(), native=native, add_to=target)
        assert added is target
        torch.testing.assert_close(added, other + ours, rtol=1e-12, atol=1e-12)
        untouched = product.offsets[1:] == product.offsets[:-1]
        assert bool(untouched.any()) and torch.equal(added[untouched], other[untouched])
    # the assembled matrix, pair by pair
    count = len(pairs)
    jac = torch.zeros(count, 3, x.shape[0], 3, dtype=torch.float64, device=device)
    for i in range(4):
        jac[torch.arange(count), :, pairs.nodes[:, i], :] += (pairs._coefficients()[:, i, None, None]
                                                              * torch.eye(3, dtype=torch.float64, device=device))
    u = pairs.direction
    a = 2.0 * pairs.stiffness  # (a float: one stiffness for every pair)
    b = 0.5 * (torch.zeros_like(pairs.gap) if pairs.friction is None else pairs.friction)
    outer = u[:, :, None] * u[:, None, :]
    block = a * outer + b[:, None, None] * (torch.eye(3, dtype=torch.float64, device=device) - outer)
    matrix = torch.einsum("cavk,cab,cbwl->vkwl", jac, block, jac)
    expected = torch.einsum("vkwl,wl->vk", matrix, dx)
    torch.testing.assert_close(ours, expected, rtol=1e-10, atol=1e-10)


def test_pair_product_bad_arguments_raise_naming_them():
    args = list(contact._example_pair_product("cpu", torch.float64)[0])
    op = library.op("contact_pair_product")
    for position, wrong, name in [(1, args[1].int(), "nodes"), (2, args[2][:, :3].contiguous(), "coef"),
                                  (7, args[7][:-1], "offsets"), (9, args[0], "out")]:
        bad = list(args)
        bad[position] = wrong
        with pytest.raises(RuntimeError, match=name):
            op(*bad)


@pytest.mark.parametrize("device", DEVICES)
def test_the_order_the_queries_are_taken_in_changes_no_output(device):
    """``query_order`` only says which query each thread serves: any permutation gives the same
    counts and the same candidates, each query's at its own offsets."""
    cell, low, high, triangle_object, point_low, point_high, vertex_object = pile_boxes(torch.float32, device, True)
    queries = list(contact.hash_queries(cell, low, high, point_low, point_high))
    outputs = []
    for order in (queries[4], torch.arange(len(queries[0]), device=device),
                  torch.randperm(len(queries[0]), generator=torch.Generator().manual_seed(3)).to(device)):
        queries[4] = order
        args = (cell.reshape(1), point_low, point_high, vertex_object, *queries, low, high, triangle_object, False,
                first_triangles(triangle_object))
        counts = library.op("contact_count_candidates")(*args)
        offsets = torch.cumsum(counts, 0) - counts
        vertex = torch.full((int(counts.sum()),), -1, dtype=torch.int64, device=device)
        triangle = torch.full_like(vertex, -1)
        library.op("contact_fill_candidates")(*args, offsets, vertex, triangle)
        outputs.append((counts, vertex, triangle))
    assert len(outputs[0][1]) > 100
    for other in outputs[1:]:
        for ours, theirs in zip(outputs[0], other):
            assert torch.equal(ours, theirs)


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("device", DEVICES)
def test_a_pair_at_the_reach_is_kept_only_outside(native, device):
    """Within the ties' rounding of the reach a triangle tied with the nearest one may lie just
    past it, left out of the pseudonormal: one face alone then puts a vertex beside its edge
    behind its plane, "inside" by a whole search (seen on a settled pile). So there a pair is kept
    only outside; nearer by more than the rounding, inside too."""
    dtype, reach = torch.float64, 0.02
    rounding = 32 * torch.finfo(dtype).eps * (0.5 + reach)  # the narrow phase's, for these vertices
    heights = [reach - rounding / 4, reach - 4 * rounding, -(reach - rounding / 4)]  # above: inside
    x = torch.tensor([[-1.0, -1.0, 0.0], [3.0, -1.0, 0.0], [-1.0, 3.0, 0.0]]
                     + [[0.5, 0.5, z] for z in heights], dtype=dtype, device=device)
    triangles = torch.tensor([[0, 2, 1]], device=device)  # its normal -z: the body lies above it
    vertices = torch.tensor([3, 4, 5], device=device)
    candidate_vertex = torch.arange(3, device=device)
    pairs = contact.nearest_pairs(x, vertices, torch.zeros(3, dtype=torch.int64, device=device), triangles,
                                  torch.ones(1, dtype=torch.int64, device=device), candidate_vertex,
                                  torch.zeros(3, dtype=torch.int64, device=device), None, None, reach, native=native)
    vertex, side = pairs[0].tolist(), pairs[6].tolist()
    assert vertex == [1, 2] and side == [-1.0, 1.0]


@pytest.mark.parametrize("device", DEVICES)
def test_a_surface_in_body_order_skips_its_own_body_and_finds_the_same_candidates(device):
    """SurfaceContact passes where each body's triangles start when they come in body order (the
    packed bodies'), and nothing otherwise (triangles shuffled): the searches' pairs
    are the same either way, over all bodies and over a subset."""
    from tensormass_torch.physics.body_contact import SurfaceContact

    surface, x, _ = pile_state(torch.float64, device)
    assert surface._triangle_first is not None and len(surface._triangle_first) == surface.num_objects + 1
    some = torch.zeros(surface.num_objects, dtype=torch.bool, device=device)
    some[[1, 2, 5]] = True
    searches = [surface._search(x, None, surface.reach), surface._search(x, None, surface.reach, some)]
    first, surface._triangle_first = surface._triangle_first, None
    assert len(searches[0][0]) > 100
    for bodies, (vertex, triangle) in zip((None, some), searches):
        whole = surface._search(x, None, surface.reach, bodies)
        assert torch.equal(vertex, whole[0]) and torch.equal(triangle, whole[1])
    surface._triangle_first = first
    shuffled = torch.randperm(len(surface.triangles), generator=torch.Generator().manual_seed(0)).to(device)
    other = SurfaceContact(surface.triangles[shuffled], surface.node_object, x, tm.Contact())
    assert other._triangle_first is None
