"""Jacobi preconditioning (solver.preconditioner): the diagonals it divides by against the probed
diagonals of the operators (float64), the preconditioned step against the plain one and a dense
solve, the cache following a cut, and bad choices."""
import dataclasses
from unittest.mock import patch

import pytest
import torch
from conftest import GROUP_CASES, group_meshes

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.physics.body_contact import Contact, PairStiffness, SurfaceContact
from tensormass_torch.solver.cg import CGSolver
from tensormass_torch.solver.implicit_euler import _coefficients, implicit_euler_step
from tensormass_torch.solver.preconditioner import (
    BlockJacobi,
    JacobiScaling,
    PairTerms,
    system_diagonal,
    system_diagonal_blocks,
)

DT = torch.float64


def probed_diagonal(product, shape):
    """The diagonal ``[V, d]`` of a linear map on ``[V, d]`` fields (its probed blocks' diagonals)."""
    return torch.diagonal(probed_blocks(product, shape), dim1=-2, dim2=-1)


@pytest.mark.parametrize("kind,model,form", GROUP_CASES)
def test_stiffness_diagonal_is_the_rest_stiffness_diagonal(kind, model, form):
    """Every group's diagonal equals the probed diagonal of -dF/dx at rest."""
    mesh = group_meshes()[kind]
    tensor_mass = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1000, model=model), form=form)
    rest = tensor_mass.rest
    expected = probed_diagonal(lambda e: -tensor_mass.dforce(rest, e), rest.shape)
    diagonal = tensor_mass.stiffness_diagonal()
    assert bool((diagonal > 0).all())
    torch.testing.assert_close(diagonal, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))


@pytest.mark.parametrize("form", ["tensor", "stress"])
def test_the_diagonal_follows_a_cut(form):
    """Removing elements edits the groups' tensors in place: the kept diagonal is summed again and
    equals the probed one of the cut model (removed elements add nothing)."""
    mesh = tm.beam_mesh(2, 2, 3, size=(0.1, 0.1, 0.3), dtype=DT)
    tensor_mass = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1000), form=form)
    before = tensor_mass.stiffness_diagonal().clone()
    assert tensor_mass.stiffness_diagonal() is tensor_mass.stiffness_diagonal()  # kept
    tensor_mass.remove_elements(torch.tensor([0, 5, 7]))
    rest = tensor_mass.rest
    expected = probed_diagonal(lambda e: -tensor_mass.dforce(rest, e), rest.shape)
    after = tensor_mass.stiffness_diagonal()
    assert not torch.equal(after, before)
    torch.testing.assert_close(after, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))


def probed_blocks(product, shape):
    """The diagonal blocks ``[V, d, d]`` of a linear map on ``[V, d]`` fields."""
    out = torch.zeros(shape[0], shape[1], shape[1], dtype=DT)
    for a in range(shape[1]):
        for i in range(shape[0]):
            e = torch.zeros(shape, dtype=DT)
            e[i, a] = 1.0
            out[i, :, a] = product(e)[i]
    return out


@pytest.mark.parametrize("kind,model,form", GROUP_CASES)
def test_stiffness_blocks_are_the_rest_stiffness_blocks(kind, model, form):
    """Every node's d x d block of -dF/dx at rest, and after a cut."""
    mesh = group_meshes()[kind]
    tensor_mass = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1000, model=model), form=form)
    rest = tensor_mass.rest
    for cut in (False, True):
        if cut:
            tensor_mass.remove_elements(torch.tensor([0, 3]))
        expected = probed_blocks(lambda e: -tensor_mass.dforce(rest, e), rest.shape)
        blocks = tensor_mass.stiffness_diagonal_blocks()
        torch.testing.assert_close(blocks, expected, rtol=1e-12, atol=1e-12 * float(expected.abs().max()))


def two_blocks_in_contact(preconditioner="auto", friction=0.0, cg_tol=1e-13, paired_blocks=True):
    """Two small blocks, one resting on the other on a floor, in contact (with Jacobi, by default)."""
    material = tm.Material(young=1e4, poisson=0.3, density=1000)
    low = tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), dtype=DT)
    high = tm.TetMesh(low.vertices + torch.tensor([0.05, 0.03, 0.095], dtype=DT), low.elements)
    return tm.Simulator([tm.Body(low, material), tm.Body(high, material)], dt=0.01,
                        planes=[tm.Plane((0, 0, 1), 0.001, 1e4, friction=0.3)],
                        contact=tm.Contact(stiffness=1e3, thickness=0.01, friction=friction), rayleigh_mass=0.5,
                        cg_tol=cg_tol, cuda_graphs=False, preconditioner=preconditioner, paired_blocks=paired_blocks)


def loaded_step_matrix(sim):
    """The step's SystemMatvec loaded at the state (node stiffness of the floor and its friction
    folded in, as a step does) and the pairs the step linearises."""
    from tensormass_torch.solver.implicit_euler import _step_system

    system, opts = sim.system, sim.options
    loaded = system.system_matvec(*_coefficients(opts), opts.pipelined, opts.variants)
    _, _, pairs = sim.body_contact.at_state(sim.x, sim.v, opts.dt)
    _step_system(system, sim.x, sim.v, opts, None, loaded)
    return loaded, pairs


def loaded_step_with_pairs(friction=0.0, seed=1):
    """The two blocks at random velocities (``seed``; None: at rest): (sim, its loaded
    SystemMatvec, its pairs, the pairs' product PairStiffness loaded with the step's coefficient
    and friction damping)."""
    sim = two_blocks_in_contact(friction=friction)
    if seed is not None:
        gen = torch.Generator().manual_seed(seed)
        sim.v = 0.05 * torch.randn(sim.x.shape, generator=gen, dtype=DT)
    loaded, pairs = loaded_step_matrix(sim)
    stiffness = PairStiffness()
    stiffness.load(pairs, _coefficients(sim.options)[1], sim.options.dt)
    return sim, loaded, pairs, stiffness


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_the_system_diagonal_is_the_step_matrix_diagonal(friction):
    """system_diagonal equals the probed diagonal of the step's whole product: mass, elasticity,
    the floor's stiffness and friction, the pairs' stiffness and friction."""
    sim, loaded, pairs, stiffness = loaded_step_with_pairs(friction)
    assert len(pairs) > 0 and (friction == 0) == (pairs.friction is None)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    expected = probed_diagonal(lambda e: loaded(e)[0] + stiffness(e), sim.x.shape)
    diagonal = system_diagonal(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness, pairs, sim.options.dt)
    torch.testing.assert_close(diagonal, expected, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_the_system_blocks_are_the_step_matrix_blocks(friction):
    """system_diagonal_blocks equals the probed diagonal blocks of the step's whole product (the
    floor and pairs with their friction couple a node's axes)."""
    sim, loaded, pairs, stiffness = loaded_step_with_pairs(friction)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    expected = probed_blocks(lambda e: loaded(e)[0] + stiffness(e), sim.x.shape)
    blocks = system_diagonal_blocks(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness, pairs,
                                    sim.options.dt)
    torch.testing.assert_close(blocks, expected, rtol=1e-12, atol=1e-14)
    off = blocks - torch.diag_embed(torch.diagonal(blocks, dim1=-2, dim2=-1))
    assert float(off.abs().max()) > 1e-6 * float(blocks.abs().max())  # the blocks are not diagonal
    # the loaded PairStiffness's blocks (the step's: its entries sorted at the load) are the pairs'
    mass_only = system_diagonal_blocks(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness)
    torch.testing.assert_close(mass_only + stiffness.stiffness_blocks(), expected, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(stiffness.stiffness_blocks(), pairs.stiffness_blocks(stiffness_coef, sim.options.dt),
                               rtol=1e-13, atol=0)


def test_the_block_scaling_is_the_inverse_cholesky_factor():
    """With blocks B = L L^T, S = L^-T: upper triangular, S^T B S = I per node, S^-1 = L^T its
    inverse; the product is S^T A S (similar to B^-1 A); a node whose block is zero (or not
    positive definite) stays unscaled."""
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(15, 15, generator=gen, dtype=DT)
    a = a @ a.T + 12 * torch.eye(15, dtype=DT)
    blocks = torch.stack([a[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(5)]).clone()
    blocks[2] = 0.0
    blocks[4] = torch.diag(torch.tensor([1.0, -2.0, 3.0], dtype=DT))  # indefinite
    scaling = JacobiScaling().load(blocks)
    s = scaling.scale
    torch.testing.assert_close(s, torch.triu(s))
    for i in (0, 1, 3):
        torch.testing.assert_close(s[i].T @ blocks[i] @ s[i], torch.eye(3, dtype=DT))
        torch.testing.assert_close(scaling.inverse[i].T @ scaling.inverse[i], blocks[i])
    for i in (2, 4):
        torch.testing.assert_close(s[i], torch.eye(3, dtype=DT))
    p = torch.randn(5, 3, generator=gen, dtype=DT)
    torch.testing.assert_close(scaling.unapply(scaling.apply(p)), p)
    big = torch.block_diag(*s)
    expected = (big.T @ a @ big) @ p.reshape(-1)
    torch.testing.assert_close(scaling.product(lambda q: (a @ q.reshape(-1)).view(5, 3))(p).reshape(-1), expected)
    torch.testing.assert_close(scaling.apply_transpose(p).reshape(-1), big.T @ p.reshape(-1))
    # the spectrum of B^-1 A, as the symmetric B^(-1/2) A B^(-1/2) has it
    keep = [i for i in range(15) if i // 3 in (0, 1, 3)]
    sub = big[keep][:, keep].T @ a[keep][:, keep] @ big[keep][:, keep]
    values, vectors = torch.linalg.eigh(torch.block_diag(*(blocks[i] for i in (0, 1, 3))))
    half = vectors @ torch.diag(values.rsqrt()) @ vectors.T
    torch.testing.assert_close(torch.linalg.eigvalsh(sub), torch.linalg.eigvalsh(half @ a[keep][:, keep] @ half))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_block_scaling_of_many_blocks(dim, device):
    """A pile's worth of blocks (200,000: more than solver libraries' batched routines take),
    float32, 2-D and 3-D: S^T B S = I to float32's rounding."""
    gen = torch.Generator().manual_seed(1)
    g = torch.randn(200_000, dim, dim, generator=gen)
    blocks = (g @ g.transpose(1, 2) + 0.1 * torch.eye(dim)).to(device)
    scaling = JacobiScaling().load(blocks)
    eye = torch.eye(dim, device=device).expand_as(blocks)
    s = scaling.scale
    torch.testing.assert_close(s.transpose(1, 2) @ blocks @ s, eye, rtol=0, atol=2e-3)
    torch.testing.assert_close(scaling.inverse @ s, eye, rtol=0, atol=1e-4)


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_block_products_are_the_dense_ones_and_follow_each_load(dim, device):
    """S v, S^T v and S^-1 v (the BSR product op where the extension serves the device, its
    reference otherwise) equal the dense block-diagonal products, through the op and the
    reference alike; a second load writes new blocks into the same buffers (a captured graph's
    products follow), S^T's included."""
    from tensormass_torch.ops import multigrid

    gen = torch.Generator().manual_seed(2)

    def random_blocks():
        g = torch.randn(7, dim, dim, generator=gen, dtype=DT)
        return (g @ g.transpose(1, 2) + 0.5 * torch.eye(dim, dtype=DT)).to(device)

    scaling = JacobiScaling().load(random_blocks())
    pointers = [m.values.data_ptr() for m in scaling._blocks]
    scaling.load(random_blocks())
    assert [m.values.data_ptr() for m in scaling._blocks] == pointers
    v = torch.randn(7, dim, generator=gen, dtype=DT).to(device)
    big, inverse = torch.block_diag(*scaling.scale), torch.block_diag(*scaling.inverse)
    for native in (True, False):
        with patch.object(multigrid.library, "op_or_reference",
                          lambda name, dev, _n=native, _f=multigrid.library.op_or_reference: _f(name, dev, _n)):
            torch.testing.assert_close(scaling.apply(v).reshape(-1), big @ v.reshape(-1))
            torch.testing.assert_close(scaling.apply_transpose(v).reshape(-1), big.T @ v.reshape(-1))
            torch.testing.assert_close(scaling.unapply(v).reshape(-1), inverse @ v.reshape(-1))


def test_the_scaled_product_is_s_a_s():
    """JacobiScaling's product is S A S with S = D^(-1/2), a fused (A p, p . Ap) product's dots
    dropped; its buffer keeps its storage across loads; rows without a positive diagonal stay
    unscaled."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(12, 12, generator=gen, dtype=DT)
    a = a @ a.T + 12 * torch.eye(12, dtype=DT)
    diagonal = torch.diagonal(a).reshape(4, 3).clone()
    diagonal[2, 1] = 0.0  # a row CG never moves
    scaling = JacobiScaling().load(diagonal)
    storage = scaling.scale.data_ptr()
    s = scaling.scale.reshape(-1)
    assert s[7] == 1.0
    p = torch.randn(4, 3, generator=gen, dtype=DT)
    expected = (s[:, None] * a * s[None, :]) @ p.reshape(-1)
    plain = scaling.product(lambda q: (a @ q.reshape(-1)).view(4, 3))
    fused = scaling.product(lambda q: ((a @ q.reshape(-1)).view(4, 3), torch.zeros(4, dtype=DT)))
    torch.testing.assert_close(plain(p).reshape(-1), expected)
    torch.testing.assert_close(fused(p).reshape(-1), expected)
    scaling.load(2.0 * torch.diagonal(a).reshape(4, 3))
    assert scaling.scale.data_ptr() == storage


@pytest.mark.parametrize("backend", ["auto", "torch"])
@pytest.mark.parametrize("guess", [False, True], ids=["x0=0", "x0"])
def test_block_jacobi_in_the_update_is_the_scaled_cg(monkeypatch, backend, guess):
    """CG preconditioned by BlockJacobi inside its update makes the iterates of CG on the scaled
    system S^T A S (JacobiScaling, x = S y), in float64 to roundoff: the same iteration counts and
    residual norms (both in B^-1's norm), the same solutions, and a dense solve's to its tolerance;
    a fixed node stays where x0 puts it, and the storage of B^-1 stays across loads."""
    monkeypatch.setenv("TENSORMASS_BACKEND", backend)
    gen = torch.Generator().manual_seed(6)
    sizes = [9, 5, 14]
    nodes = sum(sizes)
    blocks = []
    for n in sizes:  # SPD with a few stiff rows (a penalty's), coupled within each object
        q = torch.randn(3 * n, 3 * n, generator=gen, dtype=DT)
        stiff = torch.ones(3 * n, dtype=DT)
        stiff[:6] = 300.0
        blocks.append(torch.diag(stiff.sqrt()) @ (q @ q.T + 3 * n * torch.eye(3 * n, dtype=DT)) @ torch.diag(
            stiff.sqrt()))
    a = torch.block_diag(*blocks)
    free = torch.ones(nodes, 1, dtype=DT)
    free[[3, 20]] = 0.0
    project = torch.diag(free.repeat(1, 3).reshape(-1))
    a_free = project @ a @ project + torch.diag(1.0 - free.repeat(1, 3).reshape(-1))
    rhs = torch.randn(nodes, 3, generator=gen, dtype=DT)
    x0 = torch.randn(nodes, 3, generator=gen, dtype=DT) if guess else None
    diagonal_blocks = torch.stack([a[3 * i:3 * i + 3, 3 * i:3 * i + 3] for i in range(nodes)])
    segments = Segments.from_lengths(sizes)
    matvec = lambda p: (a @ p.reshape(-1)).view_as(p)  # noqa: E731

    block_jacobi = BlockJacobi().load(diagonal_blocks)
    storage = block_jacobi.inverse_blocks.data_ptr()
    torch.testing.assert_close(block_jacobi.inverse_blocks, torch.linalg.inv(diagonal_blocks))
    solver = CGSolver(segments, rhs.shape, DT, "cpu", free)
    in_update = solver.solve(matvec, rhs, x0, tol=1e-10, max_iter=500, preconditioner=block_jacobi)

    scaling = JacobiScaling().load(diagonal_blocks)
    scaled_solver = CGSolver(segments, rhs.shape, DT, "cpu", free)
    scaled = scaled_solver.solve(scaling.product(matvec), scaling.apply_transpose(rhs),
                                 None if x0 is None else scaling.unapply(x0), tol=1e-10, max_iter=500)
    assert bool(in_update.converged.all())
    assert in_update.iterations.tolist() == scaled.iterations.tolist()
    torch.testing.assert_close(in_update.residual_norm, scaled.residual_norm, rtol=1e-6, atol=1e-14)
    torch.testing.assert_close(in_update.rhs_norm, scaled.rhs_norm, rtol=1e-12, atol=0)
    torch.testing.assert_close(in_update.solution, scaling.apply(scaled.solution), rtol=1e-9, atol=1e-12)
    fixed = free[:, 0] == 0
    start = torch.zeros_like(rhs) if x0 is None else x0
    assert torch.equal(in_update.solution[fixed], start[fixed])
    # the solve on the free nodes (the fixed ones' x0 does not enter the product), x0 on the fixed
    exact = torch.linalg.solve(a_free, torch.where(fixed[:, None], start, rhs).reshape(-1))
    assert float((in_update.solution.reshape(-1) - exact).abs().max()) < 1e-7 * float(exact.abs().max())
    block_jacobi.load(2.0 * diagonal_blocks)
    assert block_jacobi.inverse_blocks.data_ptr() == storage


@pytest.mark.parametrize("friction", [0.0, 0.4])
@pytest.mark.parametrize("preconditioned", ["jacobi", "rigid"])
@pytest.mark.parametrize("paired", [True, False])
def test_preconditioned_and_plain_steps_agree(friction, preconditioned, paired):
    """The same step (contact pairs, floor and its friction) solved to 1e-13 with block Jacobi
    (alone, and under the rigid motions' coarse correction; with the contact's nodes paired and
    without) and without: the same velocities to 1e-9."""
    results = []
    for preconditioner in (preconditioned, "none"):
        sim = two_blocks_in_contact(preconditioner, friction, paired_blocks=paired)
        gen = torch.Generator().manual_seed(4)
        sim.v = 0.05 * torch.randn(sim.x.shape, generator=gen, dtype=DT)
        _, v_new, report = implicit_euler_step(sim.system, sim.x, sim.v, sim.options)
        assert all(bool(r.converged.all()) for r in report.cg)
        results.append(v_new)
    torch.testing.assert_close(results[0], results[1], rtol=1e-9, atol=1e-9)


def test_jacobi_on_a_body_without_contact_equals_the_plain_step():
    """preconditioner="jacobi" without contact (the scaled product instead of the whole-solve op):
    the plain step's velocities to 1e-9, and a fixed node stays fixed."""
    mesh = tm.beam_mesh(4, 1, 1, size=(0.4, 0.1, 0.1), dtype=DT)
    out = []
    for preconditioner in ("jacobi", "none"):
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000), fixed=mesh.vertices[:, 0] < 1e-9)
        sim = tm.Simulator([body], dt=0.01, cg_tol=1e-13, preconditioner=preconditioner)
        sim.step(3)
        out.append(sim.v.clone())
    torch.testing.assert_close(out[0], out[1], rtol=1e-9, atol=1e-9)
    assert float(out[0][mesh.vertices[:, 0] < 1e-9].abs().max()) == 0.0


def test_a_pile_with_jacobi_keeps_the_bodies_apart():
    """Two blocks dropped on each other with the default (Jacobi where they touch) and float32:
    the steps converge and the bodies stay apart (exact interpenetration under 1 % of an edge)."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    low = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=torch.float32)
    high = tm.TetMesh(low.vertices + torch.tensor([0.02, 0.0, 0.13]), low.elements)
    sim = tm.Simulator([tm.Body(low, material), tm.Body(high, material)], dt=0.005,
                       planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(), rayleigh_mass=1.0, cg_tol=1e-4)
    for _ in range(60):
        report = sim.step()
    assert report.contact.body_contacts.sum() > 0
    assert float(sim.interpenetration().max()) < 0.01 * sim.body_contact.search


def test_bad_preconditioner_raises_one_clear_error(tmp_path):
    mesh = tm.beam_mesh(1, 1, 1, dtype=DT)
    with pytest.raises(tm.SceneError, match="preconditioner must be one of 'auto', 'none', 'jacobi', 'rigid', 'multigrid', 'cholesky', "
                                            "got 'ilu'"):
        tm.Simulator([tm.Body(mesh, tm.Material(young=1e5, poisson=0.3))], preconditioner="ilu")
    scene = tmp_path / "bad.toml"
    scene.write_text('[solver]\npreconditioner = "amg"\n\n[[bodies]]\nmesh = { generator = "beam", cells = [1, 1, 1] }\n'
                     'material = { young = 1e5, poisson = 0.3, density = 1000 }\n')
    with pytest.raises(tm.SceneError, match="preconditioner"):
        tm.load_scene(scene)


def test_the_scene_file_key_reaches_the_simulator(tmp_path):
    scene = tmp_path / "jacobi.toml"
    scene.write_text('[solver]\npreconditioner = "jacobi"\n\n[[bodies]]\nmesh = { generator = "beam", cells = [1, 1, 1] }\n'
                     'material = { young = 1e5, poisson = 0.3, density = 1000 }\n')
    assert tm.load_scene(scene).simulator.options.preconditioner == "jacobi"


def test_detected_pairs_have_a_positive_diagonal():
    """ContactPairs.stiffness_diagonal of overlapping bodies is non-negative and zero off the
    pairs' nodes; with friction it grows by the tangential part."""
    mesh = tm.beam_mesh(2, 2, 1, size=(0.2, 0.2, 0.1), dtype=DT)
    rest = torch.cat([mesh.vertices, mesh.vertices + torch.tensor([0.03, 0.02, 0.09], dtype=DT)])
    from tensormass_torch.mesh.topology import boundary_faces

    triangles = torch.cat([boundary_faces(mesh.elements), boundary_faces(mesh.elements) + mesh.num_vertices])
    objects = torch.cat([torch.zeros(mesh.num_vertices, dtype=torch.int64),
                         torch.ones(mesh.num_vertices, dtype=torch.int64)])
    contact = SurfaceContact(triangles, objects, rest, Contact(stiffness=1e3, thickness=0.01))
    pairs = contact.detect(rest)
    assert len(pairs) > 0
    plain = pairs.stiffness_diagonal(0.5)
    touched = torch.zeros(rest.shape[0], dtype=torch.bool)
    touched[pairs.nodes.reshape(-1)] = True
    assert bool((plain >= 0).all()) and float(plain[~touched].abs().max()) == 0.0
    rubbing = dataclasses.replace(pairs, friction=torch.full((len(pairs),), 7.0, dtype=DT))
    assert bool((rubbing.stiffness_diagonal(0.5, 0.1) >= plain).all())


def dense_step_matrix(sim, loaded, stiffness):
    """The step's whole matrix ``[3 V, 3 V]`` (the loaded product and the pairs'), probed."""
    n = sim.x.numel()
    columns = []
    for k in range(n):
        e = torch.zeros(n, dtype=DT)
        e[k] = 1.0
        e = e.view_as(sim.x)
        columns.append((loaded(e)[0] + stiffness(e)).reshape(-1))
    return torch.stack(columns, 1)


@pytest.mark.parametrize("friction", [0.0, 0.4])
def test_paired_blocks_invert_the_merged_blocks_of_the_step_matrix(friction):
    """BlockJacobi with the step's pairs: each merged pair (two nodes of different bodies, none
    in two pairs, each the other's link of largest weight) holds the inverse of the step matrix's
    6 x 6 block over its nodes (D_i, D_j in inverse_blocks, O in the paired blocks); every other
    node its 3 x 3 block's inverse; and z = M^-1 r in tensor ops (``__call__``) and through the
    op (``ops.cg.pair_term``) is that block diagonal's product."""
    from tensormass_torch.ops import cg as cg_ops
    from tensormass_torch.ops.segments import ChunkPlan
    from tensormass_torch.solver.cg import CGState
    from tensormass_torch.solver.preconditioner import paired_nodes

    sim, loaded, pairs, stiffness = loaded_step_with_pairs(friction)
    mass_coef, stiffness_coef = _coefficients(sim.options)
    dense = dense_step_matrix(sim, loaded, stiffness)
    blocks = system_diagonal_blocks(sim.system, mass_coef, stiffness_coef, loaded.node_stiffness, pairs,
                                    sim.options.dt)
    node_object = sim.system.segments.node_object
    terms = PairTerms(pairs.nodes, pairs._coefficients(), lambda: pairs._pair_matrices(stiffness_coef, sim.options.dt))
    jacobi = BlockJacobi().load(blocks, terms, node_object, sim.system.free)
    first, second, count = paired_nodes(pairs.nodes, pairs._coefficients(), node_object, sim.x.shape[0],
                                        sim.system.free)
    merged = first < sim.x.shape[0]
    assert int(merged.sum()) >= 4 and count == min(len(pairs), sim.x.shape[0] // 2)
    i, j = first[merged], second[merged]
    assert bool((i < j).all()) and bool((node_object[i] != node_object[j]).all())
    assert torch.cat([i, j]).unique().numel() == 2 * i.numel()  # no node in two pairs
    paired = jacobi.paired
    assert torch.equal(paired.nodes[:i.numel()], torch.stack([i, j], 1)) and bool((paired.nodes[i.numel():] == -1).all())
    expected = torch.zeros_like(dense)
    alone = torch.ones(sim.x.shape[0], dtype=torch.bool)
    alone[i], alone[j] = False, False
    for node in torch.nonzero(alone)[:, 0].tolist():
        rows = slice(3 * node, 3 * node + 3)
        expected[rows, rows] = torch.linalg.inv(dense[rows, rows])
    for a, b in zip(i.tolist(), j.tolist()):
        rows = torch.tensor([3 * a, 3 * a + 1, 3 * a + 2, 3 * b, 3 * b + 1, 3 * b + 2])
        expected[rows[:, None], rows[None, :]] = torch.linalg.inv(dense[rows[:, None], rows[None, :]])
    tiny = 1e-12 * float(expected.abs().max())
    for k, (a, b) in enumerate(zip(i.tolist(), j.tolist())):
        torch.testing.assert_close(paired.blocks[k], expected[3 * a:3 * a + 3, 3 * b:3 * b + 3], rtol=1e-9, atol=tiny)
    torch.testing.assert_close(jacobi.inverse_blocks, torch.stack(
        [expected[3 * v:3 * v + 3, 3 * v:3 * v + 3] for v in range(sim.x.shape[0])]), rtol=1e-9, atol=tiny)
    # the same from the loaded PairStiffness's buffers (padded to their capacity), as a step loads it
    padded = BlockJacobi().load(blocks, PairTerms(stiffness.nodes, stiffness.coef, stiffness.pair_matrices,
                                                  stiffness.key), node_object, sim.system.free, capture=True)
    assert stiffness.capacity > len(pairs)
    torch.testing.assert_close(padded.inverse_blocks, jacobi.inverse_blocks, rtol=1e-12, atol=tiny)
    torch.testing.assert_close(padded.paired.blocks[:i.numel()], paired.blocks[:i.numel()], rtol=1e-12, atol=tiny)
    assert torch.equal(padded.paired.nodes[:i.numel()], paired.nodes[:i.numel()])
    assert bool((padded.paired.nodes[i.numel():] == -1).all())
    gen = torch.Generator().manual_seed(2)
    r = torch.randn(sim.x.shape, generator=gen, dtype=DT)
    want = (expected @ r.reshape(-1)).view_as(r)
    torch.testing.assert_close(jacobi(r), want, rtol=1e-9, atol=1e-12)
    # the op (the CG's): one object holding both bodies, active; rz = r.D r + the pairs' part = r.z
    plan = ChunkPlan.from_segments(Segments.from_lengths([sim.x.shape[0]]), 4)
    s = CGState.empty(plan, tuple(r.shape), DT, "cpu")
    s.rr.fill_(float((r * (jacobi.inverse_blocks @ r[:, :, None])[:, :, 0]).sum()))
    z = (jacobi.inverse_blocks @ r[:, :, None])[:, :, 0].contiguous()
    rz, item_ptr = torch.ones(1, dtype=DT), torch.tensor([0, i.numel()])
    for native in (None, cg_ops.native_ops_for(r)):
        out, rz_out = z.clone(), rz.clone()
        cg_ops.pair_term(r, out, paired.nodes, paired.blocks, item_ptr, rz_out, paired.dots, s, True, native)
        torch.testing.assert_close(out, want, rtol=1e-9, atol=1e-12)
        torch.testing.assert_close(rz_out, (r * want).sum().reshape(1), rtol=1e-9, atol=0)
        torch.testing.assert_close(s.beta, rz_out, rtol=1e-12, atol=0)  # beta = rz_new / 1


def test_paired_blocks_take_fewer_iterations_to_the_same_step():
    """The pile's case in small: a block resting on another on a floor, their faces' nodes
    facing each other; the default (pairs merged) and each node's own block step to the same
    velocities (1e-9; every solve to cg_tol: a contact check reading a paused solve would see
    each preconditioner's own), the merged blocks in fewer CG iterations."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    low = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=DT)
    high = tm.TetMesh(low.vertices + torch.tensor([0.0, 0.0, 0.1], dtype=DT), low.elements)
    out = []
    for paired in (True, False):
        sim = tm.Simulator([tm.Body(low, material), tm.Body(high, material)], dt=0.005,
                           planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(check_tol=None),
                           rayleigh_mass=1.0, cg_tol=1e-10, cuda_graphs=False, paired_blocks=paired)
        iterations = sum(int(sim.step().cg_iterations.max()) for _ in range(3))
        out.append((sim.v.clone(), iterations, len(sim.body_contact.detect(sim.x))))
    assert out[0][2] > 0  # in contact
    torch.testing.assert_close(out[0][0], out[1][0], rtol=1e-9, atol=1e-9)
    assert out[0][1] < out[1][1]


def test_paired_blocks_setting_is_checked_and_read_from_scene_files(tmp_path):
    mesh = tm.beam_mesh(1, 1, 1, dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3))
    with pytest.raises(tm.SceneError, match="paired_blocks must be True or False, got 'yes'"):
        tm.Simulator([body], paired_blocks="yes")
    assert tm.Simulator([body]).options.paired_blocks is True
    scene = tmp_path / "unpaired.toml"
    scene.write_text('[solver]\npaired_blocks = false\n\n[[bodies]]\nmesh = { generator = "beam", cells = [1, 1, 1] }\n'
                     'material = { young = 1e5, poisson = 0.3, density = 1000 }\n')
    assert tm.load_scene(scene).simulator.options.paired_blocks is False
    scene.write_text(scene.read_text().replace("false", '"no"'))
    with pytest.raises(tm.SceneError, match="paired_blocks"):
        tm.load_scene(scene)
