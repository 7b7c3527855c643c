"""Whole implicit Euler steps captured in CUDA graphs (solver.implicit_euler.StepGraphs) give the
same states as the eager steps, bitwise, with contact planes, fixed and prescribed nodes and
several objects; a failed step still raises and keeps the state. Skipped without CUDA and the
CUDA build of the extension."""
from __future__ import annotations

import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops


def _cuda_ready():
    return torch.cuda.is_available() and cg_ops.native_ops_for(torch.zeros(1, device="cuda")) is not None


pytestmark = pytest.mark.skipif(not _cuda_ready(), reason="needs CUDA and the CUDA build of the extension")


def make_sim(model, cuda_graphs, cg_tol=1e-5, check_every=4, cg_max_iter=200):
    bodies = []
    for k in range(3):
        mesh = tm.beam_mesh(6 + 2 * k, 2, 2, size=(0.6, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.05), device="cuda")
        mat = tm.Material(young=2e4 * (k + 1), poisson=0.3, density=1000.0, model=model, rotation="qr")
        fixed = mesh.vertices[:, 0] < 1e-9
        if k == 1:  # the far end follows a prescribed circle
            tip = mesh.vertices[:, 0] > 0.6 - 1e-4
            rest = mesh.vertices[tip].clone()
            motion = lambda t, rest=rest: rest + torch.tensor([0.0, 0.05 * math.sin(6 * t), 0.05 * (math.cos(6 * t) - 1)],  # noqa: E731
                                                              device="cuda")
            bodies.append(tm.Body(mesh, mat, fixed=fixed, prescribed=tip, motion=motion))
        else:
            bodies.append(tm.Body(mesh, mat, fixed=fixed))
    return tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                        planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], cg_tol=cg_tol, cg_max_iter=cg_max_iter,
                        check_every=check_every, cuda_graphs=cuda_graphs)


@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
def test_graphed_steps_equal_eager_steps(model):
    graphed, eager = make_sim(model, True), make_sim(model, False)
    for _ in range(12):
        graphed.step()
        eager.step()
        assert torch.equal(graphed.x, eager.x) and torch.equal(graphed.v, eager.v)
    assert float(graphed.x[:, 2].min()) < 0.05  # the beams came down to the plane
    graphs = list(graphed.system._step_graphs.values())
    # graph C is not made where A's solve ends the step itself (the pipelined CG: solve.StepEnd)
    # (graph A is keyed by whether the CG starts from a guess: these steps start cold)
    assert graphs and all(g._graphs.get(("A", False)) not in (None, False)
                          and (g._a_ends[False] or g._graphs.get("C") not in (None, False)) for g in graphs), \
        "the step was not captured"
    if model == "hooke":
        assert all(g._a_ends[False] and "C" not in g._graphs for g in graphs)


def test_fixed_budget_step_is_one_graph():
    sim = make_sim("hooke", True, cg_tol=0.0, check_every=1000, cg_max_iter=10)
    sim.options.require_convergence = False
    sim.step(4)
    (graphs,) = sim.system._step_graphs.values()
    assert graphs.first == 10 and graphs.cg.graph_replays == 0  # all iterations inside graph A
    assert int(sim.last_report.cg_iterations.max()) == 10


def test_failed_graphed_step_keeps_state():
    sim = make_sim("stvk", True)
    sim.step(3)  # graphs captured
    x, v, t = sim.x.clone(), sim.v.clone(), sim.time
    sim.v = sim.v.clone()
    sim.v[5, 0] = float("nan")
    with pytest.raises(tm.SolverError):
        sim.step()
    assert torch.equal(sim.x, x) and sim.time == t
    sim.v = v
    sim.step()  # and it goes on
    assert bool(torch.isfinite(sim.x).all())


def test_torch_backend_on_cuda_runs_eagerly(monkeypatch):
    """The pure-torch path is not captured (its reductions synchronise); it runs eagerly and leaves
    torch's CUDA random generator usable (a failed capture would not)."""
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    sim = make_sim("stvk", True)
    sim.step(3)
    assert not sim.system._step_graphs
    torch.randn(4, device="cuda")


@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_chained_steps_equal_single_steps(model):
    """sim.step(n) with a fixed CG budget chains the captured steps (one host sync per chain)."""
    def fixed_budget():
        sim = make_sim(model, True, cg_tol=0.0, check_every=1000, cg_max_iter=10)
        sim.bodies[1].motion = None  # no prescribed motion: it would need the host every step
        sim._has_prescribed = False
        sim.options.require_convergence = False
        return sim

    chained, single = fixed_budget(), fixed_budget()
    chained.step(20)
    for _ in range(20):
        single.step()
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    graphs = [g for g in chained.system._step_graphs.values() if g.chainable]
    assert graphs and all(graphs[0]._graphs.get(("chain", k, False)) not in (None, False) for k in (1, 8))


@pytest.mark.parametrize("precision", ["full", "mixed"])
def test_projected_and_mixed_steps_chain_and_equal_single_steps(precision):
    """Steps to a tolerance from the projection's guesses chain as captured graphs (float64 CG in
    one op; or one refinement round a step), with the same states as steps one at a time; a chain
    that fails at its 3rd step rewinds the space and gives them too."""
    def projected():
        mesh = tm.beam_mesh(10, 3, 3, size=(1.0, 0.25, 0.25), dtype=torch.float64, device="cuda")
        mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke")
        return tm.Simulator([tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9)], dt=0.01, gravity=(0, 0, -9.81),
                            cg_tol=1e-6, cg_max_iter=500, precision=precision, warm_start="project")

    chained, single = projected(), projected()
    for sim in (chained, single):
        for _ in range(12):  # (one at a time: the space fills, one round serves)
            sim.step()
    chained.step(10)
    for _ in range(10):
        single.step()
    (graphs,) = chained.system._step_graphs.values()
    assert graphs.chainable and graphs._graphs.get(("chain", 8, True)) not in (None, False)
    assert torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    real_first_failure = type(graphs).first_failure
    calls = []

    def first_failure(summaries):  # (the first chain's 3rd step flagged)
        calls.append(summaries.shape[0])
        found = real_first_failure(graphs, summaries)
        return min(found, 2) if len(calls) == 1 else found

    graphs.first_failure = first_failure
    chained.step(6)
    for _ in range(6):
        single.step()
    assert calls == [6, 3] and torch.equal(chained.x, single.x) and torch.equal(chained.v, single.v)
    assert bool(chained.last_report.cg[0].converged.all())


def test_paired_block_jacobi_loads_are_captured_and_equal_eager_steps():
    """Two stacked blocks pressed on a floor, block Jacobi with paired blocks (the default with
    contact): the load over the pairs' kept buffers is captured (``BlockJacobi._graphs``), and
    the steps equal the eager simulator's bit for bit."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    low = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), device="cuda")
    high = tm.TetMesh(low.vertices + torch.tensor([0.0, 0.0, 0.1], device="cuda"), low.elements)
    sims = [tm.Simulator([tm.Body(low, material), tm.Body(high, material)], dt=0.005, device="cuda",
                         planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(), rayleigh_mass=1.0,
                         cg_tol=1e-5, cuda_graphs=graphs) for graphs in (True, False)]
    for _ in range(8):
        for sim in sims:
            sim.step()
        assert torch.equal(sims[0].x, sims[1].x) and torch.equal(sims[0].v, sims[1].v)
    jacobi = sims[0].system._block_jacobi
    assert jacobi.paired is not None and any(graph not in (None, False) for graph in jacobi._graphs.values())
