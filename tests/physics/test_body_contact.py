"""Contact between bodies (physics.body_contact): the vertex-triangle penalty's force and stiffness
against the energy's derivatives (float64), momentum, the implicit step with contact against a
dense solve, two bodies dropped onto each other and a floor, the simulator's reports, bad input."""
import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import random_rotation, shaken_pile_contact

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces
from tensormass_torch.physics.body_contact import (
    Contact,
    ContactPairs,
    PairStiffness,
    SurfaceContact,
    closest_weights,
    coupled_ranges,
    signed_distance,
)
from tensormass_torch.solver.implicit_euler import implicit_euler_step

DT = torch.float64


def two_blocks(offset=(0.05, 0.03, 0.09), cells=(3, 3, 2), seed=0, jitter=0.004):
    """Two 0.2 x 0.2 x 0.1 blocks, the second shifted by ``offset`` and turned a little (they
    overlap), nodes jittered: (meshes, packed rest [V, 3], surface triangles, node objects)."""
    a = tm.beam_mesh(*cells, size=(0.2, 0.2, 0.1), dtype=DT)
    b = tm.beam_mesh(*cells, size=(0.2, 0.2, 0.1), dtype=DT)
    rng = np.random.default_rng(seed)
    turn = torch.tensor(random_rotation(rng, 3), dtype=DT)
    small = torch.linalg.matrix_exp(0.1 * (turn - turn.T))  # a rotation near the identity
    centre = torch.tensor([0.1, 0.1, 0.05], dtype=DT)
    b = tm.TetMesh((b.vertices - centre) @ small.T + centre + torch.tensor(offset, dtype=DT), b.elements)
    gen = torch.Generator().manual_seed(seed)
    rest = torch.cat([a.vertices, b.vertices])
    rest = rest + jitter * (torch.rand(rest.shape, generator=gen, dtype=DT) - 0.5)
    triangles = torch.cat([boundary_faces(a.elements), boundary_faces(b.elements) + a.num_vertices])
    objects = torch.cat([torch.zeros(a.num_vertices, dtype=torch.int64), torch.ones(b.num_vertices, dtype=torch.int64)])
    return (a, b), rest, triangles, objects


def test_closest_point_against_a_dense_search():
    """The closest point's weights against the best of a fine grid over the triangle."""
    gen = torch.Generator().manual_seed(1)
    tri = torch.rand(200, 3, 3, generator=gen, dtype=DT)
    p = torch.rand(200, 3, generator=gen, dtype=DT) * 2 - 0.5
    w = closest_weights(p, tri[:, 0], tri[:, 1], tri[:, 2])
    assert bool((w >= -1e-12).all()) and torch.allclose(w.sum(-1), torch.ones(200, dtype=DT))
    d = torch.linalg.vector_norm(p - (w[:, :, None] * tri).sum(1), dim=-1)
    n = 120
    i, j = torch.meshgrid(torch.arange(n + 1), torch.arange(n + 1), indexing="ij")
    keep = i + j <= n
    grid = torch.stack([n - i[keep] - j[keep], i[keep], j[keep]], -1).to(DT) / n  # [G, 3]
    points = torch.einsum("gk,pkc->pgc", grid, tri)
    best = torch.linalg.vector_norm(p[:, None] - points, dim=-1).amin(1)
    assert bool((d <= best + 1e-12).all())  # never further than any grid point
    assert float((best - d).max()) < 2e-2 / n * 10  # and the grid comes within its spacing


def test_signed_distance_sign_and_gradient():
    a, b, c = (torch.tensor(v, dtype=DT) for v in ([0.0, 0, 0], [1.0, 0, 0], [0.0, 1, 0]))
    s, u, w = signed_distance(torch.tensor([[0.2, 0.2, 0.3], [0.2, 0.2, -0.1]], dtype=DT), a, b, c)
    torch.testing.assert_close(s, torch.tensor([0.3, -0.1], dtype=DT))
    torch.testing.assert_close(u, torch.tensor([[0.0, 0, 1], [0.0, 0, 1]], dtype=DT))
    torch.testing.assert_close(w, torch.tensor([[0.6, 0.2, 0.2]] * 2, dtype=DT))


def probes_outside_a_block(dtype, seed, n=300):
    """A jittered, turned block away from the origin and n tiny probe triangles (bodies 1..n) just
    outside it past its edges, nearly along one face's normal: the other face sees p - q at a
    grazing angle, so only both normals together tell the side. (rest [V, 3], triangles, objects)."""
    rng = np.random.default_rng(seed)
    block = tm.beam_mesh(5, 5, 3, size=(0.2, 0.2, 0.1), dtype=DT)
    sizes = torch.tensor([0.2, 0.2, 0.1], dtype=DT)
    rows = torch.arange(n)
    corner = torch.from_numpy(rng.integers(0, 2, size=(n, 3))).to(DT)
    along = torch.from_numpy(rng.integers(0, 3, size=n))  # the edge's axis
    base = corner * sizes
    base[rows, along] = torch.from_numpy(rng.uniform(0.05, 0.95, size=n)) * sizes[along]
    out = 2 * corner - 1
    out[rows, along] = 0.0
    lean = torch.where(torch.from_numpy(rng.integers(0, 2, size=n)).bool(), (along + 1) % 3, (along + 2) % 3)
    out[rows, lean] *= torch.from_numpy(rng.uniform(0.0, 0.05, size=n))
    p = base + out / out.norm(dim=1, keepdim=True) * torch.from_numpy(rng.uniform(0.003, 0.03, size=n))[:, None]
    tiny = torch.tensor([[0, 0, 0], [1e-5, 0, 0], [0, 1e-5, 0]], dtype=DT)
    block_nodes = block.vertices + torch.from_numpy(rng.uniform(-5e-4, 5e-4, size=tuple(block.vertices.shape)))
    turn = torch.tensor(random_rotation(rng, 3), dtype=DT)
    rest = torch.cat([block_nodes, (p[:, None] + tiny).reshape(-1, 3)]) @ turn.T + torch.tensor([0.7, -0.3, 0.4], dtype=DT)
    triangles = torch.cat([boundary_faces(block.elements), block.num_vertices + torch.arange(3 * n).reshape(n, 3)])
    objects = torch.cat([torch.zeros(block.num_vertices, dtype=torch.int64), 1 + rows.repeat_interleave(3)])
    return rest.to(dtype), triangles, objects


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("seed", [0, 1])
def test_points_just_past_an_edge_are_outside(dtype, seed):
    """No probe outside the block is taken for inside it, in float32 too (the two faces of an edge
    compute its distance with different rounding: both must count for the side)."""
    rest, triangles, objects = probes_outside_a_block(dtype, seed)
    contact = SurfaceContact(triangles, objects, rest, Contact(search=0.05))
    pairs = contact.detect(rest)
    into_block = pairs.objects[:, 1] == 0
    assert int(into_block.sum()) == 0, pairs.signed[into_block]
    # the probes are near the block: their distances are seen, positive
    vertex, triangle = contact.candidates(rest)
    assert int((contact.triangle_object[triangle] == 0).sum()) > 300


@pytest.fixture(params=[0, 1, 2])
def overlapping(request):
    meshes, rest, triangles, objects = two_blocks(seed=request.param)
    contact = SurfaceContact(triangles, objects, rest, Contact(stiffness=3e3, thickness=0.01, tangent="exact"))
    return contact, rest


def test_per_body_reductions_in_packed_and_shuffled_node_orders():
    """The bodies' motion and boxes (``SurfaceContact._bodies``): segment reductions where the bodies
    own contiguous node ranges, sorted sums and scatters where they do not; both against dense
    per-body references, bit for bit between the two orders (sums up to roundoff)."""
    _, rest, triangles, objects = two_blocks()
    gen = torch.Generator().manual_seed(3)
    rate = torch.randn(rest.shape, generator=gen, dtype=DT)
    packed = SurfaceContact(triangles, objects, rest, Contact())
    assert packed._contiguous
    # the same bodies with their nodes renumbered so that they interleave
    perm = torch.randperm(len(rest), generator=gen)
    new_id = torch.empty_like(perm)
    new_id[perm] = torch.arange(len(rest))
    shuffled = SurfaceContact(new_id[triangles], objects[perm], rest[perm], Contact())
    assert not shuffled._contiguous
    a = packed._bodies(rest, rate, 0.5)
    b = shuffled._bodies(rest[perm], rate[perm], 0.5)
    mean = torch.stack([rate[objects == k].mean(0) for k in (0, 1)])
    torch.testing.assert_close(a[1], 0.5 * mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(b[1], 0.5 * mean, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(a[0][perm], b[0], rtol=1e-12, atol=1e-14)
    surface = torch.unique(triangles)
    deviation = torch.linalg.vector_norm(0.5 * rate[surface] - 0.5 * mean[objects[surface]], dim=-1)
    for k in (0, 1):
        on = objects[surface] == k
        torch.testing.assert_close(a[2][k], deviation[on].max(), rtol=1e-12, atol=1e-14)
        assert torch.equal(a[3][k], rest[surface][on].amin(0)) and torch.equal(a[4][k], rest[surface][on].amax(0))
    for got, want in zip(a[2:], b[2:]):
        torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
    assert torch.equal(packed._per_body_max(torch.zeros(len(packed.vertices), dtype=DT)), torch.zeros(2, dtype=DT))


@pytest.mark.parametrize("offset", [1.0, 10.0])
def test_a_resting_pairs_direction_keeps_its_precision_far_from_the_origin(offset):
    """float32, a small block pressed 1 um into a larger one's top face, both ``offset`` metres from
    the origin: its bottom vertices' pair directions are those of the same (rounded) positions in
    float64 to 2e-2 (the closest point's difference is taken from the triangle's corner; taken
    from the origin it lost the micrometre: 0.11 off at 1 m, 0.92 at 10 m)."""
    base = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=torch.float64)
    top = tm.beam_mesh(3, 3, 1, size=(0.1, 0.1, 0.05), origin=(0.047, 0.053, 0.1 - 1e-6), dtype=torch.float64)
    rest = (torch.cat([base.vertices, top.vertices]) + offset).to(torch.float32)
    triangles = torch.cat([boundary_faces(base.elements), boundary_faces(top.elements) + base.num_vertices])
    objects = torch.cat([torch.zeros(base.num_vertices, dtype=torch.int64),
                         torch.ones(top.num_vertices, dtype=torch.int64)])
    single, _ = SurfaceContact(triangles, objects, rest, Contact()).nearby(rest)
    double, _ = SurfaceContact(triangles, objects, rest.double(), Contact()).nearby(rest.double())
    assert single.nodes.shape == double.nodes.shape
    # the small block's bottom vertices inside the large one, where both chose one triangle (ties
    # between coplanar triangles may go either way)
    pressed = (single.nodes == double.nodes).all(1) & (double.objects[:, 0] == 1) & (double.gap < 0)
    assert int(pressed.sum()) >= 8
    error = (single.direction[pressed].double() - double.direction[pressed]).norm(dim=1)
    assert float(error.max()) < 2e-2


def test_pairs_are_found_both_ways(overlapping):
    contact, x = overlapping
    pairs = contact.detect(x)
    assert len(pairs) >= 8
    assert {tuple(o) for o in pairs.objects.tolist()} == {(0, 1), (1, 0)}
    assert bool((pairs.gap < 0).all()) and bool((pairs.signed < contact.settings.thickness).all())
    # every pair's triangle belongs to the other body, its vertex to its own
    assert bool((contact.node_object[pairs.nodes[:, 0]] == pairs.objects[:, 0]).all())
    assert bool((contact.node_object[pairs.nodes[:, 1:]] == pairs.objects[:, 1:2]).all())


@pytest.mark.parametrize("speed", [0.0, 3.0])
def test_broad_phase_holds_every_pair_whose_boxes_meet_once(overlapping, speed):
    """The candidates hold, each once, every (vertex, triangle) pair of different bodies whose
    boxes meet: the triangle's grown by the reach; with velocities (Contact.swept), both swept
    over the step in the triangle's body's frame (the vertex's segment relative to that body's
    mean motion): up to 15 cm a step here, past several cells."""
    contact, x = overlapping
    contact.settings = dataclasses.replace(contact.settings, swept=True)
    gen = torch.Generator().manual_seed(3)
    v = speed * (torch.rand(x.shape, generator=gen, dtype=DT) - 0.5)
    v[contact.node_object == 1] += torch.tensor([0.0, 0.0, -speed], dtype=DT)  # closing on the other
    dt = 0.1
    vertex, triangle = contact.candidates(x, v, dt) if speed else contact.candidates(x)
    found = list(zip(vertex.tolist(), triangle.tolist()))
    assert len(found) == len(set(found))
    mean = torch.stack([v[contact.node_object == b].mean(0) for b in range(2)])
    frame = mean[contact.triangle_object]  # [F, 3] each triangle's body's mean velocity
    corners = x[contact.triangles]
    moved = corners + dt * (v[contact.triangles] - frame[:, None])
    swept = torch.cat([corners, moved], 1)
    low, high = swept.amin(1) - contact.reach, swept.amax(1) + contact.reach  # [F, 3]
    points = x[contact.vertices]
    ends = points[:, None] + dt * (v[contact.vertices][:, None] - frame[None])  # [S, F, 3]
    point_low, point_high = torch.minimum(points[:, None], ends), torch.maximum(points[:, None], ends)
    meet = ((point_low <= high[None]) & (point_high >= low[None])).all(-1)
    meet &= contact.vertex_object[:, None] != contact.triangle_object[None]
    assert set(found) >= set(map(tuple, meet.nonzero().tolist()))
    if speed:
        still = set(zip(*(t.tolist() for t in contact.candidates(x))))
        assert set(found) - still  # pairs only the motion brings within reach


def test_force_is_minus_the_energy_gradient(overlapping):
    contact, x = overlapping
    y = x.clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(contact.energy(y), y)
    forces = contact.forces(x)
    assert float(forces.abs().max()) > 1.0
    torch.testing.assert_close(forces, -gradient, rtol=1e-10, atol=1e-10)


def test_linear_forces_are_the_forces_plus_their_change(overlapping):
    """ContactPairs.linear_forces(dx), the forces of the pairs' linear model at x + dx (a step's
    right-hand side), equals forces() + dforces(dx), with either tangent."""
    contact, x = overlapping
    pairs = contact.detect(x)
    dx = torch.randn(x.shape, generator=torch.Generator().manual_seed(2), dtype=DT)
    for chosen in (pairs, dataclasses.replace(pairs, hessians=None)):
        expected = chosen.forces() + chosen.dforces(dx)
        assert float(expected.abs().max()) > 1.0
        torch.testing.assert_close(chosen.linear_forces(dx), expected, rtol=1e-12, atol=1e-12)


def test_node_sums_by_runs_equal_add_ats(overlapping):
    """ContactPairs.node_sums: summed by the entries' runs (a sort once for the pairs, then a
    gather and a segment sum: CUDA's way) equals add_at's sums (the CPU's), for every sum the
    pairs form, and the runs are formed once per pairs; the pair stiffness loads the same runs."""
    contact, x = overlapping
    pairs = contact.detect(x)
    pairs.friction = torch.rand(len(pairs), generator=torch.Generator().manual_seed(3), dtype=DT)
    dx = torch.randn(x.shape, generator=torch.Generator().manual_seed(4), dtype=DT)
    per_entry = torch.randn(4 * len(pairs), 5, generator=torch.Generator().manual_seed(5), dtype=DT)
    by_runs = pairs.node_sums(per_entry, by_runs=True)
    torch.testing.assert_close(by_runs, pairs.node_sums(per_entry, by_runs=False), rtol=1e-12, atol=1e-12)
    assert pairs.runs() is pairs.runs()
    order, offsets = pairs.runs()
    assert torch.equal(pairs.nodes.reshape(-1)[order], torch.sort(pairs.nodes.reshape(-1)).values)
    assert int(offsets[-1]) == 4 * len(pairs) and int(offsets[0]) == 0
    values = per_entry[:, :2].clone().requires_grad_(True)  # the adjoint differentiates through them
    assert torch.autograd.gradcheck(lambda t: pairs.node_sums(t, by_runs=True), (values,))
    projected = dataclasses.replace(pairs, hessians=None)
    sums = lambda: [projected.forces(), projected.dforces(dx), projected.linear_forces(dx),  # noqa: E731
                    projected.friction_forces(dx), projected.stiffness_diagonal(2.0, 0.5),
                    projected.stiffness_row_l1(2.0, 0.5), projected.stiffness_blocks(2.0, 0.5)]
    expected = sums()
    original = ContactPairs.node_sums
    try:
        ContactPairs.node_sums = lambda self, values, by_runs=None: original(self, values, by_runs=True)
        for got, want in zip(sums(), expected):
            assert float(want.abs().max()) > 0
            torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-12)
    finally:
        ContactPairs.node_sums = original
    stiffness = PairStiffness()
    stiffness.load(projected, 2.0, 0.5)
    torch.testing.assert_close(stiffness.stiffness_blocks(), expected[-1], rtol=1e-12, atol=1e-12)


def test_forces_conserve_momentum(overlapping):
    """The forces sum to zero and so does their torque: linear and angular momentum."""
    contact, x = overlapping
    forces = contact.forces(x)
    scale = float(forces.abs().sum())
    assert float(forces.sum(0).abs().max()) < 1e-12 * scale
    assert float(torch.linalg.cross(x, forces).sum(0).abs().max()) < 1e-12 * scale
    for body in (0, 1):  # and each body takes an equal and opposite share
        mine = contact.node_object == body
        assert float(forces[mine].abs().sum()) > 0


def test_stiffness_against_finite_differences_of_the_force(overlapping):
    """tangent="exact": the pairs' product is the force's derivative (the pairs held: a step keeps
    those found where it linearises); the projected one, k J^T J, is symmetric positive
    semi-definite and differs from it by the curvature term."""
    contact, x = overlapping
    pairs = contact.detect(x)
    gen = torch.Generator().manual_seed(5)
    dx = torch.randn(x.shape, generator=gen, dtype=DT)
    eps = 1e-6
    fd = (pairs_at(contact, pairs, x + eps * dx).forces() - pairs_at(contact, pairs, x - eps * dx).forces()) / (2 * eps)
    torch.testing.assert_close(pairs.dforces(dx), fd, rtol=1e-6, atol=1e-6)
    projected = dataclasses.replace(pairs, hessians=None)
    assert float((projected.dforces(dx) - pairs.dforces(dx)).abs().max()) > 1e-3
    y = torch.randn(x.shape, generator=gen, dtype=DT)
    assert float((y * projected.dforces(dx)).sum()) == pytest.approx(float((dx * projected.dforces(y)).sum()),
                                                                     rel=1e-10)
    assert float(-(dx * projected.dforces(dx)).sum()) >= 0


def pairs_at(contact, pairs, y):
    """The same pairs (vertex, triangle, side) evaluated at positions ``y``."""
    from tensormass_torch.physics.body_contact import closest_point

    nodes = pairs.nodes
    w, diff, d, normal = closest_point(y[nodes[:, 0]], y[nodes[:, 1]], y[nodes[:, 2]], y[nodes[:, 3]])
    side = torch.sign(pairs.signed)
    u = side[:, None] * diff / d[:, None]
    return dataclasses.replace(pairs, weights=w, direction=u, signed=side * d,
                               gap=side * d - contact.settings.thickness)


@pytest.mark.parametrize("friction", [False, True])
def test_pair_stiffness_buffers_equal_the_pairs_product(friction):
    """The fixed-capacity product (what a captured CG replays) is -c times the pairs' projected
    dforces minus b times their friction forces, with padding that adds nothing; loading fewer
    pairs keeps the buffers, more grows them."""
    meshes, rest, triangles, objects = two_blocks()
    contact = SurfaceContact(triangles, objects, rest, Contact(stiffness=3e3, thickness=0.01))
    pairs = contact.detect(rest)
    gen = torch.Generator().manual_seed(3)
    if friction:
        pairs.friction = torch.rand(len(pairs), dtype=DT, generator=gen) * 50.0
    dx = torch.randn(rest.shape, dtype=DT, generator=gen)

    def expected(some):
        return -0.7 * some.dforces(dx) - 0.3 * some.friction_forces(dx)

    fields = ("nodes", "weights", "direction", "signed", "gap", "objects") + (("friction",) if friction else ())
    product = PairStiffness()
    assert product.load(pairs, 0.7, 0.3)  # first load allocates
    assert product.capacity >= len(pairs) and product.capacity & (product.capacity - 1) == 0
    torch.testing.assert_close(product(dx), expected(pairs), rtol=1e-12, atol=1e-12)
    fewer = dataclasses.replace(pairs, **{f: getattr(pairs, f)[: len(pairs) // 2] for f in fields})
    storage = product.coef.data_ptr()
    assert not product.load(fewer, 0.7, 0.3) and product.coef.data_ptr() == storage
    torch.testing.assert_close(product(dx), expected(fewer), rtol=1e-12, atol=1e-12)
    more = dataclasses.replace(pairs, **{f: torch.cat([getattr(pairs, f)] * (product.capacity // len(pairs) + 1))
                                         for f in fields})
    assert product.load(more, 0.7, 0.3)
    torch.testing.assert_close(product(dx), expected(more), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("preconditioner", ["auto", "none"])
def test_the_step_with_contact_equals_a_dense_solve(preconditioner):
    """One implicit Euler step of two bodies in contact (projected stiffness) against the dense
    system: the elastic Jacobian by autograd, the pairs' k J^T J assembled, solved by LU; with the
    default preconditioner (Jacobi where pairs join the solve) and without."""
    material = tm.Material(young=1e4, poisson=0.3, density=1000)
    (a, b), rest, _, _ = two_blocks(offset=(0.05, 0.03, 0.095), cells=(2, 2, 1), jitter=0.0)
    bodies = [tm.Body(tm.TetMesh(rest[:a.num_vertices], a.elements), material),
              tm.Body(tm.TetMesh(rest[a.num_vertices:], b.elements), material)]
    sim = tm.Simulator(bodies, dt=0.01, contact=tm.Contact(stiffness=1e3, thickness=0.01), rayleigh_mass=0.5,
                       cg_tol=1e-13, cuda_graphs=False, preconditioner=preconditioner)
    gen = torch.Generator().manual_seed(2)
    x = sim.x + 0.003 * torch.randn(sim.x.shape, generator=gen, dtype=DT)
    v = 0.1 * torch.randn(sim.x.shape, generator=gen, dtype=DT)
    system = sim.system
    pairs = sim.body_contact.detect(x)
    assert len(pairs) >= 4 and {0, 1} <= set(pairs.objects.flatten().tolist())
    _, v_new, report = implicit_euler_step(system, x, v, sim.options)
    # the two bodies were solved as one system: the same iterations
    assert report.cg_iterations[0] == report.cg_iterations[1]
    n, h, r_m = x.numel(), sim.options.dt, 0.5
    stiffness = torch.autograd.functional.jacobian(lambda y: system.model(y.reshape(-1, 3)).reshape(-1),
                                                   x.reshape(-1))
    for p in range(len(pairs)):
        jac = torch.zeros(n, dtype=DT)
        for coef, node in zip([1.0] + (-pairs.weights[p]).tolist(), pairs.nodes[p].tolist()):
            jac[3 * node:3 * node + 3] += coef * pairs.direction[p]
        stiffness -= pairs.stiffness * torch.outer(jac, jac)
    mass = system.mass.expand_as(x).reshape(-1)
    forces = system.forces(x).reshape(-1)
    matrix = torch.diag(mass * (1 + h * r_m)) - h * h * stiffness
    rhs = h * (forces + h * stiffness @ v.reshape(-1) - r_m * mass * v.reshape(-1))
    expected = v + torch.linalg.solve(matrix, rhs).reshape(-1, 3)
    torch.testing.assert_close(v_new, expected, rtol=1e-9, atol=1e-9)


def mean_edge_length(mesh) -> float:
    edges = mesh.edges()
    return float(torch.linalg.vector_norm(mesh.vertices[edges[:, 0]] - mesh.vertices[edges[:, 1]], dim=-1).mean())


def test_two_bodies_dropped_on_each_other_and_a_floor_come_to_rest():
    """The documented defaults (tm.Contact(): k = 1e5 N/m, dt = 0.005): a block dropped 2 cm onto
    another on the floor rests on it, its surface at most 1 % of the mean edge length inside."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    lower = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=DT)
    upper = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.12), dtype=DT)
    sim = tm.Simulator([tm.Body(lower, material), tm.Body(upper, material)], dt=0.005,
                       planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(), rayleigh_mass=1.0)
    deepest = torch.zeros(2, dtype=DT)
    for _ in range(120):
        report = sim.step()
        deepest = torch.maximum(deepest, report.contact.body_penetration)
    assert float(deepest.max()) <= 0.01 * mean_edge_length(lower)
    assert bool((report.contact.body_contacts > 0).all())  # they touch
    assert float(sim.kinetic_energy().sum()) < 1e-4  # at rest
    # the upper one sits on the lower one, which sits on the floor
    assert float(sim.positions(1)[:, 2].mean()) > float(sim.positions(0)[:, 2].max())
    assert float(sim.positions(0)[:, 2].min()) > -0.01 * mean_edge_length(lower)


def test_static_balance_of_two_bodies_in_contact_and_a_tool():
    """Two clamped blocks pressed 1 mm into each other, a sphere pushing the lower one sideways:
    at static equilibrium (solve_static with the body contact, float64) the force on the tool
    equals the forces at both bodies' fixed nodes plus gravity (1e-6 relative), and the
    contact's forces between the bodies sum to zero."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    mesh = tm.beam_mesh(4, 4, 2, size=(0.1, 0.1, 0.05), dtype=DT)
    lower = tm.Body(mesh, material, fixed=mesh.vertices[:, 2] < 1e-9)  # held at its bottom
    upper = tm.Body(tm.TetMesh(mesh.vertices + torch.tensor([0.02, 0.01, 0.049], dtype=DT), mesh.elements),
                    material, fixed=mesh.vertices[:, 2] > 0.05 - 1e-9)  # held at its top
    sphere = tm.Sphere(0.03, position=(-0.028, 0.05, 0.03), stiffness=1e4)
    sim = tm.Simulator([lower, upper], dt=0.01, dtype=DT, contact=tm.Contact(), tools=[sphere])
    fixed = sim.system.free[:, 0] == 0
    gravity = (0.0, 0.0, -9.81)
    u = tm.solve_static(sim.model, fixed=fixed, gravity=gravity, tools=sim.tools, body_contact=sim.body_contact,
                        tol=1e-10)
    x = sim.model.rest + u
    between = sim.body_contact.forces(x)
    assert len(sim.body_contact.detect(x)) > 0 and float(sim.tools.forces(x).abs().sum()) > 0
    weight = sim.model.lumped_mass()[:, None] * torch.tensor(gravity, dtype=DT)
    at_fixed = -(sim.model(x) + weight + between + sim.tools.forces(x))[fixed]  # what the supports put on
    force, _ = sim.tools.reactions(x)
    expected = at_fixed.sum(0) + weight.sum(0)
    torch.testing.assert_close(force[0], expected, rtol=1e-6, atol=1e-6 * float(expected.norm()))
    assert float(between.sum(0).norm()) <= 1e-12 * float(between.abs().sum())


def test_a_body_faster_than_the_search_per_step_does_not_go_through():
    """A block shot at 6 m/s onto a held one with dt = 0.01 s moves 6 cm a step, more than the
    search (the mean edge, 5.7 cm) and than the held block's thickness: the broad phase sweeps
    the boxes over the step (Contact(swept=True), the default), the pairs are found before it
    is inside, and it bounces off; without the sweep it goes through."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    lower = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=DT)
    upper = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.16), dtype=DT)
    sim = tm.Simulator([tm.Body(lower, material, fixed=lower.vertices[:, 2] < 1e-9),
                        tm.Body(upper, material, velocity=(0, 0, -6.0))], dt=0.01,
                       contact=tm.Contact(), dtype=DT)
    assert 6.0 * 0.01 > sim.body_contact.search
    deepest = 0.0
    for _ in range(20):
        sim.step()
        deepest = max(deepest, float(sim.interpenetration().max()))
    assert float(sim.positions(1)[:, 2].min()) > float(sim.positions(0)[:, 2].max())  # above it, going up
    assert float(sim.v[sim.ptr[1]:, 2].mean()) > 0
    assert deepest < 0.2 * sim.body_contact.search
    still = tm.Simulator([tm.Body(lower, material, fixed=lower.vertices[:, 2] < 1e-9),
                          tm.Body(upper, material, velocity=(0, 0, -6.0))], dt=0.01,
                         contact=tm.Contact(swept=False), dtype=DT)
    still.step(20)
    assert float(still.positions(1)[:, 2].min()) < float(still.positions(0)[:, 2].max())


def falling_pair(contact, **options):
    """Two blocks falling together at 1 m/s, 0.1 mm apart, the lower one at the floor (float64):
    no pair is closing at the start, but the floor stops the lower block within the first step."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    lower = tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, -0.005), dtype=DT)
    upper = tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.0951), dtype=DT)
    sim = tm.Simulator([tm.Body(lower, material), tm.Body(upper, material)], dt=0.005,
                       planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=contact, rayleigh_mass=1.0, dtype=DT,
                       **options)
    sim.v = torch.zeros_like(sim.v)
    sim.v[:, 2] = -1.0
    return sim


def test_the_pairs_product_in_the_step_length_skips_stopped_runs_and_steps_as_the_whole_product(monkeypatch):
    """In the CG's iterations the pairs' product goes into the fused product that ends in the step
    length (``_WithPairs.matvec_alpha``), which skips the objects (coupled runs of bodies) that
    have stopped: two stacks falling at different speeds, each a run of two bodies, stop at
    different iterations, and the steps are those of the product called whole (the same
    iterations, the states to rounding)."""
    from tensormass_torch.solver import implicit_euler

    def two_stacks():
        material = tm.Material(young=1e5, poisson=0.3, density=1000)
        bodies = []
        for x0 in (0.0, 1.0):
            for z0 in (-0.005, 0.0951):
                mesh = tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(x0, 0.0, z0), dtype=DT)
                bodies.append(tm.Body(mesh, material))
        sim = tm.Simulator(bodies, dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(),
                           rayleigh_mass=1.0, dtype=DT)
        sim.v = torch.zeros_like(sim.v)
        sim.v[:, 2] = torch.where(sim.x[:, 0] < 0.5, -1.0, -0.3).to(DT)
        return sim

    calls = []
    fused = implicit_euler._WithPairs.matvec_alpha
    monkeypatch.setattr(implicit_euler._WithPairs, "matvec_alpha",
                        lambda self, *a: calls.append(1) or fused(self, *a))
    runs = []
    for whole in (False, True):
        if whole:  # (no fused path: the CG calls the product and takes its step length apart)
            monkeypatch.setattr(implicit_euler._WithPairs, "matvec_alpha", lambda self, *a: None)
        sim = two_stacks()
        iterations = []
        for _ in range(6):
            report = sim.step()
            iterations.append([c.iterations.tolist() for c in report.cg])
        runs.append((sim.x.clone(), iterations))
    assert calls, "the fused product with the pairs did not run"
    assert any(len(set(solve)) > 1 for step in runs[0][1] for solve in step)  # the runs stop apart
    assert runs[0][1] == runs[1][1]
    torch.testing.assert_close(runs[0][0], runs[1][0], rtol=0, atol=1e-12)


def test_a_pair_the_solve_closes_joins_the_step():
    """Two blocks falling together at 1 m/s, 0.1 mm apart, the lower one on the floor: no pair is
    closing at the step's start (the same velocities), but the floor stops the lower block in the
    step and the upper one runs into it. The step is solved again with that pair: the upper
    block stops within the penalty's depth instead of most of its 5 mm travel inside the lower."""
    sim = falling_pair(tm.Contact())
    assert len(sim.body_contact.detect(sim.x, sim.v, sim.options.dt)) == 0
    start = sim.v.clone()
    report = sim.step()
    assert float(report.contact.body_penetration.max()) < 0.1 * 1.0 * sim.options.dt
    assert len(report.cg) > 1  # solved again
    # Contact(rounds=0): the pairs of the step's start only, one solve, the upper block inside
    once = falling_pair(tm.Contact(rounds=0))
    once.v = start
    alone = once.step()
    assert len(alone.cg) == 1
    assert float(once.interpenetration().max()) > 0.3 * 1.0 * sim.options.dt


def test_a_miss_within_the_tolerance_is_left_to_the_next_step():
    """The scene above with Contact(tolerance) past the depth the missed pair would reach: the
    step is solved once, as with rounds=0, bit for bit (its solve paused at check_tol for the
    check, which found nothing, and went on to cg_tol); the next step finds the pair in contact
    (its start's gap negative) and the penalty pushes the block out over the steps after. The
    default tolerance is 1/400 of the search."""
    default = falling_pair(tm.Contact())
    assert default.body_contact.tolerance == pytest.approx(default.body_contact.search / 400)
    assert len(default.step().cg) > 1
    lenient, once = falling_pair(tm.Contact(tolerance=0.01)), falling_pair(tm.Contact(rounds=0))
    assert lenient.body_contact.tolerance == 0.01
    assert len(lenient.step().cg) == 1
    once.step()
    assert torch.equal(lenient.x, once.x) and torch.equal(lenient.v, once.v)
    inside = float(lenient.interpenetration().max())
    assert 0.3 * 1.0 * 0.005 < inside < 0.01  # much of the 5 mm travel: within the tolerance, left for later
    lenient.step(25)  # the penalty pushes it out over the next steps (about 17 here)
    assert float(lenient.interpenetration().max()) < 0.05 * inside


def test_checks_read_solves_stopped_at_check_tol():
    """Contact(check_tol) (the default, 1e-2): a solve whose end a contact-set check reads pauses
    at check_tol; the step's last goes to cg_tol (after a check that found nothing, the paused
    solve goes on). The scene of the pair the solve closes, then the blocks in contact: every
    step ends converged to cg_tol, at the state of the steps solved to cg_tol throughout (the
    same pairs: the check sees a millimetre miss at a 1 % residual as at 1e-10)."""
    assert tm.Contact().check_tol == 1e-2
    loose, full = falling_pair(tm.Contact(), cg_tol=1e-10), falling_pair(tm.Contact(check_tol=None), cg_tol=1e-10)
    for step in range(6):
        report, reference = loose.step(), full.step()
        *checked, last = report.cg
        assert float(last.relative_residual.max()) <= 1e-10
        assert all(float(c.relative_residual.max()) <= 1e-2 for c in checked)
        if step == 0:  # the closing pair: a check, a round, and the last solve
            assert len(report.cg) > 1 and float(checked[0].relative_residual.max()) > 1e-8
            assert sum(int(c.iterations.max()) for c in report.cg) < sum(int(c.iterations.max()) for c in reference.cg)
        torch.testing.assert_close(loose.x, full.x, rtol=0, atol=1e-9)
        torch.testing.assert_close(loose.v, full.v, rtol=0, atol=1e-7)


def test_a_check_beside_the_resumed_solve_changes_nothing(monkeypatch):
    """On the GPU a step's first contact check, where the last step's found nothing, runs on a side
    stream beside the paused solve's next iterations, launched before it
    (``implicit_euler._check_beside``). Taken here on the CPU in the same order (the iterations
    first): the same states bit for bit and the same iterations, through a step whose check finds
    a pair (the iterations launched ahead are dropped, the round solves from the paused solution)
    and steps whose checks find nothing (the solve goes on after them)."""
    from tensormass_torch.solver import cg, implicit_euler

    plain, beside = falling_pair(tm.Contact()), falling_pair(tm.Contact())
    plain_reports = [plain.step() for _ in range(6)]
    ahead = []
    run_ahead = cg.CGSolver.run_ahead
    monkeypatch.setattr(implicit_euler, "_checks_beside", lambda x: True)
    monkeypatch.setattr(cg.CGSolver, "run_ahead", lambda self, *a, **k: ahead.append(self.paused) or run_ahead(self, *a, **k))
    for reference in plain_reports:
        report = beside.step()
        assert [c.iterations.tolist() for c in report.cg] == [c.iterations.tolist() for c in reference.cg]
    assert torch.equal(beside.x, plain.x) and torch.equal(beside.v, plain.v)
    assert len(plain_reports[0].cg) > 1 and ahead[0]  # the first step's check found the closing pair
    assert len(ahead) > 1 and all(ahead)  # later steps' checks too, each beside a paused solve


def pairs_by_vertex_and_body(pairs):
    """{(vertex node, other body): (the pair's four nodes, signed distance, weights)}."""
    return {(int(n[0]), int(o[1])): (n.tolist(), float(d), w)
            for n, o, d, w in zip(pairs.nodes, pairs.objects, pairs.signed, pairs.weights)}


@pytest.mark.parametrize("swept", [False, True])
def test_kept_candidates_hold_every_pair_a_fresh_search_finds(swept, monkeypatch):
    """Contact(skin): candidates found once for triangles grown by twice the skin are reused while
    the surface moves less than the skin (less the query's own motion): they hold every pair a
    fresh search finds, every pair within the reach is the fresh detection's, and a pair past
    it takes a triangle at least as near. One search serves the queries; a vertex moved by
    more than the skin makes a new one."""
    skin = 0.01
    kept, x, v = shaken_pile_contact(DT, "cpu", tm.Contact(skin=skin))
    fresh, _, _ = shaken_pile_contact(DT, "cpu", tm.Contact(skin=0.0))
    searches = []
    search = type(kept)._search
    monkeypatch.setattr(type(kept), "_search", lambda self, *a: searches.append(self) or search(self, *a))
    velocities, dt = (v, 0.005) if swept else (None, 0.0)
    gen = torch.Generator().manual_seed(3)
    for _ in range(5):  # each node within 1.4 mm of x; a swept query's own motion needs 6 mm of the skin
        y = x + 0.0008 * (2 * torch.rand(x.shape, generator=gen, dtype=DT) - 1)
        ours, theirs = kept.candidates(y, velocities, dt), fresh.candidates(y, velocities, dt)
        assert set(zip(*(t.tolist() for t in theirs))) <= set(zip(*(t.tolist() for t in ours)))
        assert len(ours[0]) > len(theirs[0]) > 100
        # the kept ones come by vertex, then triangle (a point query's order, which nearby's pairs
        # take without a sort of their own), even for a swept query
        key = ours[0] * len(kept.triangles) + ours[1]
        assert bool((key[1:] > key[:-1]).all())
        ours, theirs = (pairs_by_vertex_and_body(c.nearby(y, velocities, dt)[0]) for c in (kept, fresh))
        for key, (nodes, signed, weights) in theirs.items():
            if abs(signed) < fresh.reach:
                assert ours[key][0] == nodes and ours[key][1] == pytest.approx(signed, abs=1e-15)
                torch.testing.assert_close(ours[key][2], weights, rtol=0, atol=1e-15)
            elif key in ours:
                assert abs(ours[key][1]) <= abs(signed) + 1e-15
        assert all(key in theirs for key, (_, signed, _) in ours.items() if abs(signed) < fresh.reach)
    assert len([c for c in searches if c is kept]) == 1
    far = x.clone()
    far[kept.vertices[0]] += 2 * skin
    kept.candidates(far, velocities, dt)
    assert len([c for c in searches if c is kept]) == 2


def test_a_pile_with_kept_candidates_steps_as_without():
    """Two blocks falling onto each other and a floor, with Contact(skin) (the default, 1/10 of
    the search, and 5 mm) and without (0): the same states (to rounding: the pairs' order within
    a vertex may differ), in fewer searches."""
    runs = []
    for skin in (0.0, None, 0.005):
        sim = falling_pair(tm.Contact(skin=skin))
        searches = []
        search = sim.body_contact._search
        sim.body_contact._search = lambda *a, searches=searches, search=search: searches.append(1) or search(*a)
        sim.step(20)
        runs.append((sim.x.clone(), len(searches), sim.body_contact.skin))
    assert runs[0][2] == 0.0 and runs[1][2] == pytest.approx(sim.body_contact.search / 10) and runs[2][2] == 0.005
    for kept in runs[1:]:
        torch.testing.assert_close(kept[0], runs[0][0], rtol=0, atol=1e-10)
        assert kept[1] < runs[0][1] / 2


@pytest.mark.parametrize("swept", [False, True])
def test_checks_take_the_step_search_candidates_where_the_solve_kept_near_the_prediction(swept):
    """Contact(check_margin): a step's start search grows its triangles by twice the margin and
    keeps its candidates; a check at x + dx takes them for the bodies whose surface vertices all
    ended within the margin of where the step's velocities put them (x + dt v; x where the search
    is not swept), and searches again for the pairs of the others among the bodies near them.
    Together they hold every candidate of a fresh search at x + dx and give its pairs, bit for
    bit, in its order; where the bodies that moved off reach half the surfaces, None (a fresh
    search)."""
    dt = 0.005
    contact, x, v = shaken_pile_contact(DT, "cpu", tm.Contact(swept=swept, skin=0.0))
    fresh, _, _ = shaken_pile_contact(DT, "cpu", tm.Contact(swept=swept, check_margin=0.0, skin=0.0))
    margin = contact.check_margin
    assert margin == pytest.approx(contact.search / 16) and fresh.check_margin == 0.0
    assert shaken_pile_contact(DT, "cpu", tm.Contact(swept=swept))[0].check_margin == 0.0  # a skin serves the checks
    start, fresh_start = contact.nearby(x, v, dt), fresh.nearby(x, v, dt)  # the step's start: the same pairs
    assert torch.equal(start[0].nodes, fresh_start[0].nodes) and torch.equal(start[1], fresh_start[1])
    assert fresh._step_search is None
    predicted = x + dt * v if swept else x
    gen = torch.Generator().manual_seed(5)
    block = contact.node_object == 7  # the top block of a column: it and 3 others within its reach
    for off_bodies in (0, 1):  # every body within the margin; one (block 7) 2.5 margins off
        for _ in range(2):
            end = predicted + 0.99 * margin * (2 * torch.rand(x.shape, generator=gen, dtype=DT) - 1)
            end[block] += 2.5 * margin * off_bodies
            found = contact._step_candidates(x, end - x)
            assert found is not None and len(found) == 1 + off_bodies
            theirs = set(zip(*(t.tolist() for t in fresh.candidates(end))))
            ours = [set(zip(*(t.tolist() for t in run[:2]))) for run in found]
            assert theirs <= set().union(*ours)
            if off_bodies:  # the kept ones leave block 7's pairs to the search again
                assert found[0][2].tolist() == [b == 7 for b in range(8)] and found[1][2] is None
                assert all(contact.triangle_object[t] == 7 or contact.vertex_object[v] == 7 for v, t in ours[1])
            pairs, reference = contact.nearby(end, found=found)[0], fresh.nearby(end)[0]
            assert len(reference) > 50 and bool((reference.objects == 7).any())
            for field in ("nodes", "weights", "direction", "signed", "gap", "objects"):
                assert torch.equal(getattr(pairs, field), getattr(reference, field)), field
    assert contact._step_candidates(x, end + 2.5 * margin - x) is None  # every body off
    assert contact._step_candidates(x.clone(), predicted - x) is None  # another state's


@pytest.mark.parametrize("swept", [False, True])
def test_a_later_check_takes_the_first_checks_search(swept):
    """_step_candidates(later=True): a check whose bodies past the margin have their neighbourhood
    searched grows that search by 4 margins and keeps it; a later check of the step whose bodies
    past the margin were all past at the first, and moved at most 2 margins since, takes it with
    no search and finds a fresh search's pairs bit for bit; a body past the margin only at the
    later check, or one that moved further, takes a search of its own, and a check without
    ``later`` keeps nothing. (Two piles of 8 blocks 0.5 m apart: block 7's grown neighbourhood is
    under half the surfaces.)"""
    dt = 0.005
    contact, x, v = shaken_pile_contact(DT, "cpu", tm.Contact(swept=swept, skin=0.0), rows=2)
    fresh, _, _ = shaken_pile_contact(DT, "cpu", tm.Contact(swept=swept, check_margin=0.0, skin=0.0), rows=2)
    margin = contact.check_margin
    contact.nearby(x, v, dt)
    searches = []
    search = contact._search
    contact._search = lambda *a, **k: searches.append(a[3] if len(a) > 3 else None) or search(*a, **k)
    predicted = x + dt * v if swept else x
    gen = torch.Generator().manual_seed(7)

    def ends(shifts):  # every body within half a margin of its prediction, but those shifted
        end = predicted + 0.49 * margin * (2 * torch.rand(x.shape, generator=gen, dtype=DT) - 1)
        for body, shift in shifts.items():
            end[contact.node_object == body] += shift * margin
        return end

    def check(end, later):
        found = contact._step_candidates(x, end - x, later)
        pairs, reference = contact.nearby(end, found=found)[0], fresh.nearby(end)[0]
        assert bool((reference.objects == 7).any())
        for field in ("nodes", "weights", "direction", "signed", "gap", "objects"):
            assert torch.equal(getattr(pairs, field), getattr(reference, field)), field
        return found

    found = check(ends({7: 2.5}), later=True)  # block 7 past: its neighbourhood searched, grown
    assert len(searches) == 1 and len(found) == 2 and found[0][2].tolist() == [b == 7 for b in range(16)]
    assert 0 < int(searches[0].sum()) < 8  # within its own pile
    for shifts in ({7: 3.5}, {7: 1.5}, {}):  # block 7 moved at most 2 margins: the kept search serves
        found = check(ends(shifts), later=False)
        assert len(searches) == 1 and len(found) == 1 + bool(shifts)
    check(ends({7: 2.5, 1: 2.5}), later=False)  # block 1 past only now: searched (and nothing kept)
    assert len(searches) == 2 and contact._check_search is None
    check(ends({7: 2.5}), later=True)
    check(ends({7: 5.5}), later=False)  # block 7 more than 2 margins from the first check: searched
    assert len(searches) == 4 and contact._check_search is None
    check(ends({7: 2.5}), later=True)
    contact.nearby(x, v, dt)  # a new start search: the checks' kept search goes with the old one
    assert contact._check_search is None


def test_the_kept_step_search_holds_no_autograd_graph():
    """A differentiable step's positions require grad: what the start search keeps for the checks
    (the predicted positions) and what a check computes from it carry no graph."""
    contact, x, v = shaken_pile_contact(DT, "cpu", tm.Contact(skin=0.0))
    x = x.clone().requires_grad_(True)
    contact.nearby(x, v, 0.005)
    assert contact._step_search[2].grad_fn is None and not contact._step_search[2].requires_grad
    found = contact._step_candidates(x, 0.005 * v)
    assert found is not None and all(not t.requires_grad for run in found for t in run if t is not None)


def test_a_pile_whose_checks_take_the_step_search_steps_as_with_searches():
    """Two blocks falling onto each other and a floor without a skin, the checks taking the step's
    candidates (the default check_margin) or searching on their own (0): the same states bit for
    bit, in fewer searches. The first step's floor stops the lower block (5 mm from where its
    velocity put it): that check searches."""
    runs = []
    for margin in (0.0, None):
        sim = falling_pair(tm.Contact(check_margin=margin, skin=0.0))
        searches, taken = [], []
        search, step_candidates = sim.body_contact._search, sim.body_contact._step_candidates
        sim.body_contact._search = lambda *a: searches.append(1) or search(*a)
        sim.body_contact._step_candidates = lambda *a: (lambda found: taken.append(found is not None) or found)(
            step_candidates(*a))
        sim.step(20)
        runs.append((sim.x.clone(), sim.v.clone(), len(searches), taken))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert not any(runs[0][3]) and runs[1][3][0] is False and sum(runs[1][3]) >= len(runs[1][3]) - 2
    assert runs[1][2] <= runs[0][2] - sum(runs[1][3])


def test_a_rounds_solve_is_checked_again_for_deep_misses_only():
    """Contact(recheck_tolerance): the step's first solve is checked at the tolerance, a round's
    solve at the recheck tolerance (by default 1/100 of the search, 4 times the tolerance): the
    closing pair's step checks its first solve, takes a round, and checks that round's solve at
    the larger tolerance. Deep misses still take the round: the 6 m/s block of
    test_a_body_faster_than_the_search_per_step_does_not_go_through bounces off at the defaults
    (with one round it stays inside the held block)."""
    sim = falling_pair(tm.Contact())
    contact = sim.body_contact
    assert contact.recheck_tolerance == pytest.approx(contact.search / 100) == pytest.approx(4 * contact.tolerance)
    tolerances = []
    relinearise = contact.relinearise
    contact.relinearise = lambda *a, **k: tolerances.append(k["tolerance"]) or relinearise(*a, **k)
    assert len(sim.step().cg) == 2
    assert tolerances == [contact.tolerance, contact.recheck_tolerance]
    assert falling_pair(tm.Contact(recheck_tolerance=1e-9)).body_contact.recheck_tolerance == contact.tolerance


@pytest.mark.parametrize("recheck", [0.0, -1e-3, float("nan"), "0.01", True])
def test_contact_recheck_tolerance_must_be_positive(recheck):
    with pytest.raises(tm.SceneError, match="contact recheck_tolerance must be a positive finite number or None"):
        tm.Contact(recheck_tolerance=recheck)


@pytest.mark.parametrize("margin", [-1e-3, float("nan"), float("inf"), "0.01", True])
def test_contact_check_margin_must_be_non_negative(margin):
    with pytest.raises(tm.SceneError, match="contact check_margin must be a non-negative finite number or None"):
        tm.Contact(check_margin=margin)


@pytest.mark.parametrize("skin", [-1e-3, float("nan"), float("inf"), "0.01", True])
def test_contact_skin_must_be_non_negative(skin):
    with pytest.raises(tm.SceneError, match="contact skin must be a non-negative finite number or None"):
        tm.Contact(skin=skin)


@pytest.mark.parametrize("check_tol", [0.0, 1.0, -1e-3, float("nan"), "0.01", True])
def test_contact_check_tol_must_be_in_zero_one(check_tol):
    with pytest.raises(tm.SceneError, match=r"contact check_tol must be a number in \(0, 1\) or None"):
        tm.Contact(check_tol=check_tol)


@pytest.mark.parametrize("tolerance", [0.0, -1e-3, float("nan"), "0.1", True])
def test_contact_tolerance_must_be_positive(tolerance):
    with pytest.raises(tm.SceneError, match="contact tolerance must be a positive finite number or None"):
        tm.Contact(tolerance=tolerance)


@pytest.mark.parametrize("rounds", [-1, 2.0, True, None])
def test_contact_rounds_must_be_a_non_negative_integer(rounds):
    with pytest.raises(tm.SceneError, match="contact rounds must be a non-negative integer"):
        tm.Contact(rounds=rounds)


def test_pairs_relinearised_where_the_step_ends(overlapping):
    """After a motion dx that turns one body and presses it on (a pair's fixed triangle, closest
    point and direction then miss the surfaces' turn), every vertex in contact at x + dx has an
    active pair whose model g + u . J dx is at most the tolerance shallower than its gap there,
    one pair per (vertex, body), and a re-linearised pair's model is exact at dx."""
    contact, x = overlapping
    near, active = contact.nearby(x)
    second = contact.node_object == 1
    centre = x[second].mean(0)
    turn = torch.linalg.matrix_exp(torch.tensor([[0.0, 0.0, -0.15], [0.0, 0.0, 0.0], [0.15, 0.0, 0.0]], dtype=DT))
    dx = torch.zeros_like(x)
    dx[second] = (x[second] - centre) @ turn.T + centre + torch.tensor([0.0, 0.0, -0.01], dtype=DT) - x[second]
    end = contact.detect(x + dx)
    at_end = {(int(n), int(o)): float(g) for n, o, g in zip(end.nodes[:, 0], end.objects[:, 1], end.gap)}

    def models(pairs, mask):
        return {(int(n), int(o)): float(g) for n, o, g in
                zip(pairs.nodes[mask, 0], pairs.objects[mask, 1], pairs.end_gap(dx)[mask])}

    def shallower(model):  # by how much the models miss the deepest vertex at the end (none: no force)
        return max(min(model.get(key, math.inf), 0.0) - gap for key, gap in at_end.items())

    assert len(end) >= 8 and shallower(models(near, active)) > 5 * contact.tolerance
    pairs, active, changed = contact.relinearise(x, dx, near, active)
    assert changed and shallower(models(pairs, active)) <= contact.tolerance
    assert (pairs.nodes[:, 0] * contact.num_objects + pairs.objects[:, 1]).unique().numel() == len(pairs)
    def rows(p):
        return torch.cat([p.nodes.to(DT), p.weights, p.direction, p.gap[:, None]], dim=1)

    fresh = ~(rows(pairs)[:, None, :] == rows(near)[None]).all(-1).any(1)
    assert bool(fresh.any()) and bool(active[fresh].all())
    for key, gap in models(pairs, fresh).items():
        assert abs(gap - at_end[key]) < 1e-12


def block_on_a_slab(theta_deg, friction, steps=125, dt=2e-3, friction_velocity=1e-3):
    """A soft 0.1 m cube resting on a stiff slab held at its base, gravity tilted by theta from
    the slab's normal: the cube's mass-weighted mean velocity along the slope at each step [steps]."""
    theta = math.radians(theta_deg)
    slab = tm.beam_mesh(4, 4, 1, size=(0.4, 0.4, 0.05), dtype=DT)
    cube = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), origin=(0.1, 0.15, 0.05), dtype=DT)
    bodies = [tm.Body(slab, tm.Material(young=1e7, poisson=0.3, density=1000), fixed=slab.vertices[:, 2] < 1e-9),
              tm.Body(cube, tm.Material(young=1e6, poisson=0.3, density=1000))]
    sim = tm.Simulator(bodies, dt=dt, gravity=(9.81 * math.sin(theta), 0.0, -9.81 * math.cos(theta)), dtype=DT,
                       contact=Contact(friction=friction, friction_velocity=friction_velocity), cg_tol=1e-10)
    cube_nodes = slice(slab.num_vertices, None)
    mass = sim.system.mass[cube_nodes, 0]
    speeds = []
    for _ in range(steps):
        sim.step()
        speeds.append(float((mass * sim.v[cube_nodes, 0]).sum() / mass.sum()))
    return torch.tensor(speeds, dtype=DT)


@pytest.mark.parametrize("theta, friction", [(40, 0.5), (30, 0.3), (40, 0.0)])
def test_a_block_slides_down_a_slope_at_coulombs_acceleration(theta, friction):
    """Past the friction angle (tan theta > mu) the block slides at g (sin theta - mu cos theta)."""
    dt = 2e-3
    speeds = block_on_a_slab(theta, friction, dt=dt)
    first = 25  # past the first steps, where the normal force builds up
    measured = float(speeds[-1] - speeds[first]) / ((len(speeds) - 1 - first) * dt)
    coulomb = 9.81 * (math.sin(math.radians(theta)) - friction * math.cos(math.radians(theta)))
    assert abs(measured - coulomb) < 0.05 * coulomb, (measured, coulomb)


def test_a_block_below_the_friction_angle_sticks():
    """tan theta < mu: the block stays, creeping slower than the regularisation's slip speed
    (frictionless, it would be moving at g sin theta t ~ 0.8 m/s by the end)."""
    speeds = block_on_a_slab(20, 0.5, friction_velocity=1e-3)
    assert float(speeds[-25:].abs().max()) < 1e-3


def test_friction_forces_conserve_linear_momentum_and_oppose_the_slip(overlapping):
    contact, x = overlapping
    pairs = contact.detect(x)
    pairs.friction = torch.full((len(pairs),), 20.0, dtype=DT)
    v = torch.randn(x.shape, dtype=DT, generator=torch.Generator().manual_seed(5))
    forces = pairs.friction_forces(v)
    assert float(forces.abs().max()) > 1e-3
    assert float(forces.sum(0).abs().max()) < 1e-12 * float(forces.abs().sum())
    assert float((forces * v).sum()) < 0  # it dissipates: negative power
    # with friction set, detection computes it from the slip: mu k max(0, -g) / max(|v_t|, eps_v)
    rubbing = SurfaceContact(contact.triangles, contact.node_object, contact.rest,
                             dataclasses.replace(contact.settings, friction=0.4))
    found = rubbing.detect(x, v, 1e-3)
    assert found.friction is not None and bool((found.friction >= 0).all())
    assert bool((found.friction[found.gap >= 0] == 0).all()) and float(found.friction.max()) > 0


def test_coupled_ranges():
    class Pairs:
        def __init__(self, objects):
            self.objects = torch.tensor(objects, dtype=torch.int64).reshape(-1, 2)

        def __len__(self):
            return self.objects.shape[0]

    assert coupled_ranges(Pairs([]), 4) == [0, 1, 2, 3, 4]
    assert coupled_ranges(Pairs([[1, 2]]), 4) == [0, 1, 3, 4]
    assert coupled_ranges(Pairs([[3, 0]]), 5) == [0, 4, 5]
    assert coupled_ranges(Pairs([[0, 1], [2, 3], [3, 2]]), 5) == [0, 2, 4, 5]


def test_a_body_alone_has_no_self_contact_at_rest():
    """Self-contact leaves out a vertex's neighbourhood at rest; a body folded onto itself meets itself."""
    strip = tm.beam_mesh(12, 2, 1, size=(1.2, 0.2, 0.1), dtype=DT)
    triangles = boundary_faces(strip.elements)
    objects = torch.zeros(strip.num_vertices, dtype=torch.int64)
    contact = SurfaceContact(triangles, objects, strip.vertices, Contact(self_contact=True, thickness=0.01))
    assert len(contact.detect(strip.vertices)) == 0
    # fold: the far half turned over onto the near half, 0.105 above it (inside the thickness)
    x = strip.vertices.clone()
    far = x[:, 0] > 0.6
    x[far, 0] = 1.2 - x[far, 0]
    x[far, 2] = 0.205 - x[far, 2]
    pairs = contact.detect(x)
    assert len(pairs) > 0
    assert bool(((x[pairs.nodes[:, 0], 0] < 0.6) | (strip.vertices[pairs.nodes[:, 0], 0] > 0.6)).all())
    without = SurfaceContact(triangles, objects, strip.vertices, Contact(self_contact=False, thickness=0.01))
    assert len(without.detect(x)) == 0


@pytest.mark.parametrize("kwargs, word", [
    (dict(stiffness=-1.0), "stiffness"), (dict(stiffness=float("nan")), "stiffness"),
    (dict(thickness=-0.1), "thickness"), (dict(search=0.0), "search"), (dict(self_contact="yes"), "self_contact"),
    (dict(tangent="wrong"), "tangent"), (dict(friction=-0.1), "friction"),
    (dict(friction=float("inf")), "friction"), (dict(friction_velocity=0.0), "friction_velocity"),
    (dict(swept=1), "swept"),
])
def test_bad_contact_settings_raise_one_clear_error(kwargs, word):
    with pytest.raises(tm.SceneError, match=word):
        tm.Contact(**kwargs)


def test_the_simulator_rejects_a_bad_contact():
    body = tm.Body(tm.beam_mesh(1, 1, 1), tm.Material(young=1e4, poisson=0.3, density=1000))
    with pytest.raises(tm.SceneError, match="contact must be a tm.Contact"):
        tm.Simulator([body], contact={"stiffness": 1e3})
    tri = tm.Body(tm.beam_tri_mesh(2, 2), tm.Material(young=1e4, poisson=0.3, density=1000))
    with pytest.raises(tm.SceneError, match="tetrahedral"):
        tm.Simulator([tri], contact=tm.Contact())


def test_without_contact_the_report_has_no_body_contact():
    body = tm.Body(tm.beam_mesh(2, 1, 1), tm.Material(young=1e4, poisson=0.3, density=1000))
    sim = tm.Simulator([body], tools=[tm.Sphere(0.1, position=(5.0, 0, 0))])
    report = sim.step()
    assert sim.body_contact is None and report.contact.body_contacts.tolist() == [0]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    _, rest, triangles, objects = two_blocks(seed=4)
    cpu = SurfaceContact(triangles, objects, rest, Contact(stiffness=3e3, thickness=0.01))
    gpu = cpu.to(device="cuda")
    a, b = cpu.detect(rest), gpu.detect(rest.cuda())
    assert torch.equal(a.nodes, b.nodes.cpu())
    torch.testing.assert_close(a.forces(), b.forces().cpu(), rtol=1e-9, atol=1e-9)  # FMA on the device
    dx = torch.randn(rest.shape, dtype=DT)
    torch.testing.assert_close(a.dforces(dx), b.dforces(dx.cuda()).cpu(), rtol=1e-9, atol=1e-9)
    # deterministic on the device: the same bits twice
    assert torch.equal(b.forces(), gpu.detect(rest.cuda()).forces())


def test_a_step_after_one_whose_check_found_pairs_skips_the_settled_test():
    """SurfaceContact.first_check_found: after a step whose first contact-set check found pairs,
    the next step goes straight to its check without the settled test (which only skips a check
    that would find nothing): the states are those of steps that test every time, bit for bit,
    in fewer tests; a step whose check found nothing tests again."""
    from tensormass_torch.physics import body_contact as bc

    runs = []
    for always in (True, False):
        sim = falling_pair(tm.Contact())
        tests = []
        settled = sim.body_contact.settled
        sim.body_contact.settled = lambda *a: tests.append(1) or settled(*a)
        for _ in range(40):
            if always:
                sim.body_contact.first_check_found = False
            sim.step()
        runs.append((sim.x, sim.v, len(tests)))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])
    assert runs[1][2] < runs[0][2] <= 40
    sim.body_contact.first_check_found = True  # another contact's steps start afresh
    assert bc.SurfaceContact.with_values(sim.body_contact, stiffness=2e5).first_check_found is False


def test_the_settled_test_waits_after_failures_and_changes_no_step(monkeypatch):
    """SurfaceContact.settled_if_due: after settled tests that failed in a row the next waits 1, 2,
    4, ... steps (at most ``settled_wait``, SETTLED_WAIT by default) and a test that passes makes
    the next due at once; a block landing on another, then resting, steps bit for bit as when the
    test runs at every step, in fewer tests."""
    from tensormass_torch.physics import body_contact as bc

    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    stacked = [tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.11 * i), dtype=DT) for i in range(2)]

    def run(wait: int):
        sim = tm.Simulator([tm.Body(m, material) for m in stacked], dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)],
                           contact=tm.Contact(friction=0.5), rayleigh_mass=2.0, dtype=DT)
        sim.body_contact.settled_wait = wait
        calls = []
        original = bc.SurfaceContact.settled
        monkeypatch.setattr(bc.SurfaceContact, "settled", lambda self, *a: calls.append(original(self, *a)) or calls[-1])
        sim.step(200)
        monkeypatch.setattr(bc.SurfaceContact, "settled", original)
        return sim, calls

    wait = bc.SETTLED_WAIT
    assert wait == 8
    waited, tested = run(wait)
    every, all_tested = run(0)
    assert torch.equal(waited.x, every.x) and torch.equal(waited.v, every.v)
    assert len(all_tested) == 200 and not all(all_tested) and all(all_tested[-100:])
    assert len(tested) < len(all_tested) and all(tested[-100:])
    # the waits: tests that fail at steps 0, 2, 5, 10, 19 (waits 1, 2, 4, 8), then pass at each step
    surface = waited.body_contact

    def steps(answers, count):  # (the steps whose test ran, the steps found settled)
        surface._settled_failures = surface._settled_left = 0
        ran = []
        monkeypatch.setattr(bc.SurfaceContact, "settled", lambda self, *a: ran.append(step) or answers[len(ran) - 1])
        settled = []
        for step in range(count):
            if surface.settled_if_due(None, None, None, None):
                settled.append(step)
        return ran, settled

    assert steps([False] * 5 + [True] * 4, 32) == ([0, 2, 5, 10, 19, 28, 29, 30, 31], [28, 29, 30, 31])
    assert steps([False] * 7, 46) == ([0, 2, 5, 10, 19, 28, 37], [])  # the wait stays at settled_wait
    surface.settled_wait = 0
    assert steps([False] * 3 + [True], 4) == ([0, 1, 2, 3], [3])


def test_settled_steps_skip_the_contact_sets_check_exactly():
    """Where the bodies' motion provably leaves nothing for the contact set's check to find
    (SurfaceContact.settled: bodies far apart, or resting on each other), its detection is
    skipped, and the steps are those of the check run in full, bit for bit; a motion that closes
    a gap, or slides a vertex along a pair, is not settled."""
    from tensormass_torch.physics import body_contact as bc

    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    apart = [tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(0.4 * i, 0.0, 0.05 + 0.1 * i), dtype=DT)
             for i in range(3)]
    stacked = [tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.11 * i), dtype=DT) for i in range(2)]

    def run(meshes, skip: bool, steps: int):
        sim = tm.Simulator([tm.Body(m, material) for m in meshes], dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)],
                           contact=tm.Contact(), rayleigh_mass=20.0, dtype=DT)
        calls = []
        original = bc.SurfaceContact.settled

        def settled(self, x, dx, pairs, active):
            calls.append(original(self, x, dx, pairs, active))
            return calls[-1] if skip else False

        bc.SurfaceContact.settled = settled
        try:
            solves = [len(sim.step().cg) for _ in range(steps)]
        finally:
            bc.SurfaceContact.settled = original
        return sim, solves, calls

    skipped, solves, calls = run(apart, True, 30)
    full, _, _ = run(apart, False, 30)
    assert len(calls) == 30 and all(calls)  # every step: nothing near, and it was skipped
    assert solves == [1] * 30
    assert torch.equal(skipped.x, full.x) and torch.equal(skipped.v, full.v)
    # a block dropped 1 cm onto another (heavily damped): settled once both are still
    skipped, _, calls = run(stacked, True, 200)
    full, _, _ = run(stacked, False, 200)
    assert len(skipped.body_contact.detect(skipped.x)) > 0  # in contact
    assert not all(calls) and all(calls[-20:])  # the upper block lands (1 cm), then both are still
    assert torch.equal(skipped.x, full.x) and torch.equal(skipped.v, full.v)
    # motions that are not settled: one block onto another across the gap; a vertex sliding
    surface = skipped.body_contact
    x = skipped.x.clone()
    near, active = surface.nearby(x)
    dx = torch.zeros_like(x)
    assert surface.settled(x, dx, near, active)
    dx[skipped.ptr[1]:, 2] = -0.01  # the upper block 1 cm into the lower
    assert not surface.settled(x, dx, near, active)
    far, _, _ = run(apart, True, 1)
    x = far.x.clone()
    empty, none_active = far.body_contact.nearby(x)
    dx = torch.zeros_like(x)
    dx[far.ptr[1]:far.ptr[2], 0] = -0.4  # body 1 onto body 0
    assert not far.body_contact.settled(x, dx, empty, none_active)
