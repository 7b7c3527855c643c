"""The pipelined whole CG solve (hooke_node_solve through solve.system_solve: Chronopoulos-Gear's
CG, one reduction and one grid barrier an iteration, one persistent kernel on the GPU).

Its oracle is the two-reduction CG op by op (CGSolver.start + _iterate) in float64: the same
iterates in exact arithmetic, so the solutions agree to rounding and the statuses (converged,
capped, breakdown, b = 0) and iteration counts per object of a batch are the same. It runs where
whole solves run (CGSolver.begin/solve, implicit steps); elsewhere (the CPU, a plan beyond one
wave of the GPU) the op returns False having changed nothing; a chunk beyond the layout its
caller promised ends its object as non-finite; bad inputs are rejected with nothing changed. Where
an implicit step asks (solve.StepEnd), the same kernel also ends the step (hooke_node_solve_step):
bitwise what euler_update after the solve gives.

The switches are the solver's configuration, passed down explicitly: the matvec's ``pipelined``
(``StepOptions.pipelined``; False: the classic CG) and kernel variants (``KernelVariants``: the
layouts tried, the streamed layout's cache and pairing, the step end in the solve, the rows' window)."""
from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import with_variants
from test_cg_solve_in_one_op import FIELDS, fresh_solver, make_scene, make_system, matvec_at, op_by_op, state_of

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops import library, node_graph, solve
from tensormass_torch.ops.segments import ChunkPlan
from tensormass_torch.ops.variants import PIPELINED_LAYOUTS, KernelVariants
from tensormass_torch.sim import builtin as scenes

pytestmark = pytest.mark.skipif(not library.ensure_registered() or not hasattr(torch.ops.tensormass, "hooke_node_solve"),
                                reason="needs the extension with hooke_node_solve")
gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="the pipelined solve is a GPU kernel")


@pytest.fixture(params=["shared", "streamed", "streamed-uncached", "streamed-partly", "streamed-unpaired"])
def layout_variants(request):
    """The kernel variants of each layout of the pipelined solve's graph, alone
    (``pipelined_layouts`` narrowed to it); the streamed one also with none of its slots in shared
    memory, with only each node's first 3 neighbours and Kdir blocks there
    (``stream_cache_slots``): both paths in one node, and with each thread walking its node's
    slots alone (``stream_pairs=False``)."""
    name, _, variant = request.param.partition("-")
    changes = {}
    if variant == "unpaired":
        changes["stream_pairs"] = False
    elif variant:
        changes["stream_cache_slots"] = 0 if variant == "uncached" else 3
    return KernelVariants(pipelined_layouts=(name,), **changes)


@pytest.fixture
def layout(layout_variants):
    """The name of the one layout of ``layout_variants``."""
    (name,) = layout_variants.pipelined_layouts
    return name


def ran_layout(cg):
    """The layout the pipelined op ran in on ``cg``'s state, or None where it did not run."""
    work = cg.state.__dict__.get("_solve_work")
    return None if work is None else work.layout


def pipelined(system, matvec, rhs, tol, max_iter):
    """A whole solve through CGSolver.begin; asserts that it ran as the pipelined op."""
    cg = fresh_solver(system, rhs)
    cg.begin(matvec, rhs, tol, max_iter, max_iter)
    assert ran_layout(cg) is not None, "the solve did not take the pipelined op"
    return state_of(cg)


def reference(rhs, tol, max_iter, contact=False, mass_coef=1.02):
    """The float64 two-reduction CG on the same system."""
    system, matvec, _ = make_system(torch.float64, rhs.device, contact=contact, mass_coef=mass_coef)
    return op_by_op(system, matvec, rhs.double(), tol, max_iter, (max_iter,))


def rel(a, b):
    return float((a.double() - b.double()).norm() / b.double().norm().clamp_min(1e-300))


@gpu
@pytest.mark.parametrize("tol,max_iter", [(1e-8, 300), (0.0, 10), (0.0, 1)])
def test_float64_matches_the_two_reduction_cg(layout_variants, tol, max_iter):
    system, matvec, rhs = make_system(torch.float64, "cuda", contact=False, variants=layout_variants)
    got = pipelined(system, matvec, rhs, tol, max_iter)
    want = reference(rhs, tol, max_iter)
    # converged solves agree to what the tolerance leaves (x differs by ~ cond * tol * rounding of the
    # last steps); fixed budgets to rounding
    assert rel(got["x"], want["x"]) < (1e-7 if tol else 1e-10)
    # r against b: both converged r are below tol |b|, their difference too
    assert float((got["r"] - want["r"]).norm()) < (tol if tol else 1e-10) * float(want["rhs_sq"].sum().sqrt())
    assert torch.equal(got["status"], want["status"])
    # a converged object may cross the threshold one iteration apart (r.r rounded differently
    # right at it); a fixed budget runs the same count
    slack = 1 if tol else 0
    assert int((got["iterations"] - want["iterations"]).abs().max()) <= slack
    assert torch.allclose(got["rhs_sq"], want["rhs_sq"], rtol=1e-12)
    assert torch.allclose(got["threshold"], want["threshold"], rtol=1e-12)


def started_from(system, matvec, rhs, guess, tol, max_iter):
    """A solver that :meth:`CGSolver.start` left at ``guess`` (r = b - A guess, the threshold
    relative to b)."""
    cg = fresh_solver(system, rhs)
    cg.start(matvec, rhs, guess, tol, max_iter)
    return cg


@gpu
@pytest.mark.parametrize("guess_tol", [1e-2, 1e-12])
@pytest.mark.parametrize("tol,max_iter", [(1e-8, 300), (0.0, 10)])
def test_from_a_guess_matches_the_two_reduction_cg_from_it(layout_variants, tol, max_iter, guess_tol):
    """A warm start (CGSolver.start from a guess, then iterate(started=True)) goes on by the
    pipelined op from the start's iterate: float64, against the two-reduction CG from the same
    start; the threshold and b.b are the start's (relative to b, not to the guess's residual). A
    guess already within tol stops at the start (0 iterations, x the guess)."""
    system, matvec, rhs = make_system(torch.float64, "cuda", contact=False, variants=layout_variants)
    guess = op_by_op(system, matvec, rhs, guess_tol, 1000, (1000,))["x"]
    cg = started_from(system, matvec, rhs, guess, tol, max_iter)
    started = state_of(cg)
    cg.iterate(matvec, max_iter, max_iter, started=True)
    assert ran_layout(cg) is not None, "the warm solve did not take the pipelined op"
    got = state_of(cg)
    ref = started_from(system, matvec, rhs, guess, tol, max_iter)
    for _ in range(max_iter):
        ref._iterate(matvec, max_iter)
    want = state_of(ref)
    assert torch.equal(got["rhs_sq"], started["rhs_sq"]) and torch.equal(got["threshold"], started["threshold"])
    assert torch.equal(got["status"], want["status"])
    slack = 1 if tol else 0
    assert int((got["iterations"] - want["iterations"]).abs().max()) <= slack
    assert rel(got["x"], want["x"]) < (1e-7 if tol else 1e-10)
    assert float((got["r"] - want["r"]).norm()) < (tol if tol else 1e-10) * float(want["rhs_sq"].sum().sqrt())
    if tol and guess_tol < tol:  # within tol from the start
        assert got["status"].tolist() == [cg_ops.CONVERGED] * 3 and int(got["iterations"].max()) == 0
        assert torch.equal(got["x"], guess)


@gpu
@pytest.mark.parametrize("cuda_graphs", [True, False])
@pytest.mark.parametrize("warm_start", ["extrapolate", "project"])
def test_warm_steps_take_it_and_match_the_classic_cg(monkeypatch, warm_start, cuda_graphs):
    """Implicit steps with a warm start on the GPU, captured or eager, run the pipelined op from
    the guess: the same trajectory to the tolerance as the classic CG's (pipelined=False), in as
    many iterations to one a step."""
    original, warm_solves = solve.system_solve, []

    def recorded(*args, **kwargs):
        ran = original(*args, **kwargs)
        if kwargs.get("from_iterate"):
            warm_solves.append(ran)
        return ran

    monkeypatch.setattr(solve, "system_solve", recorded)
    runs = []
    for pipelined in (True, False):
        warm_solves.clear()
        mesh = tm.beam_mesh(12, 3, 3, size=(1.0, 0.25, 0.25), dtype=torch.float64, device="cuda")
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke"),
                       fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, warm_start=warm_start, cg_tol=1e-10, cuda_graphs=cuda_graphs,
                           rayleigh_mass=0.1, device="cuda", dtype=torch.float64)
        sim.options = dataclasses.replace(sim.options, pipelined=pipelined)
        counts = []
        for _ in range(8):
            sim.step()
            counts.append(int(sim.last_report.cg[0].iterations.max()))
        assert (warm_solves and all(warm_solves)) if pipelined else not warm_solves, warm_solves
        runs.append((sim.x.clone(), counts))
    (x_pipelined, counts_pipelined), (x_classic, counts_classic) = runs
    torch.testing.assert_close(x_pipelined, x_classic, rtol=0, atol=1e-8)
    assert max(abs(a - b) for a, b in zip(counts_pipelined, counts_classic)) <= 1, (counts_pipelined, counts_classic)


@gpu
@pytest.mark.parametrize("contact", [False, True])
def test_float32_is_as_close_to_float64_as_the_two_reduction_cg(layout_variants, contact):
    """SOFA's budget (tol = 0, 10 iterations): both float32 solvers round; neither much worse."""
    system64, _, rhs64 = make_system(torch.float64, "cuda", contact=contact)
    system, x, _ = make_scene(torch.float32, "cuda", contact=contact)
    matvec = matvec_at(system, x, variants=layout_variants)
    rhs = rhs64.float()
    want = reference(rhs, 0.0, 10, contact=contact)
    got = pipelined(system, matvec, rhs, 0.0, 10)
    plain = op_by_op(system, matvec_at(system, x, pipelined=False), rhs, 0.0, 10, (10,))  # the classic CG
    err_pipelined, err_plain = rel(got["x"], want["x"]), rel(plain["x"], want["x"])
    assert err_pipelined < max(10 * err_plain, 1e-5), (err_pipelined, err_plain)
    assert got["status"].tolist() == [cg_ops.CAPPED] * 3 and got["iterations"].tolist() == [10] * 3


@gpu
def test_per_object_statuses_zero_rhs_and_breakdown(layout_variants):
    system, matvec, rhs = make_system(torch.float64, "cuda", contact=False, variants=layout_variants)
    rhs[system.segments.node_object == 1] = 0.0
    got = pipelined(system, matvec, rhs, 1e-7, 600)
    want = reference(rhs, 1e-7, 600)
    assert got["status"].tolist() == [cg_ops.CONVERGED] * 3 and int(got["iterations"][1]) == 0
    # converged objects may cross the threshold an iteration apart (r.r rounded otherwise at it)
    assert int((got["iterations"] - want["iterations"]).abs().max()) <= 1
    assert float(got["x"][system.segments.node_object == 1].abs().max()) == 0.0
    assert rel(got["x"], want["x"]) < 1e-7

    system, matvec, rhs = make_system(torch.float64, "cuda", contact=False, mass_coef=-1.0,
                                      variants=layout_variants)  # indefinite
    got = pipelined(system, matvec, rhs, 1e-8, 50)
    want = reference(rhs, 1e-8, 50, mass_coef=-1.0)
    assert torch.equal(got["status"], want["status"]) and bool((got["status"] == cg_ops.BREAKDOWN).any())
    assert torch.equal(got["iterations"], want["iterations"])


@gpu
def test_solves_and_steps_take_it_and_the_switch_turns_it_off():
    system, x, rhs = make_scene(torch.float32, "cuda")
    matvec = matvec_at(system, x)
    result = system.cg_solver(rhs, cuda_graphs=False).solve(matvec, rhs, tol=1e-5, max_iter=300)
    assert bool(result.converged.all()) and ran_layout(system._cg) == PIPELINED_LAYOUTS[0]
    cg = fresh_solver(system, rhs)
    cg.begin(matvec_at(system, x, pipelined=False), rhs, 1e-5, 300, 300)  # the switch: the classic CG
    assert "_solve_work" not in cg.state.__dict__
    assert rel(cg.state.x, result.solution) < 1e-4


def step_sim(prescribed: bool):
    """Two hooke beams on the GPU with contact, a fixed CG budget (chained steps) or, with a
    prescribed tip (an imposed velocity), steps one at a time."""
    bodies = []
    for k in range(2):
        mesh = tm.beam_mesh(6 + 2 * k, 2, 2, size=(0.6, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.05), device="cuda")
        mat = tm.Material(young=2e4 * (k + 1), poisson=0.3, density=1000.0, model="hooke")
        fixed = mesh.vertices[:, 0] < 1e-9
        if prescribed and k == 1:
            tip = mesh.vertices[:, 0] > 0.6 - 1e-4
            rest = mesh.vertices[tip].clone()
            motion = lambda t, rest=rest: rest + torch.tensor([0.0, 0.05 * t, -0.1 * t], device="cuda")  # noqa: E731
            bodies.append(tm.Body(mesh, mat, fixed=fixed, prescribed=tip, motion=motion))
        else:
            bodies.append(tm.Body(mesh, mat, fixed=fixed))
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], cg_tol=0.0 if not prescribed else 1e-5,
                       cg_max_iter=10 if not prescribed else 200, check_every=1000, cuda_graphs=True)
    sim.options.require_convergence = False
    return sim


@gpu
@pytest.mark.parametrize("prescribed", [False, True])
def test_the_step_end_in_the_solve_equals_euler_update_after_it(layout_variants, layout, prescribed):
    """Chained steps (a fixed budget) and single steps with an imposed velocity: the solve that
    ends the step itself gives the states, statuses, iterations and residuals of the solve then
    euler_update, bitwise; each object's |v_new|^2 to rounding (summed over other chunks)."""
    runs = {}
    for fused in (True, False):
        sim = with_variants(step_sim(prescribed), layout_variants, fused_step_end=fused)
        norms = []
        for _ in range(3):
            sim.step(1 if prescribed else 6)
            (graphs,) = sim.system._step_graphs.values()
            norms.append((graphs.summary if prescribed else graphs.ring[:6])[..., 4, :].clone())
        work = graphs.cg.state.__dict__["_solve_work"]
        assert work.layout == layout and bool(work.end_work) == fused  # the solve ran it, or not
        assert graphs.chainable != prescribed
        runs[fused] = sim, torch.stack(norms), graphs
    (fused, fused_norms, fused_graphs), (plain, plain_norms, plain_graphs) = runs[True], runs[False]
    assert torch.equal(fused.x, plain.x) and torch.equal(fused.v, plain.v)
    assert fused.steps_done == plain.steps_done == (3 if prescribed else 18)
    assert torch.equal(fused.last_report.cg_iterations, plain.last_report.cg_iterations)
    assert torch.equal(fused.last_report.cg[0].residual_norm, plain.last_report.cg[0].residual_norm)
    torch.testing.assert_close(fused_norms, plain_norms, rtol=1e-6, atol=0)
    if prescribed:  # graph A ended the step: no graph C
        assert "C" not in fused_graphs._graphs and "C" in plain_graphs._graphs
    if not prescribed:  # the ring's rows and position advanced as euler_update advances them
        assert int(fused_graphs.ring_pos) == int(plain_graphs.ring_pos) == 6
        assert torch.equal(fused_graphs.ring[:6, :4], plain_graphs.ring[:6, :4])


def largest_chunk(plan):
    return int((plan.chunk_start[1:] - plan.chunk_start[:-1]).max())


def direct_call(system, matvec, rhs, cg, plan, slots, reference=False, **changes):
    """hooke_node_solve on cg's state over ``plan`` (promising its largest chunk) with ``slots``;
    keyword changes replace arguments (by name: library.pack packs them); ``reference``: the op's
    pure-torch reference in its place. Raises NotImplementedError where the solve does not fit
    one wave."""
    group = system.model.groups[0]
    neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group)
    s = cg.state
    args = dict(neighbor=neighbor, node_k=node_k, incidences=incidences, row_node=rows, mass=system.mass.reshape(-1),
                free=system.free.reshape(-1), c_mass=1.02, c_stiff=2e-4, node_stiffness=matvec.node_stiffness,
                rhs=rhs, tol_sq=0.0, chunk_start=plan.chunk_start, chunk_object=plan.chunk_object,
                object_chunk=plan.object_chunk, chunk_nodes=largest_chunk(plan), chunk_slots=slots, max_iter=10, x=s.x, r=s.r, p=s.p,
                threshold=s.threshold, rhs_sq=s.rhs_sq, rr=s.rr, status=s.status, alpha=s.alpha, beta=s.beta,
                iterations=s.iterations,
                exchange=torch.zeros(2, rhs.shape[0], 4 * rhs.shape[1], dtype=rhs.dtype, device=rhs.device),
                sums=torch.zeros(4 * plan.num_chunks, dtype=torch.float64, device=rhs.device),
                counters=torch.zeros(3, dtype=torch.int32, device=rhs.device))
    end_args = {}
    if "end" in changes:  # hooke_node_solve_step: the step's end after the solve
        changes.pop("end")
        like, objects = rhs, plan.object_chunk.numel() - 1
        end_args = dict(state_x=torch.zeros_like(like), state_v=torch.zeros_like(like), dv_imposed=None, h=0.01,
                        x_new=torch.zeros_like(like), v_new=torch.zeros_like(like),
                        norms=torch.zeros(objects, dtype=like.dtype, device=like.device),
                        summary=torch.zeros(5, objects, dtype=torch.float64, device=like.device),
                        end_sums=torch.zeros(plan.num_chunks, dtype=torch.float64, device=like.device),
                        end_counter=torch.zeros(objects + 1, dtype=torch.int32, device=like.device),
                        ring=None, ring_pos=None, carry=False)
        for key in list(changes):
            if key in end_args:
                end_args[key] = changes.pop(key)
    args.update(changes)
    name = "hooke_node_solve_step" if end_args else "hooke_node_solve"
    op = getattr(solve, "_ref_" + name) if reference else getattr(torch.ops.tensormass, name)
    op(*library.pack(name, **args, **end_args))


def test_the_reference_from_a_guess_is_the_two_reduction_cg_from_it():
    """The warm solve's oracle (the op's reference with from_iterate, on the CPU): from the iterate
    a start from a guess left, the two-reduction CG op by op from that start; the start's threshold
    and b.b kept."""
    system, matvec, rhs = make_system(torch.float64, "cpu", contact=False)
    guess = op_by_op(system, matvec, rhs, 1e-2, 1000, (1000,))["x"]
    cg = started_from(system, matvec, rhs, guess, 1e-8, 300)
    started = state_of(cg)
    plan = solve.solve_plan(cg.plan)
    direct_call(system, matvec, cg.state.r, cg, plan, 0, reference=True, max_iter=300, tol_sq=1.0, flags=3,
                cache_slots=-1, from_iterate=True)
    got = state_of(cg)
    ref = started_from(system, matvec, rhs, guess, 1e-8, 300)
    for _ in range(300):
        ref._iterate(matvec, 300)
    want = state_of(ref)
    assert torch.equal(got["threshold"], started["threshold"]) and torch.equal(got["rhs_sq"], started["rhs_sq"])
    assert got["status"].tolist() == want["status"].tolist() == [cg_ops.CONVERGED] * 3
    assert 0 < int(want["iterations"].min())
    assert int((got["iterations"] - want["iterations"]).abs().max()) <= 1
    assert rel(got["x"], want["x"]) < 1e-7


@gpu
def test_a_plan_beyond_one_wave_is_not_run_and_changes_nothing():
    sim = scenes.sofa_beam(device="cuda", scale=3).simulator  # 936 nodes: one chunk each is too many
    system = sim.system
    matvec = system.system_matvec(1.02, 2e-4).load(sim.x)
    rhs = torch.randn_like(sim.x)
    cg = fresh_solver(system, rhs)
    plan = ChunkPlan.from_segments(system.segments, 1)
    before = state_of(cg)
    with pytest.raises(NotImplementedError, match="does not fit one wave"):
        direct_call(system, matvec, rhs, cg, plan, solve.chunk_slots(system.model.groups[0], plan))
    for k in FIELDS:
        assert torch.equal(state_of(cg)[k], before[k]), k


@gpu
def test_a_chunk_beyond_the_promised_layout_ends_its_object_as_non_finite():
    system, matvec, rhs = make_system(torch.float32, "cuda", contact=False)
    cg = fresh_solver(system, rhs)
    plan = solve.solve_plan(cg.plan)
    slots = solve.chunk_slots(system.model.groups[0], plan)
    direct_call(system, matvec, rhs, cg, plan, slots - 1)
    status = cg.state.status.tolist()
    assert cg_ops.NONFINITE in status, status  # the object of the chunk with the most slots
    direct_call(system, matvec, rhs, cg, plan, slots)
    assert cg.state.status.tolist() == [cg_ops.CAPPED] * 3


@gpu
def test_a_streamed_chunk_beyond_the_promised_nodes_ends_its_object_and_larger_ones_are_not_run():
    sim = scenes.sofa_beam(device="cuda", scale=3).simulator  # 936 nodes, one object
    system = sim.system
    matvec = system.system_matvec(1.02, 2e-4).load(sim.x)
    rhs = torch.randn_like(sim.x)
    cg = fresh_solver(system, rhs)
    plan = ChunkPlan.from_segments(system.segments, 2 * solve.STREAM_CHUNK_NODES)
    direct_call(system, matvec, rhs, cg, plan, 0, chunk_nodes=solve.STREAM_CHUNK_NODES)
    assert cg.state.status.tolist() == [cg_ops.NONFINITE]
    before = state_of(cg)  # chunks larger than both layouts take: not run, nothing changed
    with pytest.raises(NotImplementedError, match="does not fit one wave"):
        direct_call(system, matvec, rhs, cg, plan, 0)
    for k in FIELDS:  # the NaN b.b too
        torch.testing.assert_close(state_of(cg)[k], before[k], rtol=0, atol=0, equal_nan=True, msg=k)


@gpu
@pytest.mark.parametrize("window", [None, 0])
def test_full_chunks_match_the_two_reduction_cg(layout_variants, layout, window):
    """936 nodes in one object: streamed chunks of 256 rows whose mirror rows pair up (the slots
    of each pair halved between their threads), rows sorted by slot count or in node order
    (``node_graph_window=0``); float64 against the two-reduction CG."""
    variants = layout_variants if window is None else layout_variants.replace(node_graph_window=window)
    sim = scenes.sofa_beam(device="cuda", dtype=torch.float64, scale=3).simulator
    matvec = sim.system.system_matvec(1.02, 2e-4, variants=variants).load(sim.x)
    classic = sim.system.system_matvec(1.02, 2e-4, pipelined=False, variants=variants).load(sim.x)
    rhs = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64).to("cuda")
    for tol, max_iter in ((0.0, 30), (1e-9, 2000)):
        cg = fresh_solver(sim.system, rhs)
        cg.begin(matvec, rhs, tol, max_iter, max_iter)
        assert ran_layout(cg) == layout
        got = state_of(cg)
        plain = fresh_solver(sim.system, rhs)
        plain.begin(classic, rhs, tol, max_iter, max_iter)
        assert got["status"].tolist() == plain.state.status.tolist()
        assert abs(int(got["iterations"][0]) - int(plain.state.iterations[0])) <= (1 if tol else 0)
        assert rel(got["x"], plain.state.x) < (1e-7 if tol else 1e-10)


@gpu
def test_a_graph_beyond_one_wave_in_shared_memory_streams():
    """44,541 nodes: 348 chunks of 128 (more than an H100's 264 resident blocks), 174 of 256."""
    mesh = tm.beam_mesh(100, 20, 20, size=(1.0, 0.2, 0.2), device="cuda")
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke"),
                   fixed=mesh.vertices[:, 0] < 1e-9)
    sim = tm.Simulator([body], dt=0.01, gravity=(0, 0, -9.81), form="tensor", device="cuda")
    matvec = sim.system.system_matvec(1.0, 1e-4).load(sim.x)
    rhs = torch.randn(sim.x.shape, generator=torch.Generator().manual_seed(5)).to("cuda")
    cg = fresh_solver(sim.system, rhs)
    if not solve.persistent_cg_fits(rhs.device, solve.solve_plan(cg.plan).num_chunks):
        cg.begin(matvec, rhs, 1e-5, 400, 400)
        work = cg.state.__dict__["_solve_work"]
        assert work.layout == "streamed" and work.misfits == {"shared"}
    else:  # a GPU with more multiprocessors: the shared layout's test case, streamed forced
        streamed = sim.system.system_matvec(1.0, 1e-4, variants=KernelVariants(pipelined_layouts=("streamed",)))
        cg.begin(streamed.load(sim.x), rhs, 1e-5, 400, 400)
        assert ran_layout(cg) == "streamed"
    got = state_of(cg)
    plain = fresh_solver(sim.system, rhs)
    plain.begin(sim.system.system_matvec(1.0, 1e-4, pipelined=False).load(sim.x), rhs, 1e-5, 400, 400)
    assert got["status"].tolist() == [cg_ops.CONVERGED] == plain.state.status.tolist()
    assert abs(int(got["iterations"][0]) - int(plain.state.iterations[0])) <= 2
    assert rel(got["x"], plain.state.x) < 1e-4


def test_the_cpu_has_no_pipelined_kernel_and_changes_nothing():
    system, matvec, rhs = make_system(torch.float64, "cpu")
    cg = fresh_solver(system, rhs)
    before = state_of(cg)
    plan = solve.solve_plan(cg.plan)
    with pytest.raises(NotImplementedError, match="the CPU has no pipelined kernel"):
        direct_call(system, matvec, rhs, cg, plan, solve.chunk_slots(system.model.groups[0], plan))
    summary = torch.zeros(5, 3, dtype=torch.float64)
    with pytest.raises(NotImplementedError, match="the CPU has no pipelined kernel"):
        direct_call(system, matvec, rhs, cg, plan, solve.chunk_slots(system.model.groups[0], plan), end=True,
                    summary=summary)
    assert float(summary.abs().max()) == 0.0
    assert not solve.system_solve(system.model.groups[0], system.mass.reshape(-1), system.free.reshape(-1), 1.0,
                                  1e-4, None, rhs, 1e-6, cg.plan, cg.state, 10)
    for k in FIELDS:
        assert torch.equal(state_of(cg)[k], before[k]), k


def test_a_solve_from_the_iterate_takes_no_step_end():
    """from_iterate goes on from a start's iterate: it neither begins nor ends a step (one clear
    error, on any device, nothing changed)."""
    system, matvec, rhs = make_system(torch.float64, "cpu")
    cg = fresh_solver(system, rhs)
    before = state_of(cg)
    end = solve.StepEnd(rhs, rhs, None, 0.01, torch.empty_like(rhs), torch.empty_like(rhs),
                        torch.zeros(3, dtype=rhs.dtype), torch.zeros(5, 3, dtype=torch.float64))
    with pytest.raises(ValueError, match="from_iterate.*takes no step_end"):
        solve.system_solve(system.model.groups[0], system.mass.reshape(-1), system.free.reshape(-1), 1.0, 1e-4, None,
                           cg.state.r, 1e-6, cg.plan, cg.state, 10, step_end=end, from_iterate=True)
    for k in FIELDS:
        assert torch.equal(state_of(cg)[k], before[k]), k


def test_packed_arguments_name_what_is_missing():
    """The solve ops take their tensors in lists (system, plan, cg, buffers, step): a list of the
    wrong length or with a missing tensor is one error naming the list and its members."""
    system, matvec, rhs = make_system(torch.float32, "cpu")
    cg = fresh_solver(system, rhs)
    plan = solve.solve_plan(cg.plan)
    slots = solve.chunk_slots(system.model.groups[0], plan)
    named = dict(zip(solve.SYSTEM, [*node_graph.hooke_rows_graph(system.model.groups[0]), system.mass.reshape(-1),
                                    None]),
                 c_mass=1.0, c_stiff=1e-4, node_stiffness=None, rhs=rhs, tol_sq=0.0, **dict(zip(solve.PLAN, plan.tensors())),
                 chunk_nodes=largest_chunk(plan), chunk_slots=slots, max_iter=5, **dict(zip(solve.CG, cg.state.packed())),
                 exchange=torch.zeros(2, rhs.shape[0], 4 * rhs.shape[1]),
                 sums=torch.zeros(4 * plan.num_chunks, dtype=torch.float64), counters=torch.zeros(3, dtype=torch.int32))
    args = list(library.pack("hooke_node_solve", **named))
    before = state_of(cg)
    for position, value, message in [
            (0, args[0][:5], r"system must be the 6 tensors \[neighbor, node_k, incidences, row_node\?, mass, free\?\]"),
            (0, [None] + args[0][1:], r"system\[0\] \(neighbor\) is None"),
            (6, args[6][:2], r"plan must be the 3 tensors \[chunk_start, chunk_object, object_chunk\]"),
            (10, args[10][:-1], "cg must be the 10 tensors"),
            (11, args[11] + [rhs], r"buffers must be the 3 tensors \[exchange, sums, counters\], got 4")]:
        call = list(args)
        call[position] = value
        with pytest.raises(RuntimeError, match=message):
            torch.ops.tensormass.hooke_node_solve(*call)
    for k in FIELDS:
        assert torch.equal(state_of(cg)[k], before[k]), k
    misnamed = dict(named)
    misnamed["counter"] = misnamed.pop("counters")
    with pytest.raises(TypeError, match=r"missing \['counters'\]; unknown \['counter'\]"):
        library.pack("hooke_node_solve", **misnamed)


def test_the_solve_plans_and_their_slots():
    system, _, rhs = make_system(torch.float64, "cpu")
    cg = fresh_solver(system, rhs)
    plan = solve.solve_plan(cg.plan)
    assert solve.solve_plan(cg.plan) is plan  # cached
    assert largest_chunk(plan) <= solve.SOLVE_CHUNK_NODES
    streamed = solve.solve_plan(cg.plan, "streamed")
    assert streamed is solve.solve_plan(cg.plan, "streamed") and streamed is not plan
    assert largest_chunk(streamed) <= solve.STREAM_CHUNK_NODES
    assert torch.equal(streamed.chunk_object, torch.arange(3))  # 54-90 nodes an object: one chunk each
    with pytest.raises(ValueError, match="layout must be one of"):
        solve.solve_plan(cg.plan, "global")
    group = system.model.groups[0]
    _, _, incidences = library.plan_indices(group.plan)
    starts = plan.chunk_start.tolist()
    want = max(int(incidences[a:b].sum()) for a, b in zip(starts[:-1], starts[1:]))
    assert solve.chunk_slots(group, plan) == want


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_bad_inputs_are_rejected_with_nothing_changed(device):
    system, matvec, rhs = make_system(torch.float32, device)
    cg = fresh_solver(system, rhs)
    plan = solve.solve_plan(cg.plan)
    slots = solve.chunk_slots(system.model.groups[0], plan)
    before = state_of(cg)
    cases = [(dict(exchange=torch.zeros(2, rhs.shape[0], 3 * rhs.shape[1], device=device)), "exchange has shape"),
             (dict(sums=torch.zeros(3, dtype=torch.float64, device=device)), "sums has shape"),
             (dict(counters=torch.zeros(3, dtype=torch.int64, device=device)), "counters is Long"),
             (dict(max_iter=-1), "max_iter must be >= 0"),
             (dict(chunk_slots=-1), "chunk_slots must be >= 0"),
             (dict(chunk_nodes=0), "chunk_nodes must be >= 1"),
             (dict(x=cg.state.x[:-1]), "x has shape"),
             (dict(status=cg.state.status.float()), "status is Float")]
    objects = plan.object_chunk.numel() - 1
    step_end_cases = [  # hooke_node_solve_step's own arguments
        (dict(state_x=torch.zeros(3, 3, device=device)), "state_x has shape"),
        (dict(state_v=torch.zeros_like(rhs).double()), "state_v is Double"),
        (dict(end_sums=torch.zeros(plan.num_chunks + 1, dtype=torch.float64, device=device)), "end_sums has shape"),
        (dict(end_counter=torch.zeros(objects, dtype=torch.int32, device=device)), "end_counter has shape"),
        (dict(summary=torch.zeros(4, objects, dtype=torch.float64, device=device)), "summary has shape"),
        (dict(ring=torch.zeros(2, 5, objects, dtype=torch.float64, device=device)), "ring and ring_pos go together"),
        (dict(x_new=torch.zeros_like(rhs)[:, :2]), "x_new has shape")]
    for change, message in cases + [(dict(end=True, **change), message) for change, message in cases[:2]] + [
            (dict(end=True, **change), message) for change, message in step_end_cases]:
        with pytest.raises(RuntimeError, match=message):
            direct_call(system, matvec, rhs, cg, plan, slots, **change)
    for k in FIELDS:
        assert torch.equal(state_of(cg)[k], before[k]), k
