"""The multigrid preconditioner (solver.multigrid) and preconditioned CG (solver.cg): the
assembled rest matrix against the step's product (float64, every group kind), the V-cycle a
symmetric positive definite operator (dense), preconditioned CG against dense solves and plain
CG, per object in a batch, the step with multigrid against the plain step on the CPU extension
and pure torch, CUDA against the CPU, the hierarchy rebuilt after a cut, scene files and bad
input."""
import dataclasses
import sys

import numpy as np
import pytest
import torch
from conftest import GROUP_CASES, beam_scene_file, group_meshes, on_each_cpu_backend

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.solver import multigrid
from tensormass_torch.solver.cg import CGSolver, batched_cg
from tensormass_torch.solver.implicit_euler import _coefficients
from tensormass_torch.solver.preconditioner import MultigridSolve, system_multigrid

pytest.importorskip("pyamg")
DT = torch.float64


def beam_sim(cells=(12, 3, 3), model="hooke", young=1e5, preconditioner="multigrid", device="cpu", **options):
    """A beam 1 x 0.25 x 0.25 m held at x = 0 under gravity (float64)."""
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=young, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] == 0)
    options = {"cg_tol": 1e-10, "cuda_graphs": False, **options}
    return tm.Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), preconditioner=preconditioner, device=device,
                        **options)


@pytest.mark.parametrize("kind,model,form", GROUP_CASES)
def test_the_rest_matrix_is_the_steps_product_at_rest(kind, model, form):
    """c_M M + c_K K_rest assembled from the groups' edge blocks equals the step's product at
    rest on free rows and is the identity on fixed ones."""
    mesh = group_meshes()[kind]
    fixed = mesh.vertices[:, 0] == 0
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000, model=model), fixed=fixed)
    sim = tm.Simulator([body], dt=0.01, cuda_graphs=False, form=form)
    assert sim.model.groups[0].form == form
    system = sim.system
    mass_coef, stiffness_coef = _coefficients(sim.options)
    edges, blocks = sim.model.rest_stiffness_edges()
    matrix = multigrid.rest_system_matrix(edges, blocks, system.mass, mass_coef, stiffness_coef, system.free)
    gen = torch.Generator().manual_seed(1)
    p = torch.randn(sim.x.shape, generator=gen, dtype=DT)
    assembled = torch.from_numpy(matrix @ p.reshape(-1).numpy()).reshape(p.shape)
    free = system.free
    product = mass_coef * system.mass * (p * free) - stiffness_coef * sim.model.dforce(sim.model.rest, p * free)
    torch.testing.assert_close(assembled * free, product * free, rtol=1e-12, atol=1e-12 * float(product.abs().max()))
    torch.testing.assert_close(assembled[fixed], p[fixed], rtol=0, atol=0)


def dense_of(operator, n, dtype=DT):
    """The matrix ``[n, n]`` of a linear map on ``[n/3, 3]`` fields."""
    eye = torch.eye(n, dtype=dtype)
    return torch.stack([operator(eye[i].reshape(-1, 3)).reshape(-1) for i in range(n)], dim=1)


def test_the_v_cycle_is_symmetric_positive_definite():
    """With three levels, the cycle (on the hierarchy's fine operator, and on the step's own
    product with a floor's stiffness) is a symmetric positive definite matrix on the free nodes."""
    sim = beam_sim(cells=(16, 2, 2), planes=[tm.Plane((0, 0, 1), 0.05, 1e5)])
    system = sim.system
    mass_coef, stiffness_coef = _coefficients(sim.options)
    edges, blocks = sim.model.rest_stiffness_edges()
    matrix = multigrid.rest_system_matrix(edges, blocks, system.mass, mass_coef, stiffness_coef, system.free)
    cycle = multigrid.Multigrid(matrix, multigrid.rigid_body_modes(sim.model.rest), DT, "cpu", coarse_size=30)
    assert len(cycle.sizes) == 3, cycle.sizes
    free = system.free.expand(-1, 3).reshape(-1) > 0
    n = sim.x.numel()
    plain = dense_of(cycle, n)[free][:, free]
    fused = system.system_matvec(mass_coef, stiffness_coef)
    fused.load(sim.x + torch.tensor([0.0, 0.0, -0.06], dtype=DT))  # some nodes below the floor
    assert float(fused.node_stiffness.abs().max()) > 0
    solve = MultigridSolve(cycle).load(fused, stiffness_coef * fused.node_stiffness, system.free)
    own = dense_of(lambda r: solve(r * system.free), n)[free][:, free]
    for operator in (plain, own):
        torch.testing.assert_close(operator, operator.T, rtol=0, atol=1e-10 * float(operator.abs().max()))
        assert float(torch.linalg.eigvalsh(operator).min()) > 0


def test_a_node_stiffness_reaches_every_coarse_level():
    """``Multigrid.load(N)``: each coarse operator becomes the Galerkin product of the level above
    with N added at the finest (dense float64), the coarsest inverse that of its operator; fixed
    nodes' blocks are left out; ``load(None)`` restores the rest operators."""
    sim = beam_sim(cells=(16, 2, 2))
    system = sim.system
    mass_coef, stiffness_coef = _coefficients(sim.options)
    edges, blocks = sim.model.rest_stiffness_edges()
    matrix = multigrid.rest_system_matrix(edges, blocks, system.mass, mass_coef, stiffness_coef, system.free)
    cycle = multigrid.Multigrid(matrix, multigrid.rigid_body_modes(sim.model.rest), DT, "cpu", coarse_size=30)
    rest = [level.matrix.to_dense().clone() for level in cycle.levels] + [cycle.coarse_inverse.clone()]
    gen = torch.Generator().manual_seed(3)
    n = torch.randn(sim.x.shape[0], 3, 3, generator=gen, dtype=DT)
    node_stiffness = n @ n.transpose(1, 2)
    node_stiffness[1::3] = 0  # nodes without a penalty
    cycle.load(node_stiffness, system.free)
    free = system.free.reshape(-1)
    kept = (node_stiffness * free[:, None, None]).numpy()
    import scipy.sparse as sp

    operator = torch.from_numpy((matrix + sp.block_diag(list(kept), format="csr")).toarray())
    for depth, level in enumerate(cycle.levels):
        if depth > 0:
            torch.testing.assert_close(level.matrix.to_dense(), operator, rtol=1e-12, atol=1e-12 * float(
                operator.abs().max()))
            bound = 1.0 / level.inverse_diagonal.reshape(-1)  # l1-Jacobi's scaling: at least each row's l1
            assert bool((bound >= operator.abs().sum(1) * (1 - 1e-12)).all())
        operator = level.restrict.to_dense() @ operator @ level.prolong.to_dense()
    torch.testing.assert_close(cycle.coarse_inverse, torch.linalg.inv(operator), rtol=1e-9, atol=1e-9 * float(
        cycle.coarse_inverse.abs().max()))
    cycle.load(None)
    for before, level in zip(rest[1:], cycle.levels[1:]):
        assert torch.equal(level.matrix.to_dense(), before)
    torch.testing.assert_close(cycle.coarse_inverse, rest[-1], rtol=1e-12, atol=0)


def test_a_floor_costs_few_iterations(monkeypatch):
    """A beam lying on a stiff floor: with the floor's stiffness in the coarse levels, a step takes
    the iterations of a free one; without (``Multigrid.load`` a no-op), several times more."""
    iterations = {}
    for update in (True, False):
        if not update:
            monkeypatch.setattr(multigrid.Multigrid, "load", lambda *args, **kwargs: None)
        mesh = tm.beam_mesh(48, 4, 4, size=(1.0, 0.1, 0.1), dtype=DT)
        body = tm.Body(mesh, tm.Material(young=1e6, poisson=0.3, density=1000.0), fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, preconditioner="multigrid", cg_tol=1e-8, cuda_graphs=False,
                           planes=[tm.Plane((0, 0, 1), 0.001, 1e6)])
        sim.step(2)
        assert len(sim.system._rest_preconditioner[1][2].sizes) == 2
        iterations[update] = int(sim.last_report.cg[0].iterations.max())
    assert iterations[True] <= 20 and 3 * iterations[True] < iterations[False], iterations


def contact_pile(preconditioner, dtype=DT, cg_tol=1e-4):
    """Eight blocks (4 x 4 x 2 cells, 0.2 x 0.2 x 0.1 m) in four offset columns of two, 3 cm apart,
    dropped onto a floor with contact between them (the benchmarks' piles, small)."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    block = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=dtype)
    bodies = [tm.Body(tm.TetMesh(block.vertices + torch.tensor([0.25 * i + 0.01 * k, 0.25 * j, 0.02 + 0.13 * k],
                                                                dtype=dtype), block.elements), material)
              for i in range(2) for j in range(2) for k in range(2)]
    return tm.Simulator(bodies, dt=0.005, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(),
                        rayleigh_mass=1.0, dtype=dtype, cg_tol=cg_tol, preconditioner=preconditioner,
                        cuda_graphs=False)


def test_pairs_bound_their_rows_for_the_smoothers():
    """ContactPairs.stiffness_row_l1 is each pair's assembled rows' l1 norms (a pair alone, with
    friction), bounds the sum of many pairs' and exceeds their diagonal where they couple nodes:
    the smoothers' l1-Jacobi scaling needs the bound, not the diagonal."""
    sim = contact_pile("multigrid")
    sim.step(24)  # the upper blocks rest on the lower ones
    pairs = sim.body_contact.detect(sim.x, sim.v, sim.options.dt)
    assert len(pairs) > 20
    pairs = dataclasses.replace(pairs, friction=torch.rand(len(pairs), generator=torch.Generator().manual_seed(0),
                                                           dtype=DT))
    n = sim.x.numel()

    def assembled(chosen):
        eye = torch.eye(n, dtype=DT)
        return torch.stack([(chosen.dforces(eye[i].view(-1, 3)) + 0.3 * chosen.friction_forces(eye[i].view(-1, 3)))
                            .reshape(-1) for i in range(n)], dim=1).neg()

    one = pairs.select(torch.tensor([3]))
    torch.testing.assert_close(one.stiffness_row_l1(1.0, 0.3).reshape(-1), assembled(one).abs().sum(1))
    bound = pairs.stiffness_row_l1(1.0, 0.3).reshape(-1)
    matrix = assembled(pairs)
    assert bool((bound >= matrix.abs().sum(1) * (1 - 1e-12)).all())
    assert float((matrix.abs().sum(1) - matrix.diagonal()).max()) > 0.5 * float(matrix.diagonal().max())


def test_a_pile_in_contact_converges_with_multigrid():
    """Contact pairs couple nodes across bodies: with the pairs' diagonal in place of their rows'
    l1 norms in the finest smoother's scaling, D^-1 A left the Chebyshev interval and this pile's
    CG stalled. Now each solve converges in a few tens of iterations, and the steps are block
    Jacobi's to the solves' tolerance (solved to 1e-12: at 1e-8, the two trajectories part by
    millimetres within a few steps of contact, the stiff system amplifying the solves' error)."""
    steps = {}
    for preconditioner in ("multigrid", "auto"):
        sim = contact_pile(preconditioner, cg_tol=1e-12)
        most = pairs = 0
        for _ in range(22):
            report = sim.step()
            most = max(most, max(int(c.iterations.max()) for c in report.cg))
            pairs = max(pairs, len(report.contact_solves[-1][0]))
        assert pairs > 20  # the blocks met
        steps[preconditioner] = (sim.x, most)
    assert steps["multigrid"][1] < 60, steps["multigrid"][1]
    torch.testing.assert_close(steps["multigrid"][0], steps["auto"][0], rtol=0, atol=1e-10)


def test_a_failed_coarse_update_is_one_clear_error_and_changes_nothing(monkeypatch):
    """Where the sparse products that carry the floor's penalty into the coarse levels fail (cuSPARSE's
    SpGEMM out of resources on a GPU pile of hundreds of blocks), the step raises one SolverError
    that names the preconditioner and the way out, the state as it was and the levels at the
    rest's; the next step without the failure is the step of a simulator that never failed, bit
    for bit."""
    from tensormass_torch.solver.multigrid import Multigrid

    sim, twin = contact_pile("multigrid"), contact_pile("multigrid")
    sim.step(20)  # the lower blocks on the floor
    twin.step(20)
    x, v = sim.x.clone(), sim.v.clone()
    galerkin = Multigrid._galerkin

    def failing(level, delta):
        raise RuntimeError("CUDA error: insufficient resources when calling `cusparseSpGEMM_compute(...)`")

    monkeypatch.setattr(Multigrid, "_galerkin", staticmethod(failing))
    with pytest.raises(tm.SolverError, match=r"preconditioner='multigrid' could not carry .* "
                                             r"insufficient resources.*preconditioner='auto'"):
        sim.step()
    assert torch.equal(sim.x, x) and torch.equal(sim.v, v)
    monkeypatch.setattr(Multigrid, "_galerkin", staticmethod(galerkin))
    sim.step()
    twin.step()
    assert torch.equal(sim.x, twin.x)
    # a load that failed is never taken for the last one: the same penalty loads again after it
    solve = sim.system._multigrid_solve
    doubled = 2.0 * solve._node_stiffness
    solve.load(solve.product, doubled, sim.system.free)
    expected = solve.multigrid.coarse_inverse.clone()
    solve.load(solve.product, 0.5 * doubled, sim.system.free)
    monkeypatch.setattr(Multigrid, "_galerkin", staticmethod(failing))
    with pytest.raises(tm.SolverError):
        solve.load(solve.product, doubled, sim.system.free)
    monkeypatch.setattr(Multigrid, "_galerkin", staticmethod(galerkin))
    solve.load(solve.product, doubled, sim.system.free)
    assert torch.equal(solve.multigrid.coarse_inverse, expected)


def test_one_scene_steps_the_same_with_multigrid_twice():
    """pyamg draws its spectral radius estimates' start vectors from numpy's global generator: the
    hierarchy's build seeds it (and puts the caller's state back), so two simulators of one scene
    step to the same positions bit for bit (docs/preconditioners.md)."""
    np.random.seed(1)
    expected = np.random.rand(3)
    np.random.seed(1)
    runs = []
    for _ in range(2):
        sim = contact_pile("multigrid")
        sim.step(3)
        runs.append(sim.x)
    assert torch.equal(runs[0], runs[1])
    np.testing.assert_array_equal(np.random.rand(3), expected)  # the caller's generator, untouched


def test_preconditioned_cg_matches_a_dense_solve_per_object():
    """Two objects of a packed batch (one soft, one 100x stiffer, different sizes) solved together:
    each matches its dense solve and needs a fraction of plain CG's iterations; an object whose
    right-hand side is zero stops at once."""
    meshes = [tm.beam_mesh(10, 2, 2, size=(1.0, 0.2, 0.2), dtype=DT), tm.beam_mesh(6, 3, 2, size=(0.6, 0.3, 0.2),
                                                                                    dtype=DT)]
    bodies = [tm.Body(m, tm.Material(young=e, poisson=0.3, density=1000.0), fixed=m.vertices[:, 0] == 0)
              for m, e in zip(meshes, (1e5, 1e7))]
    sim = tm.Simulator(bodies, dt=0.01, cuda_graphs=False, preconditioner="multigrid")
    system = sim.system
    mass_coef, stiffness_coef = _coefficients(sim.options)
    fused = system.system_matvec(mass_coef, stiffness_coef)
    fused.load(sim.x)
    cycle = system_multigrid(system, mass_coef, stiffness_coef, sim.x)
    gen = torch.Generator().manual_seed(2)
    rhs = torch.randn(sim.x.shape, generator=gen, dtype=DT) * system.free
    n = sim.x.numel()
    dense = dense_of(lambda p: fused(p)[0], n)
    free = system.free.expand(-1, 3).reshape(-1) > 0
    expected = torch.zeros(n, dtype=DT)
    expected[free] = torch.linalg.solve(dense[free][:, free], rhs.reshape(-1)[free])
    pcg = batched_cg(fused, rhs, system.segments, system.free, tol=1e-12, max_iter=500, preconditioner=cycle)
    plain = batched_cg(fused, rhs, system.segments, system.free, tol=1e-12, max_iter=5000)
    assert pcg.status() == ["converged", "converged"]
    torch.testing.assert_close(pcg.solution.reshape(-1), expected, rtol=0, atol=1e-9 * float(expected.abs().max()))
    assert all(3 * int(a) < int(b) for a, b in zip(pcg.iterations, plain.iterations)), (pcg.iterations,
                                                                                        plain.iterations)
    # an object with nothing to solve stops at the start; the other's iterates are its own
    ptr = system.segments.ptr.tolist()
    half = rhs.clone()
    half[ptr[1]:] = 0
    solver = CGSolver(system.segments, rhs.shape, DT, "cpu", system.free, cuda_graphs=False)
    one = solver.solve(fused, half, tol=1e-12, max_iter=500, preconditioner=cycle)
    assert one.iterations[1] == 0 and one.status()[1] == "converged"
    alone = batched_cg(fused, half, Segments.single(sim.x.shape[0]), system.free, tol=1e-12, max_iter=500,
                       preconditioner=cycle)
    torch.testing.assert_close(one.solution, alone.solution, rtol=0, atol=1e-9 * float(alone.solution.abs().max()))


@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
def test_a_multigrid_step_is_the_plain_step(model):
    """Steps with multigrid (a floor, Rayleigh damping) land where plain CG's do; with far fewer
    iterations."""
    runs, iterations = [], []
    for preconditioner in ("none", "multigrid"):
        sim = beam_sim(model=model, preconditioner=preconditioner, rayleigh_mass=0.1, rayleigh_stiffness=0.001,
                       planes=[tm.Plane((0, 0, 1), -0.02, 1e4)])
        sim.step(15)
        runs.append(sim.x.clone())
        iterations.append(int(sim.last_report.cg[0].iterations.max()))
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)
    assert 2 * iterations[1] < iterations[0], iterations


def test_the_cpu_extension_and_pure_torch_agree(monkeypatch):
    def run():
        sim = beam_sim(model="corotational", planes=[tm.Plane((0, 0, 1), -0.02, 1e4)])
        sim.step(10)
        return sim.x.clone()

    extension, pure = on_each_cpu_backend(monkeypatch, run)
    torch.testing.assert_close(extension, pure, rtol=0, atol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
@pytest.mark.parametrize("warm_start", [False, True, "project"])
def test_cuda_matches_the_cpu(model, warm_start):
    """The preconditioned steps on CUDA (captured in graphs: the right-hand side, the start and
    the predicted iterations, then one iteration a look) equal the CPU's in float64, with and
    without warm starts, on and off the floor."""
    runs = []
    for device in ("cpu", "cuda"):
        sim = beam_sim(model=model, device=device, cuda_graphs=True, planes=[tm.Plane((0, 0, 1), -0.02, 1e4)],
                       warm_start=warm_start)
        sim.step(20)
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)
    graphs = [g for g in sim.system._step_graphs.values() if g.preconditioned]
    assert len(graphs) == 1 and sum(1 for k, g in graphs[0]._graphs.items() if g) >= 2  # replayed, not eager


def test_the_hierarchy_follows_a_cut_and_the_coefficients():
    sim = beam_sim(cells=(8, 2, 2))
    sim.step()
    first = sim.system._rest_preconditioner[1][2]
    sim.step()
    assert sim.system._rest_preconditioner[1][2] is first  # kept from step to step
    sim.remove_elements(0, torch.arange(0, 12))
    sim.step()
    assert sim.system._rest_preconditioner[1][2] is not first
    cut = sim.system._rest_preconditioner[1][2]
    sim.options = dataclasses.replace(sim.options, dt=0.005)
    sim.step()
    assert sim.system._rest_preconditioner[1][2] is not cut


def test_scene_file_and_bad_input(tmp_path, monkeypatch):
    path = beam_scene_file(tmp_path / "multigrid.toml", 'preconditioner = "multigrid"', cells=(6, 2, 2))
    scene = tm.load_scene(path)
    assert scene.simulator.options.preconditioner == "multigrid"
    scene.simulator.step(2)
    with pytest.raises(tm.SceneError, match="preconditioner must be one of 'auto', 'none', 'jacobi', 'rigid', 'multigrid', 'cholesky', "
                                            "got 'amg'"):
        beam_sim(preconditioner="amg")
    sim = beam_sim(cells=(4, 1, 1))
    x = sim.x.clone()
    monkeypatch.setitem(sys.modules, "pyamg", None)  # as if it were not installed
    with pytest.raises(tm.SceneError, match="builds its hierarchy with pyamg, which is not installed"):
        sim.step()
    assert torch.equal(sim.x, x) and sim.steps_done == 0
    monkeypatch.delitem(sys.modules, "pyamg")
    monkeypatch.setattr(multigrid, "MAX_DIRECT", 10)
    with pytest.raises(tm.SceneError, match="could not coarsen this mesh below"):
        sim.step()
    assert torch.equal(sim.x, x)
