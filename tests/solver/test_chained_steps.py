"""Chained steps (Simulator.step(n) on the GPU: up to MAX_CHAIN steps with one host synchronisation,
StepGraphs.run_steps) give the same states as one step at a time, bitwise, and a failed step in a
chain raises with the state of the step before it. Run here on the CPU: the step graphs are built
on the CPU and their phases run eagerly (the CUDA capture itself is tested in solver/test_cuda_graph_capture.py)."""
from __future__ import annotations

import pytest
import torch
from conftest import with_variants

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.sim import simulator as scene_module
from tensormass_torch.solver import implicit_euler
from tensormass_torch.solver.implicit_euler import StepGraphs

pytestmark = pytest.mark.skipif(cg_ops.native_ops_for(torch.zeros(1)) is None,
                                reason="needs the compiled CG ops of the extension")


@pytest.fixture
def graphs_on_cpu(monkeypatch):
    """StepGraphs on the CPU, their phases run eagerly instead of captured."""
    def cpu_step_graphs(system, opts, imposed):
        key = (opts.dt, opts.cg_tol, opts.cg_max_iter, opts.check_every, opts.require_convergence, imposed)
        if key not in system._step_graphs:
            system._step_graphs[key] = StepGraphs(system, opts, imposed)
        return system._step_graphs[key]

    def eager(graphs, key, work):
        work()
        return False

    monkeypatch.setattr(scene_module, "step_graphs_for", cpu_step_graphs)
    monkeypatch.setattr(implicit_euler, "step_graphs_for", cpu_step_graphs)
    monkeypatch.setattr(implicit_euler, "run_captured", eager)


def watching_chains(monkeypatch, flag_first_at=None) -> list:
    """The length of every chain run from now on (StepGraphs.first_failure's calls); with
    ``flag_first_at`` k, the first chain's step k is reported failed (if none before it did)."""
    chains = []
    real_first_failure = StepGraphs.first_failure

    def first_failure(self, summaries):
        chains.append(summaries.shape[0])
        found = real_first_failure(self, summaries)
        return min(found, flag_first_at) if flag_first_at is not None and len(chains) == 1 else found

    monkeypatch.setattr(StepGraphs, "first_failure", first_failure)
    return chains


def make_sim(model="hooke", cg_max_iter=12, check_every=1000, tol=0.0, require=False):
    bodies = []
    for k in range(2):
        mesh = tm.beam_mesh(6, 2, 2, size=(0.6, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.02), dtype=torch.float64)
        mat = tm.Material(young=3e4 * (k + 1), poisson=0.3, density=1000.0, model=model)
        bodies.append(tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9))
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)],
                       cg_tol=tol, cg_max_iter=cg_max_iter, check_every=check_every)
    sim.options.require_convergence = require
    return sim


@pytest.mark.parametrize("model", ["hooke", "stvk"])
def test_chained_steps_equal_single_steps(graphs_on_cpu, model):
    chained, single = make_sim(model), make_sim(model)
    chained.step(9)
    for _ in range(9):
        single.step()
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert chained.time == single.time and chained.steps_done == single.steps_done == 9
    (graphs,) = chained.system._step_graphs.values()
    assert graphs.chainable and int(graphs.ring_pos) == 9  # the 9 steps ran as one chain
    assert torch.equal(chained.last_report.cg_iterations, single.last_report.cg_iterations)
    assert torch.equal(chained.last_report.cg[0].residual_norm, single.last_report.cg[0].residual_norm)


def test_chains_longer_than_the_ring(graphs_on_cpu):
    chained, single = make_sim(), make_sim()
    (graphs,) = [implicit_euler.step_graphs_for(chained.system, chained.options, False)]
    graphs.ring = graphs.ring[:4]  # chains of at most 4 steps
    chained.step(10)
    single.step(1)
    for _ in range(9):
        single.step(1)
    assert torch.equal(chained.x, single.x) and chained.steps_done == 10


def test_failure_inside_a_chain_commits_the_steps_before_it(graphs_on_cpu, monkeypatch):
    """A step flagged as failed in the middle of a chain: the steps before it are committed (run
    again), it runs on its own (which here succeeds), and the chain goes on: same states as steps
    one at a time."""
    chained, single = make_sim(), make_sim()
    graphs = implicit_euler.step_graphs_for(chained.system, chained.options, False)
    chains = watching_chains(monkeypatch, flag_first_at=3)  # the 4th step of the first chain
    chained.step(8)
    for _ in range(8):
        single.step()
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert chained.steps_done == 8 and chained.time == single.time
    assert graphs is implicit_euler.step_graphs_for(chained.system, chained.options, False)
    assert chains[0] == 8 and len(chains) == 2  # the first chain, then the rest after the lone step


def test_first_failure_finds_the_first_failed_step(graphs_on_cpu):
    sim = make_sim()
    graphs = implicit_euler.step_graphs_for(sim.system, sim.options, False)
    summaries = torch.zeros(6, 5, 3, dtype=torch.float64)
    summaries[:, 0] = cg_ops.CAPPED
    assert graphs.first_failure(summaries) == 6 and not graphs.failure(summaries[0])
    summaries[4, 0, 2] = cg_ops.BREAKDOWN
    summaries[5, 4, 0] = float("nan")
    assert graphs.first_failure(summaries) == 4 and graphs.failure(summaries[4]) and graphs.failure(summaries[5])


def test_failed_chain_raises_and_keeps_the_state(graphs_on_cpu):
    sim = make_sim("stvk")
    sim.step(3)
    x, t = sim.x.clone(), sim.time
    sim.v = sim.v.clone()
    sim.v[7, 2] = float("nan")
    with pytest.raises(tm.SolverError):
        sim.step(5)
    assert torch.equal(sim.x, x) and sim.time == t and sim.steps_done == 3


def test_not_converged_fixed_budget_raises_when_convergence_is_required(graphs_on_cpu):
    sim = make_sim(cg_max_iter=2, tol=1e-12, require=True)
    with pytest.raises(tm.SolverError, match="not converged"):
        sim.step(4)
    assert sim.steps_done == 0 and torch.equal(sim.x, sim.model.rest)


def test_steps_that_need_host_checks_are_not_chained(graphs_on_cpu):
    """A CG that runs op by op (stvk element by element: ``node_tangent`` off) past check_every
    iterations needs the host: not chained."""
    sim = with_variants(make_sim("stvk", cg_max_iter=50, check_every=8, tol=1e-8), node_tangent=False)
    sim.step(3)
    (graphs,) = sim.system._step_graphs.values()
    assert not graphs.chainable and int(graphs.ring_pos) == 0 and sim.steps_done == 3


def test_stvk_steps_chain_with_the_tangent_on_the_node_graph(graphs_on_cpu):
    """With its differential on the node graph (``KernelVariants.node_tangent``), stvk's CG is one op that
    stops on the device: its steps chain, bitwise one step at a time."""
    chained, single = (make_sim("stvk", cg_max_iter=50, check_every=8, tol=1e-8) for _ in range(2))
    chained.step(3)
    for _ in range(3):
        single.step()
    (graphs,) = chained.system._step_graphs.values()
    assert graphs.chainable and int(graphs.ring_pos) == 3
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)


def test_steps_with_a_tolerance_chain_where_the_cg_is_one_op(graphs_on_cpu):
    """The hooke tensor form's CG is one op that stops on the device: steps with a tolerance and
    a cap far past check_every chain, bitwise one step at a time, each stopping when converged."""
    chained, single = make_sim(cg_max_iter=200, check_every=8, tol=1e-8, require=True), make_sim(
        cg_max_iter=200, check_every=8, tol=1e-8, require=True)
    chained.step(5)
    for _ in range(5):
        single.step()
    (graphs,) = chained.system._step_graphs.values()
    assert graphs.chainable and int(graphs.ring_pos) == 5
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    iterations = chained.last_report.cg_iterations
    assert torch.equal(iterations, single.last_report.cg_iterations)
    assert bool((iterations > 8).all() and (iterations < 200).all())  # past check_every, converged


def make_mixed_sim(tol=1e-6):
    """A clamped beam under gravity, float64 steps to ``tol`` in float32 iterations (precision
    "mixed") from the projection's guesses: the first steps take two or three rounds each, the
    later ones one (the space holds what the motion needs)."""
    mesh = tm.beam_mesh(8, 3, 3, size=(1.0, 0.25, 0.25), dtype=torch.float64)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke")
    return tm.Simulator([tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9)], dt=0.01, gravity=(0, 0, -9.81),
                        cg_tol=tol, cg_max_iter=500, precision="mixed", warm_start="project")


def test_mixed_steps_chain_and_equal_single_steps(graphs_on_cpu, monkeypatch):
    """Refined steps chain (one round a step, on the device; the solution space joined after each)
    once a step on its own took one round, and give the states of steps one at a time, bitwise."""
    chained, single = make_mixed_sim(), make_mixed_sim()
    for sim in (chained, single):
        for _ in range(12):  # (one at a time: the space fills, one round serves)
            sim.step()
    chains = watching_chains(monkeypatch)
    chained.step(9)
    for _ in range(9):
        single.step()
    (graphs,) = chained.system._step_graphs.values()
    assert chains == [9] and graphs.chainable and int(graphs.ring_pos) == 9  # the 9 steps ran as one chain
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert torch.equal(chained.last_report.cg_iterations, single.last_report.cg_iterations)
    assert bool(chained.last_report.cg[0].converged.all())


@pytest.mark.parametrize("inner_tol", [1e-3, 0.3], ids=["flagged", "short-rounds"])
def test_a_failed_chained_mixed_step_rewinds_the_space(graphs_on_cpu, monkeypatch, inner_tol):
    """A chained refined step that fails (flagged at the 4th step, or left active at the 1st by a
    round whose correction stops short: inner tolerance 0.3): the space is rewound to the chain's
    start, the good steps run again from it and the failed one alone, with its rounds; the chains
    go on where a step on its own takes one round. The states of steps one at a time, bitwise
    (without the rewind the good steps would start from guesses of a space that already holds
    their solutions)."""
    chained, single = make_mixed_sim(), make_mixed_sim()
    for sim in (chained, single):
        for _ in range(12):
            sim.step()
        sim.system.refinement(sim.options).inner_tol = inner_tol
    chains = watching_chains(monkeypatch, flag_first_at=3)
    chained.step(8)
    for _ in range(8):
        single.step()
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert chained.steps_done == single.steps_done == 20
    # flagged: 3 good steps, the 4th alone, a chain of the other 4; short rounds: the 1st alone
    # (more than one round), then none chained
    assert chains == ([8, 4] if inner_tol == 1e-3 else [8])


def test_mixed_steps_that_need_rounds_stop_chaining(graphs_on_cpu, monkeypatch):
    """Where one round does not serve (tolerance 1e-8 from the first step), the chain fails at
    its first step, that step runs on its own with its rounds, and the next steps are not
    chained while steps take more than one: the states of steps one at a time, bitwise."""
    chained, single = make_mixed_sim(1e-8), make_mixed_sim(1e-8)
    chains = watching_chains(monkeypatch)
    chained.step(6)
    for _ in range(6):
        single.step()
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert chains == [6] and chained.steps_done == 6


def test_mixed_steps_from_extrapolated_guesses_are_not_chained(graphs_on_cpu):
    """warm_start="extrapolate" makes each step's guess on the host: a chained refined step would
    start from zero instead, so those steps run one at a time."""
    sim = make_mixed_sim()
    sim.options.warm_start = "extrapolate"
    sim.step(5)
    (graphs,) = sim.system._step_graphs.values()
    assert not graphs.chainable and int(graphs.ring_pos) == 0 and sim.steps_done == 5


def test_projected_steps_chain_and_equal_single_steps(graphs_on_cpu, monkeypatch):
    """Float64 steps to a tolerance from the projection's guesses (the whole CG one op) chain, each
    joining its solution to the space, and give the states of steps one at a time, bitwise; a
    failure in the chain rewinds the space as for refined steps."""
    def projected():
        sim = make_mixed_sim()
        sim.options.precision = "full"
        return sim

    chained, single = projected(), projected()
    chained.step(9)
    for _ in range(9):
        single.step()
    (graphs,) = chained.system._step_graphs.values()
    assert graphs.chainable and int(graphs.ring_pos) == 9
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert torch.equal(chained.last_report.cg_iterations, single.last_report.cg_iterations)
    chains = watching_chains(monkeypatch, flag_first_at=2)
    chained.step(6)
    for _ in range(6):
        single.step()
    assert chains == [6, 3]
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
