"""The rigid bodies' coarse correction (solver.rigid_modes, ``preconditioner="rigid"``): its coarse
matrix against the dense Galerkin product Z^T A Z of the step's probed operator (float64), its
groups' principal blocks, the preconditioner symmetric positive definite, fewer iterations on a
tower, and bad input (the step against the plain one: test_preconditioner)."""
import pytest
import torch
from conftest import group_meshes
from test_preconditioner import loaded_step_with_pairs, two_blocks_in_contact

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.solver import rigid_modes as rigid_modes_module
from tensormass_torch.solver.cg import CGSolver
from tensormass_torch.solver.implicit_euler import _coefficients
from tensormass_torch.solver.preconditioner import BlockJacobi, JacobiScaling, system_diagonal_blocks
from tensormass_torch.solver.rigid_modes import (
    BodySums,
    RigidModeCorrection,
    contact_clusters,
    contact_groups,
    group_matrices,
    lever_arms,
    modes_of,
    morton_groups,
    own_blocks,
    rigid_modes,
)

DT = torch.float64


def dense(product, size):
    """The matrix ``[size, size]`` of a linear map on flat vectors."""
    eye = torch.eye(size, dtype=DT)
    return torch.stack([product(eye[i]) for i in range(size)], 1)


def step_pieces(friction=0.0, velocities=True):
    """The two blocks' step: (sim, loaded product, pairs, pairs' product, node weights c_M m I + c_K N)."""
    sim, loaded, pairs, stiffness = loaded_step_with_pairs(friction, 3 if velocities else None)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    weights = (mass_coef * sim.system.mass)[:, :, None] * torch.eye(3, dtype=DT) + stiffness_coef * loaded.node_stiffness
    return sim, loaded, pairs, stiffness, weights


def coarse_reference(sim, loaded, stiffness, modes):
    """Z^T (c_M M + c_K N + the pairs' part) Z ``[6 B, 6 B]`` (body-major) from the probed
    operator without elasticity."""
    mass_coef, stiffness_coef = _coefficients(sim.options)
    shape = sim.x.shape

    def without_elasticity(flat):
        p = flat.view(shape)
        nodes = mass_coef * sim.system.mass * p + stiffness_coef * (loaded.node_stiffness @ p[:, :, None])[:, :, 0]
        return (nodes + stiffness(p)).reshape(-1)

    operator = dense(without_elasticity, shape.numel())
    bodies = sim.system.segments.num_objects
    z = torch.zeros(shape.numel(), 6 * bodies, dtype=DT)
    for b in range(bodies):
        rows = (sim.system.segments.node_object == b).repeat_interleave(3)
        for k in range(6):
            z[rows, 6 * b + k] = modes[k].reshape(-1)[rows]
    return z.T @ operator @ z


@pytest.mark.parametrize("friction", [0.0, 0.4])
@pytest.mark.parametrize("fixed", [False, True])
def test_the_coarse_matrix_is_the_galerkin_product(friction, fixed):
    """One group of both bodies: E equals Z^T A Z without elasticity (mass, floor and its
    friction, the pairs and theirs) to roundoff, in the groups' slot order; with every third
    node fixed (Z zero there), of the masked modes."""
    sim, loaded, pairs, stiffness, weights = step_pieces(friction)
    sums = BodySums(sim.system.segments, sim.x)
    modes, centres = rigid_modes(sim.x, sim.system.mass.reshape(-1), sums)
    free = None
    if fixed:
        free = torch.ones(sim.x.shape[0], 1, dtype=DT)
        free[::3] = 0.0
        modes = modes * free
    group, slot, groups = morton_groups(centres, 2)
    assert groups == 1 and sorted(slot.tolist()) == [0, 1]
    mass_coef, stiffness_coef = _coefficients(sim.options)
    arms = lever_arms(sim.x, sim.system.mass.reshape(-1), sums)[0]
    matrices = group_matrices(own_blocks(arms, weights, sums, free), arms, group, slot, groups, 2, pairs,
                              pairs._pair_matrices(stiffness_coef, sim.options.dt), free)
    reference = coarse_reference(sim, loaded, stiffness, modes)
    order = torch.argsort(slot)
    index = torch.cat([torch.arange(6) + 6 * int(b) for b in order])
    torch.testing.assert_close(matrices[0], reference[index][:, index], rtol=1e-10, atol=1e-10 * float(reference.abs().max()))
    coupling = reference[:6, 6:]
    assert float(coupling.abs().max()) > 1e-3 * float(reference.abs().max())  # the pairs join the bodies


def test_groups_keep_their_principal_blocks():
    """Groups of one body: each body's own block of the whole E (its pairs' diagonal terms kept,
    their coupling dropped)."""
    sim, loaded, pairs, stiffness, weights = step_pieces()
    sums = BodySums(sim.system.segments, sim.x)
    modes, centres = rigid_modes(sim.x, sim.system.mass.reshape(-1), sums)
    group, slot, groups = morton_groups(centres, 1)
    assert groups == 2 and slot.tolist() == [0, 0]
    mass_coef, stiffness_coef = _coefficients(sim.options)
    arms = lever_arms(sim.x, sim.system.mass.reshape(-1), sums)[0]
    matrices = group_matrices(own_blocks(arms, weights, sums), arms, group, slot, groups, 1, pairs,
                              pairs._pair_matrices(stiffness_coef, sim.options.dt))
    reference = coarse_reference(sim, loaded, stiffness, modes)
    for b in range(2):
        torch.testing.assert_close(matrices[int(group[b])], reference[6 * b:6 * b + 6, 6 * b:6 * b + 6],
                                   rtol=1e-10, atol=1e-10 * float(reference.abs().max()))


class _Pairs:
    """The part of ``ContactPairs`` that ``group_matrices`` reads: nodes [P, 4] (vertex, triangle),
    the bodies [P, 2] (vertex's, triangle's) and the coefficients [P, 4] (1, -w)."""

    def __init__(self, nodes, objects, weights):
        self.nodes, self.objects, self.weights = nodes, objects, weights

    def __len__(self):
        return self.nodes.shape[0]

    def _coefficients(self):
        return torch.cat([torch.ones_like(self.weights[:, :1]), -self.weights], 1)


@pytest.mark.parametrize("size", [1, 2, 3])
def test_group_matrices_equal_the_dense_sum_over_pairs(size):
    """Five bodies in groups of ``size``, pairs in both orientations, repeated pairs of bodies,
    self-contact and pairs between groups: E's principal blocks over the groups = the dense sum
    over the pairs of (V + T)^T M_p (V + T) placed at the bodies' blocks (float64), the coupling of
    two groups dropped and their own terms kept."""
    g = torch.Generator().manual_seed(4)
    lengths = [4, 3, 5, 4, 3]
    segments = Segments.from_lengths(lengths)
    bodies, v = len(lengths), sum(lengths)
    arms = torch.randn(v, 3, generator=g, dtype=DT)
    free = (torch.rand(v, 1, generator=g, dtype=DT) > 0.2).to(DT)
    body_pairs = [(0, 1), (1, 0), (0, 1), (2, 2), (3, 4), (4, 1), (2, 3), (1, 1), (4, 3), (0, 4)]
    first = segments.ptr.tolist()

    def node_of(b):
        return first[b] + int(torch.randint(lengths[b], (1,), generator=g))

    nodes = torch.tensor([[node_of(a), node_of(b), node_of(b), node_of(b)] for a, b in body_pairs])
    objects = torch.tensor(body_pairs)
    pairs = _Pairs(nodes, objects, torch.rand(len(body_pairs), 3, generator=g, dtype=DT))
    half = torch.randn(len(body_pairs), 3, 3, generator=g, dtype=DT)
    pair_matrices = half @ half.transpose(1, 2)
    half = torch.randn(bodies, 6, 6, generator=g, dtype=DT)
    own = half @ half.transpose(1, 2)
    group, slot, groups = morton_groups(torch.randn(bodies, 3, generator=g, dtype=DT), size)
    matrices = group_matrices(own, arms, group, slot, groups, size, pairs, pair_matrices, free)
    whole = torch.block_diag(*own)  # [6 B, 6 B]
    modes = (modes_of(arms) * free).permute(1, 2, 0)  # [V, 3, 6]
    for p, (a, b) in enumerate(body_pairs):
        weights = pairs._coefficients()[p]
        part = {a: weights[0] * modes[nodes[p, 0]]}
        part[b] = part.get(b, 0) + sum(weights[i] * modes[nodes[p, i]] for i in (1, 2, 3))
        for c in part:
            for d in part:
                if c == d or group[c] == group[d]:
                    whole[6 * c:6 * c + 6, 6 * d:6 * d + 6] += part[c].T @ pair_matrices[p] @ part[d]
    for k in range(groups):
        members = sorted((int(slot[b]), b) for b in range(bodies) if int(group[b]) == k)
        index = torch.cat([torch.arange(6) + 6 * b for _, b in members])
        count = 6 * len(members)
        torch.testing.assert_close(matrices[k][:count, :count], whole[index][:, index], rtol=1e-12, atol=1e-12)
        assert bool((matrices[k][count:] == 0).all()) and bool((matrices[k][:, count:] == 0).all())


def test_the_modes_are_rigid_motions():
    """The elastic product annihilates each mode at rest (hooke), the translations are unit and
    the rotations turn each body about its centre of mass."""
    sim = two_blocks_in_contact()
    sums = BodySums(sim.system.segments, sim.x)
    modes, centres = rigid_modes(sim.x, sim.system.mass.reshape(-1), sums)
    tensor_mass = sim.system.model
    for k in range(6):
        forces = tensor_mass.dforce(tensor_mass.rest, modes[k])
        assert float(forces.abs().max()) < 1e-9 * (1.0 + float(tensor_mass.dforce(tensor_mass.rest, sim.x).abs().max()))
    assert torch.equal(modes[0], torch.tensor([1.0, 0.0, 0.0], dtype=DT).expand_as(modes[0]))
    mass = sim.system.mass.reshape(-1)
    for b in range(2):
        rows = sim.system.segments.node_object == b
        for k in range(3, 6):
            torch.testing.assert_close((mass[rows, None] * modes[k][rows]).sum(0), torch.zeros(3, dtype=DT),
                                       rtol=0, atol=1e-12)


def loaded_correction(group_bodies=2):
    """The correction loaded for the two blocks' step (with block Jacobi's scaling) and the
    scaled step product p -> S^T A S p."""
    sim, loaded, pairs, stiffness, weights = step_pieces(velocities=False)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    scaling = JacobiScaling().load(system_diagonal_blocks(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness,
                                                          pairs, sim.options.dt))
    correction = RigidModeCorrection(group_bodies).load(
        sim.x, sim.system.mass.reshape(-1), sim.system.segments, sim.system.free, weights, scaling, pairs,
        pairs._pair_matrices(stiffness_coef, sim.options.dt))
    scaled = scaling.product(lambda p: loaded(p)[0] + stiffness(p))
    return sim, correction, scaled


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("coupled", [False, True], ids=["a-body-an-object", "one-object"])
def test_the_correction_on_block_jacobi_is_the_scaled_systems(monkeypatch, backend, coupled):
    """Loaded on a BlockJacobi (B^-1 in the CG's update, Z in the system's own unknowns, the
    coarse part added by ``correct``, and in the iterations by the direction and r.z from the
    coarse vectors), the preconditioner is B^-1 + w Z E^-1 Z^T = S (I + w Z' E^-1 Z'^T) S^T, and
    the CG makes the scaled system's iterates (float64, to roundoff): the same iteration counts
    and residual norms, the same solution, converged; with a body an object of the CG, and with
    both bodies one object (the contact's coupled run: each object's r.z sums its bodies')."""
    monkeypatch.setenv("TENSORMASS_BACKEND", backend)
    sim, loaded, pairs, stiffness, weights = step_pieces(velocities=False)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    blocks = system_diagonal_blocks(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness, pairs,
                                    sim.options.dt)
    arguments = (sim.x, sim.system.mass.reshape(-1), sim.system.segments, sim.system.free, weights)
    matrices = pairs._pair_matrices(stiffness_coef, sim.options.dt)
    scaling = JacobiScaling().load(blocks)
    on_scaling = RigidModeCorrection(2).load(*arguments, scaling, pairs, matrices)
    on_blocks = RigidModeCorrection(2).load(*arguments, BlockJacobi().load(blocks), pairs, matrices)
    assert on_scaling.inverse_blocks is None and on_blocks.inverse_blocks is not None
    product = lambda p: loaded(p)[0] + stiffness(p)  # noqa: E731
    r = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(2), dtype=DT)
    torch.testing.assert_close(on_blocks(r), scaling.apply(on_scaling(scaling.apply_transpose(r))), rtol=1e-10,
                               atol=1e-12 * float(on_blocks(r).abs().max()))
    rhs = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(3), dtype=DT)
    segments, free = sim.system.segments, sim.system.free
    if coupled:
        segments = Segments.from_lengths([int(segments.lengths.sum())])
    direct = CGSolver(segments, rhs.shape, DT, "cpu", free).solve(product, rhs, tol=1e-10, max_iter=500,
                                                                  preconditioner=on_blocks)
    scaled = CGSolver(segments, rhs.shape, DT, "cpu", free).solve(scaling.product(product), scaling.apply_transpose(rhs),
                                                                  tol=1e-10, max_iter=500, preconditioner=on_scaling)
    assert bool(direct.converged.all())
    assert direct.iterations.tolist() == scaled.iterations.tolist()
    torch.testing.assert_close(direct.residual_norm, scaled.residual_norm, rtol=1e-5, atol=1e-14)
    torch.testing.assert_close(direct.solution, scaling.apply(scaled.solution), rtol=1e-8,
                               atol=1e-10 * float(direct.solution.abs().max()))


def test_a_load_that_keeps_the_bodies_part_equals_a_fresh_one():
    """A second load with the same ``kept`` key (a contact round: other pairs, another scaling)
    reuses the modes and the bodies' own blocks and equals a fresh load, in the same buffers."""
    sim, loaded, pairs, _, weights = step_pieces(velocities=False)
    mass_coef, stiffness_coef = _coefficients(sim.options)

    def arguments(chosen):
        scaling = JacobiScaling().load(system_diagonal_blocks(sim.system, mass_coef, stiffness_coef,
                                                              loaded.node_stiffness, chosen, sim.options.dt))
        return (sim.x, sim.system.mass.reshape(-1), sim.system.segments, sim.system.free, weights, scaling, chosen,
                chosen._pair_matrices(stiffness_coef, sim.options.dt))

    fewer = pairs.select(torch.arange(0, len(pairs), 2))
    kept = RigidModeCorrection(2).load(*arguments(pairs), kept="load 1")
    storage = kept.inverses.values.data_ptr()
    kept.load(*arguments(fewer), kept="load 1")
    fresh = RigidModeCorrection(2).load(*arguments(fewer))
    assert kept.inverses.values.data_ptr() == storage
    torch.testing.assert_close(kept.inverses.values, fresh.inverses.values, rtol=1e-12, atol=0)
    for name in ("node_inverse", "arms"):
        torch.testing.assert_close(getattr(kept, name), getattr(fresh, name), rtol=1e-12, atol=0)
    assert torch.equal(kept.inverses.block_cols, fresh.inverses.block_cols)
    r = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(6), dtype=DT)
    torch.testing.assert_close(kept(r), fresh(r), rtol=1e-12, atol=1e-14)


def test_a_lagged_load_keeps_the_bodies_part_until_its_refresh():
    """Under one ``lag`` key the bodies' part (their arms and groups) of the first load is kept for
    ``refresh`` - 1 loads of new products at moved positions, then made again; the lagged
    correction is still symmetric positive definite, and without a key every load makes it."""
    sim, loaded, pairs, _, weights = step_pieces(velocities=False)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    scaling = JacobiScaling().load(system_diagonal_blocks(sim.system, mass_coef, stiffness_coef,
                                                          loaded.node_stiffness, pairs, sim.options.dt))
    angle = torch.tensor(0.05, dtype=DT)
    turn = torch.tensor([[torch.cos(angle), -torch.sin(angle), 0.0], [torch.sin(angle), torch.cos(angle), 0.0],
                         [0.0, 0.0, 1.0]], dtype=DT)

    def load(correction, x, key, lag):
        return correction.load(x, sim.system.mass.reshape(-1), sim.system.segments, sim.system.free, weights,
                               scaling, pairs, pairs._pair_matrices(stiffness_coef, sim.options.dt), kept=key, lag=lag)

    lagged, fresh = RigidModeCorrection(2, refresh=3), RigidModeCorrection(2, refresh=3)
    positions = [sim.x, sim.x @ turn.T, sim.x @ (turn @ turn).T, sim.x @ (turn @ turn @ turn).T]
    arms = []
    for k, x in enumerate(positions):
        load(lagged, x, ("product", k), (mass_coef, stiffness_coef))
        load(fresh, x, ("product", k), None)
        arms.append((lagged.arms.clone(), fresh.arms.clone()))
    assert torch.equal(arms[1][0], arms[0][0]) and torch.equal(arms[2][0], arms[0][0])
    torch.testing.assert_close(arms[3][0], arms[3][1], rtol=0, atol=0)
    assert not torch.allclose(arms[1][1], arms[0][1])  # (the positions turned: fresh arms differ)
    load(lagged, positions[0], ("product", 4), (mass_coef, stiffness_coef))  # lagged: the arms at positions[3]
    shape = sim.x.shape
    matrix = dense(lambda flat: lagged(flat.view(shape)).reshape(-1), shape.numel())
    torch.testing.assert_close(matrix, matrix.T, rtol=1e-10, atol=1e-10 * float(matrix.abs().max()))
    assert float(torch.linalg.eigvalsh(matrix).min()) > 0.5
    with pytest.raises(ValueError, match="refresh"):
        RigidModeCorrection(refresh=0)


@pytest.mark.parametrize("lag_pairs", [True, False])
def test_a_lagged_load_keeps_the_coarse_inverses_whole_with_lag_pairs(lag_pairs):
    """With ``lag_pairs`` (the default) a lagged load keeps the last load's coarse inverses whole,
    the pairs' part too (only N follows the load's block Jacobi); without it, the lagged load makes
    the pairs' part again. A second load of the same product (a contact round) makes it from its
    own pairs either way."""
    sim, loaded, pairs, _, weights = step_pieces(velocities=False)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    matrices = pairs._pair_matrices(stiffness_coef, sim.options.dt)

    def scaling_of(scale):
        return JacobiScaling().load(scale * system_diagonal_blocks(sim.system, mass_coef, stiffness_coef,
                                                                   loaded.node_stiffness, pairs, sim.options.dt))

    def arguments(scale, pair_scale):
        return (sim.x, sim.system.mass.reshape(-1), sim.system.segments, sim.system.free, weights,
                scaling_of(scale), pairs, pair_scale * matrices)

    lag = (mass_coef, stiffness_coef)
    correction = RigidModeCorrection(2, lag_pairs=lag_pairs).load(*arguments(1.0, 1.0), kept="product 0", lag=lag)
    first = correction.inverses.values.clone()
    correction.load(*arguments(2.0, 3.0), kept="product 1", lag=lag)  # lagged: stiffer pairs, another scaling
    assert correction._age == 1
    remade = RigidModeCorrection(2).load(*arguments(2.0, 3.0))
    torch.testing.assert_close(correction.node_inverse, remade.node_inverse, rtol=1e-12, atol=0)
    if lag_pairs:
        assert torch.equal(correction.inverses.values, first)
    else:
        torch.testing.assert_close(correction.inverses.values, remade.inverses.values, rtol=1e-12, atol=0)
        assert not torch.allclose(correction.inverses.values, first)
    correction.load(*arguments(2.0, 3.0), kept="product 1", lag=lag)  # the same product's next round
    torch.testing.assert_close(correction.inverses.values, remade.inverses.values, rtol=1e-12, atol=0)
    r = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(8), dtype=DT)
    torch.testing.assert_close(correction(r), remade(r), rtol=1e-12, atol=1e-14)


def test_the_correction_is_exact_on_the_coarse_space():
    """At rest (hooke: a rigid motion strains nothing) Z'^T A' Z' = E for the scaled step matrix
    A', so the coarse solve inverts A' on the span of Z': Z'^T A' (coarse(A' Z' c)) = Z'^T A' Z' c."""
    sim, correction, scaled = loaded_correction()
    shape = sim.x.shape
    basis = correction.basis().permute(2, 0, 1).contiguous()  # Z' [6, V, 3]
    images = [scaled(basis[k]) for k in range(6)]
    gen = torch.Generator().manual_seed(5)
    weights = torch.randn(2, 6, generator=gen, dtype=DT)
    per_node = weights[sim.system.segments.node_object]  # [V, 6]
    field = sum(per_node[:, k, None] * basis[k] for k in range(6))
    image = scaled(field)
    back = correction.coarse(image)
    torch.testing.assert_close(back, field.view(shape), rtol=1e-8, atol=1e-8 * float(field.abs().max()))
    assert len(images) == 6


def test_the_restriction_in_runs_equals_one_sum_a_body(monkeypatch):
    """The restriction sums runs of a body's nodes, then the runs: runs of 5 nodes (each body's
    last one shorter) give the correction of runs longer than the bodies, to rounding."""
    sim, whole, _ = loaded_correction()
    assert int(sim.system.segments.lengths.max()) <= rigid_modes_module.RESTRICTION_RUN
    monkeypatch.setattr(rigid_modes_module, "RESTRICTION_RUN", 5)
    _, runs, _ = loaded_correction()
    assert runs._run_ptr.numel() - 1 == int(((sim.system.segments.lengths + 4) // 5).sum())
    r = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(8), dtype=DT)
    torch.testing.assert_close(runs(r), whole(r), rtol=1e-12, atol=1e-13)


@pytest.mark.parametrize("group_bodies", [1, 2])
def test_the_preconditioner_is_symmetric_positive_definite(group_bodies):
    sim, correction, _ = loaded_correction(group_bodies)
    shape = sim.x.shape
    matrix = dense(lambda flat: correction(flat.view(shape)).reshape(-1), shape.numel())
    torch.testing.assert_close(matrix, matrix.T, rtol=1e-10, atol=1e-10 * float(matrix.abs().max()))
    assert float(torch.linalg.eigvalsh(matrix).min()) > 0.5  # the identity plus a positive part


def tower(preconditioner, dtype=DT, device="cpu"):
    """Four blocks (1e6 Pa, the piles' stiffness) stacked on a floor, each resting in the one
    below's contact layer."""
    material = tm.Material(young=1e6, poisson=0.3, density=1000)
    block = tm.beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=dtype)
    bodies = [tm.Body(tm.TetMesh(block.vertices + torch.tensor([0.01 * k, 0.0, 0.001 + 0.1015 * k], dtype=dtype),
                                 block.elements), material) for k in range(4)]
    return tm.Simulator(bodies, dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(),
                        rayleigh_mass=1.0, cg_tol=1e-6, preconditioner=preconditioner, dtype=dtype, device=device)


def test_a_tower_takes_fewer_iterations_with_the_rigid_correction():
    """A stack of four blocks whose contacts carry the weight above: the coarse space takes a
    stack's near-rigid motions off the CG (the same solution to the tolerance)."""
    counts, ends = {}, {}
    for preconditioner in ("jacobi", "rigid"):
        sim = tower(preconditioner)
        sim.step(10)  # the blocks settle into their contacts
        total = 0
        for _ in range(10):
            report = sim.step()
            total += sum(int(c.iterations.max()) for c in report.cg)
        assert int(report.contact.body_contacts.sum()) > 0
        counts[preconditioner], ends[preconditioner] = total, sim.x.clone()
    assert counts["rigid"] < 0.8 * counts["jacobi"], counts
    torch.testing.assert_close(ends["rigid"], ends["jacobi"], rtol=0, atol=1e-5)


def test_auto_takes_the_rigid_correction_where_body_contact_pairs_join_the_solve():
    """``"auto"`` (the default): the rigid correction on block Jacobi for the solves body contact
    pairs join, bit for bit ``"rigid"``'s steps where every solve has pairs (the tower settled in
    its contacts); plain CG, with neither block Jacobi nor the correction, on the same tower
    lifted apart (no pair)."""
    settled = tower("rigid")
    settled.step(10)  # every step from here has pairs
    ends, corrections = {}, {}
    for preconditioner in ("auto", "rigid"):
        sim = tower(preconditioner)
        sim.x, sim.v = settled.x.clone(), settled.v.clone()
        sim.step(3)
        assert int(sim.last_report.contact.body_contacts.sum()) > 0
        ends[preconditioner], corrections[preconditioner] = sim.x.clone(), sim.system._rigid
    assert corrections["auto"] is not None and corrections["rigid"] is not None
    assert torch.equal(ends["auto"], ends["rigid"])
    apart = tower("auto")  # lifted: the blocks fall a step without touching
    apart.x = apart.x + torch.arange(4, dtype=DT).repeat_interleave(apart.x.shape[0] // 4)[:, None] * torch.tensor(
        [0.0, 0.0, 0.1], dtype=DT)
    apart.step()
    assert int(apart.last_report.contact.body_contacts.sum()) == 0
    assert apart.system._rigid is None and apart.system._block_jacobi is None


def test_the_step_lags_the_bodies_part_only_while_the_contacts_hold_still():
    """implicit_euler._rigid: after a step whose first contact check found pairs the correction's
    bodies' part is computed afresh at the next step's first load; after one whose check found
    nothing it is lagged (up to RigidModeCorrection.refresh loads), the same tower either way."""
    sim = tower("rigid")
    sim.step(10)
    correction = sim.system._rigid
    assert correction.refresh == rigid_modes_module.REFRESH > 1
    ages = []
    for found in (True, False, False, True, False):
        sim.system.body_contact.first_check_found = found  # what the last step's check found
        arms = correction.arms.clone()
        sim.step()
        ages.append(correction._age)
        assert torch.equal(correction.arms, arms) == (not found)  # lagged: the arms kept
    assert ages == [0, 1, 2, 0, 1]


def test_morton_groups_partition_the_bodies():
    gen = torch.Generator().manual_seed(2)
    centres = torch.rand(37, 3, generator=gen, dtype=DT)
    group, slot, groups = morton_groups(centres, 8)
    assert groups == 5
    places = (group * 8 + slot).tolist()
    assert sorted(places) == list(range(37))
    near = morton_groups(torch.tensor([[0.0, 0, 0], [5.0, 5, 5], [0.01, 0, 0], [5.0, 5, 5.01]], dtype=DT), 2)[0]
    assert near[0] == near[2] and near[1] == near[3] and near[0] != near[1]


def test_bad_group_size_raises_one_clear_error():
    with pytest.raises(ValueError, match="group_bodies must be at least 1, got 0"):
        RigidModeCorrection(group_bodies=0)


def test_the_scene_file_takes_rigid(tmp_path):
    scene = tmp_path / "rigid.toml"
    scene.write_text('[solver]\npreconditioner = "rigid"\n\n[[bodies]]\nmesh = { generator = "beam", cells = [1, 1, 1] }\n'
                     'material = { young = 1e5, poisson = 0.3, density = 1000 }\n')
    assert tm.load_scene(scene).simulator.options.preconditioner == "rigid"


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a GPU")
def test_a_captured_correction_replays_each_load():
    """The correction inside a CUDA graph: replayed after a new load, it gives the new load's
    eager result (its buffers keep their storage)."""
    sim = tower("rigid", torch.float32, "cuda")
    sim.step(12)
    correction = sim.system._rigid
    r = torch.randn_like(sim.x)
    out = torch.empty_like(r)
    correction(r)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out.copy_(correction(r))
    sim.step()  # a new load into the same buffers
    graph.replay()
    torch.testing.assert_close(out, correction(r), rtol=1e-6, atol=1e-6 * float(out.abs().max()))


@pytest.mark.parametrize("kind", ["tri2d", "membrane"])
def test_rigid_on_triangle_bodies_steps_as_jacobi(kind):
    """Triangle bodies (a planar mesh, which the simulator moves in 3-D, and a membrane) take the
    correction and step as "jacobi" does, to the tolerance."""
    mesh = group_meshes()[kind]
    out = {}
    for preconditioner in ("rigid", "jacobi"):
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000), fixed=mesh.vertices[:, 0] < 1e-9)
        sim = tm.Simulator([body], dt=0.01, cg_tol=1e-12, preconditioner=preconditioner)
        sim.step(3)
        out[preconditioner] = (sim.v.clone(), sim.system._rigid)
    torch.testing.assert_close(out["rigid"][0], out["jacobi"][0], rtol=1e-8, atol=1e-9)
    assert out["rigid"][1] is not None and out["jacobi"][1] is None


def chains(count=4, length=10):
    """``count`` chains of ``length`` bodies side by side (columns 0.25 apart, bodies 0.13 above
    each other): consecutive bodies of a chain joined by 200-202 pairs, neighbours across two
    chains by 5, and 500 pairs of body 3 with itself; the pairs' bodies ``[P, 2]`` (shuffled) and
    the bodies' centres ``[B, 3]``."""
    pairs = []
    for c in range(count):
        for k in range(length - 1):
            pairs += [[c * length + k, c * length + k + 1]] * (200 + k % 3)
        if c < count - 1:
            for k in range(length):
                pairs += [[c * length + k, (c + 1) * length + k]] * 5
    pairs += [[3, 3]] * 500  # self-contact: joins nothing, however many
    objects = torch.tensor(pairs)
    objects = objects[torch.randperm(len(objects), generator=torch.Generator().manual_seed(0))]
    centres = torch.tensor([[0.25 * (b // length), 0.0, 0.13 * (b % length)] for b in range(count * length)], dtype=DT)
    return objects, centres


@pytest.mark.parametrize("most", [32, 10, 8, 4])
def test_contact_clusters_join_the_heaviest_edges_up_to_the_size(most):
    """Heavy-edge matching on the bodies' contact graph: no cluster above the size; chains of ten
    whose links outweigh their neighbours' each fall whole in one cluster where they fit."""
    objects, _ = chains()
    label = contact_clusters(objects, 40, most)
    assert int(torch.bincount(label).max()) <= most
    if most >= 10:
        assert all(len(set(label[10 * c:10 * c + 10].tolist())) == 1 for c in range(4))
    else:
        assert len(set(label.tolist())) <= 40 // (most // 2)  # (clusters of at least half the size, about)
    assert torch.equal(label, contact_clusters(objects, 40, most))
    assert torch.equal(contact_clusters(objects[:0], 40, most, 4), torch.arange(40))


def test_contact_groups_keep_the_chains_the_morton_curve_cuts():
    objects, centres = chains()
    group, slot, groups = contact_groups(centres, objects, 10)
    assert groups == 4 and sorted((group * 10 + slot).tolist()) == list(range(40))
    assert all(len(set(group[10 * c:10 * c + 10].tolist())) == 1 for c in range(4))
    morton = morton_groups(centres, 10)[0]
    assert any(len(set(morton[10 * c:10 * c + 10].tolist())) > 1 for c in range(4))


def test_bad_grouping_raises_one_clear_error():
    with pytest.raises(ValueError, match="grouping must be one of"):
        RigidModeCorrection(grouping="metis")


def test_two_towers_take_fewer_iterations_with_contact_groups():
    """Two towers of four blocks in groups of four bodies: the contact groups hold each tower, the
    Morton curve's mix them (the same solution to the tolerance)."""
    counts, ends = {}, {}
    for grouping in ("morton", "contact"):
        material = tm.Material(young=1e6, poisson=0.3, density=1000)
        block = tm.beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=DT)
        bodies = [tm.Body(tm.TetMesh(block.vertices + torch.tensor([0.25 * i + 0.01 * k, 0.0, 0.001 + 0.1015 * k],
                                                                   dtype=DT), block.elements), material)
                  for i in range(2) for k in range(4)]
        sim = tm.Simulator(bodies, dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(),
                           rayleigh_mass=1.0, cg_tol=1e-6, preconditioner="rigid", dtype=DT)
        sim.system._rigid = RigidModeCorrection(4, grouping=grouping)
        sim.step(10)
        counts[grouping] = sum(sum(int(c.iterations.max()) for c in sim.step().cg) for _ in range(10))
        ends[grouping] = sim.x.clone()
    assert counts["contact"] < counts["morton"], counts
    torch.testing.assert_close(ends["contact"], ends["morton"], rtol=0, atol=1e-5)
