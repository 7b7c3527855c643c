"""A whole CG solve in one op (hooke_node_cg through SystemMatvec.solve_in_one_op / CGSolver.begin):
bitwise the op-by-op solve (start, then matvec-alpha, cg_update, cg_direction per iteration) in
every buffer of the CG state, per object of a batch whose objects stop at different iterations
(converged, capped, zero right-hand side, breakdown), for any split of the iterations between
calls; it stops once no object is active; bad inputs are rejected with nothing changed. On the
CPU (the CG ops' functions in a loop) and on CUDA when there is one (one persistent kernel)."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops import library, solve
from tensormass_torch.ops.variants import DEFAULT, KernelVariants
from tensormass_torch.solver.implicit_euler import SystemMatvec

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
pytestmark = pytest.mark.skipif(not library.ensure_registered() or not hasattr(torch.ops.tensormass, "hooke_node_cg"),
                                reason="needs the extension with hooke_node_cg")

FIELDS = ("x", "r", "p", "rr", "alpha", "beta", "threshold", "rhs_sq", "status", "iterations", "counter")


def make_scene(dtype, device, contact=True, bodies=3):
    """(system, x, rhs): hooke beams (tensor form) of stiffnesses 1e4, 1e5, ..., the positions x
    [V, 3] the matvecs are loaded at, and a right-hand side."""
    meshes = []
    for k in range(bodies):
        mesh = tm.beam_mesh(5 + 2 * k, 2, 2, size=(0.5, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.01), dtype=dtype,
                            device=device)
        mat = tm.Material(young=1e4 * 10 ** k, poisson=0.3, density=1000.0, model="hooke")
        meshes.append(tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9))
    planes = [tm.Plane((0.0, 0.0, 1.0), 0.02, 1e4)] if contact else None
    sim = tm.Simulator(meshes, dt=0.01, gravity=(0, 0, -9.81), planes=planes, form="tensor", device=device,
                       dtype=dtype)
    gen = torch.Generator().manual_seed(3)
    x = sim.x + 0.01 * torch.randn(sim.x.shape, generator=gen, dtype=dtype).to(device)
    rhs = torch.randn(sim.x.shape, generator=gen, dtype=dtype).to(device)
    return sim.system, x, rhs


def matvec_at(system, x, mass_coef=1.02, pipelined=True, variants=DEFAULT):
    """The system's matvec (c_M = mass_coef, c_K = 2e-4) loaded at x, with the CG (``pipelined``:
    whole GPU solves by the pipelined CG where it fits; False: the classic CG) and kernel variants
    given (as ``StepOptions`` pass them)."""
    return system.system_matvec(mass_coef, 2e-4, pipelined, variants).load(x)


def make_system(dtype, device, contact=True, bodies=3, mass_coef=1.02, pipelined=True, variants=DEFAULT):
    """(system, matvec, rhs) of :func:`make_scene`, the matvec as :func:`matvec_at` gives it."""
    system, x, rhs = make_scene(dtype, device, contact, bodies)
    return system, matvec_at(system, x, mass_coef, pipelined, variants), rhs


def classic_system(dtype, device, **changes):
    """:func:`make_system` with the classic CG (``pipelined=False``): these tests are
    hooke_node_cg's, and whole GPU solves would otherwise take the pipelined CG
    (solve.system_solve, tests/ops/test_pipelined_solve.py), which is not bitwise the op-by-op CG."""
    return make_system(dtype, device, pipelined=False, **changes)


def fresh_solver(system, rhs, chunk_nodes=None):
    from tensormass_torch.solver.cg import CGSolver

    return CGSolver(system.segments, rhs.shape, rhs.dtype, rhs.device, system.free, chunk_nodes=chunk_nodes,
                    cuda_graphs=False)


def state_of(cg):
    return {k: getattr(cg.state, k).clone() for k in FIELDS}


def op_by_op(system, matvec, rhs, tol, max_iter, counts, chunk_nodes=None):
    cg = fresh_solver(system, rhs, chunk_nodes)
    cg.start(matvec, rhs, None, tol, max_iter)
    for count in counts:
        for _ in range(count):
            cg._iterate(matvec, max_iter)
    return state_of(cg)


def in_one_op(system, matvec, rhs, tol, max_iter, counts, chunk_nodes=None):
    cg = fresh_solver(system, rhs, chunk_nodes)
    assert cg.solves_in_one_op(matvec)
    assert matvec.solve_in_one_op(cg, rhs, cg._effective_tol(tol, rhs.dtype), max_iter, counts[0])
    for count in counts[1:]:
        assert matvec.solve_in_one_op(cg, None, 0.0, max_iter, count)
    return state_of(cg)


def assert_same(got, want):
    for k in FIELDS:
        assert torch.equal(got[k], want[k]), k


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("counts", [(0,), (1,), (3,), (2, 5), (1, 1, 1, 4), (60,)])
@pytest.mark.parametrize("chunk_nodes", [None, 16])
def test_one_op_equals_op_by_op(device, dtype, counts, chunk_nodes):
    system, matvec, rhs = classic_system(dtype, device)
    tol, max_iter = 1e-5, 40  # the objects stop at different iterations; the cap stops some
    got = in_one_op(system, matvec, rhs, tol, max_iter, counts, chunk_nodes)
    want = op_by_op(system, matvec, rhs, tol, max_iter, counts, chunk_nodes)
    assert_same(got, want)
    if sum(counts) >= max_iter:  # every object stopped: converged or capped
        assert bool((got["status"] != cg_ops.ACTIVE).all())


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("chunk_nodes", [1, 7, 4096])
def test_chunkings_and_a_zero_rhs(device, chunk_nodes):
    """Objects over many chunks or one; an object with b = 0 is converged from the start."""
    system, matvec, rhs = classic_system(torch.float64, device, contact=False)
    rhs[system.segments.node_object == 1] = 0.0
    got = in_one_op(system, matvec, rhs, 1e-7, 600, (600,), chunk_nodes)
    want = op_by_op(system, matvec, rhs, 1e-7, 600, (600,), chunk_nodes)
    assert_same(got, want)
    assert got["status"].tolist() == [cg_ops.CONVERGED] * 3 and int(got["iterations"][1]) == 0


@pytest.mark.parametrize("device", DEVICES)
def test_breakdown_on_an_indefinite_system(device):
    system, matvec, rhs = classic_system(torch.float64, device, contact=False, mass_coef=-1.0)
    got = in_one_op(system, matvec, rhs, 1e-8, 50, (50,))
    want = op_by_op(system, matvec, rhs, 1e-8, 50, (50,))
    assert_same(got, want)
    assert bool((got["status"] == cg_ops.BREAKDOWN).any())


@pytest.mark.parametrize("device", DEVICES)
def test_stops_once_no_object_is_active(device):
    """After convergence the op returns without touching the state: a later call changes nothing."""
    system, matvec, rhs = classic_system(torch.float64, device)
    cg = fresh_solver(system, rhs)
    cg.begin(matvec, rhs, 1e-6, 500, 500)
    assert bool((cg.state.status == cg_ops.CONVERGED).all())
    before = state_of(cg)
    assert matvec.solve_in_one_op(cg, None, 0.0, 500, 100)
    assert_same(state_of(cg), before)


@pytest.mark.parametrize("device", DEVICES)
def test_solve_uses_one_op_and_matches(monkeypatch, device):
    system, matvec, rhs = classic_system(torch.float32, device)
    calls = []
    original = SystemMatvec.solve_in_one_op
    monkeypatch.setattr(SystemMatvec, "solve_in_one_op",
                        lambda self, *a: calls.append(a[1] is not None) or original(self, *a))
    one = system.cg_solver(rhs, cuda_graphs=False).solve(matvec, rhs, tol=1e-5, max_iter=300, check_every=4)
    assert calls == [True], "the whole solve is one call, started there"
    monkeypatch.setattr(SystemMatvec, "solves_in_one_op", lambda self, cg: False)
    monkeypatch.setattr(SystemMatvec, "solve_in_one_op", lambda self, *a: False)
    system._cg = None
    plain = system.cg_solver(rhs, cuda_graphs=False).solve(matvec, rhs, tol=1e-5, max_iter=300, check_every=4)
    assert torch.equal(one.solution, plain.solution) and torch.equal(one.iterations, plain.iterations)
    assert bool(one.converged.all())


def test_not_served_elsewhere():
    """Other models, the padded layout, a gradient wanted: no one-op path (the caller iterates)."""
    system, x, rhs = make_scene(torch.float64, "cpu")
    cg = fresh_solver(system, rhs)
    padded = matvec_at(system, x, pipelined=False, variants=KernelVariants(hooke_matvec="padded"))
    assert not cg.solves_in_one_op(padded)
    before = state_of(cg)
    assert not padded.solve_in_one_op(cg, rhs, 1e-6, 10, 10)
    assert_same(state_of(cg), before)
    matvec = matvec_at(system, x, pipelined=False, variants=KernelVariants(hooke_matvec="node"))
    assert cg.solves_in_one_op(matvec)
    assert not matvec.solve_in_one_op(cg, rhs.clone().requires_grad_(), 1e-6, 10, 10)


def test_bad_inputs_are_rejected():
    system, matvec, rhs = classic_system(torch.float64, "cpu")
    cg = fresh_solver(system, rhs)
    cg.start(matvec, rhs, None, 1e-6, 10)
    s = cg.state
    group = system.model.groups[0]
    before = state_of(cg)

    def call(state=s, rhs_=rhs, count=5, max_iter=10):
        solve.system_cg(group, system.mass.reshape(-1), system.free.reshape(-1), 1.0, 1e-4, matvec.node_stiffness,
                        torch.empty_like(s.p), rhs_, 1e-6, cg.plan.tensors(), state, max_iter, count)

    bad = lambda **kw: cg_ops.CGState(**{**s.__dict__, **kw})  # noqa: E731
    with pytest.raises(RuntimeError, match="work has shape"):
        call(state=bad(work=s.work[:-1]))
    with pytest.raises(RuntimeError, match="sums has shape"):
        call(state=bad(sums=s.sums[:1]))
    with pytest.raises(RuntimeError, match="rr_swap is Float"):
        call(state=bad(rr_swap=s.rr_swap.float()))
    with pytest.raises(RuntimeError, match="rhs has shape"):
        call(rhs_=rhs[:-1])
    with pytest.raises(RuntimeError, match="count must be >= 0"):
        call(count=-1)
    with pytest.raises(RuntimeError, match="max_iter must be >= 0"):
        call(max_iter=-2)
    assert_same(state_of(cg), before)  # nothing changed


def test_gpu_plans_beyond_one_wave_iterate_op_by_op(monkeypatch):
    """On a GPU the one-op path needs every chunk resident at once (a persistent block each)."""
    class Props:
        multi_processor_count = 132

    monkeypatch.setattr(torch.cuda, "get_device_properties", lambda device: Props())
    cuda = torch.device("cuda", 0)
    limit = solve.PERSISTENT_BLOCKS_PER_SM * 132
    assert solve.persistent_cg_fits(cuda, limit) and not solve.persistent_cg_fits(cuda, limit + 1)
    assert solve.persistent_cg_fits(torch.device("cpu"), 10 ** 9)
