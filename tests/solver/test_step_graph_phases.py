"""The phases of a captured step (solver.implicit_euler.StepGraphs), run eagerly on the CPU
extension (their CUDA graphs replay exactly these ops), against the step function's eager path:
plain CG (its whole solve in one op), warm starts (the start through the ops, then the one op),
and the multigrid-preconditioned step (right-hand side, the preconditioner loaded, the start and
the predicted iterations, one iteration a look), with a floor and prescribed nodes. So the logic
of the phases is tested where CI runs; tests/solver/test_cuda_graph_capture.py and
test_multigrid.py check the captured graphs on CUDA."""
import dataclasses
import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.solver import implicit_euler as ie

DT = torch.float64
pytestmark = pytest.mark.skipif(cg_ops.native_ops_for(torch.zeros(1, dtype=DT)) is None,
                                reason="needs the CPU extension (its euler_update)")


def make_sim(preconditioner, warm_start, prescribed):
    mesh = tm.beam_mesh(40, 4, 4, size=(1.0, 0.25, 0.25), dtype=DT)
    fixed = mesh.vertices[:, 0] == 0
    options = {}
    if prescribed:
        tip = mesh.vertices[:, 0] > 1.0 - 1e-9
        rest = mesh.vertices[tip].clone()
        options = dict(prescribed=tip, motion=lambda t: rest + torch.tensor([0.0, 0.0, -0.1 * math.sin(5 * t)],
                                                                           dtype=DT))
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0), fixed=fixed, **options)
    return tm.Simulator([body], dt=0.01, cg_tol=1e-10, cuda_graphs=False, preconditioner=preconditioner,
                        warm_start=warm_start, rayleigh_mass=0.1, planes=[tm.Plane((0, 0, 1), -0.05, 1e4)])


@pytest.mark.parametrize("preconditioner", ["none", "multigrid"])
@pytest.mark.parametrize("warm_start", [False, True, "project"])
@pytest.mark.parametrize("prescribed", [False, True])
def test_the_phases_are_the_eager_step(monkeypatch, preconditioner, warm_start, prescribed):
    if preconditioner == "multigrid":
        pytest.importorskip("pyamg")
    monkeypatch.setattr(ie, "run_captured", lambda graphs, key, work: work() and False)
    eager = make_sim(preconditioner, warm_start, prescribed)
    phased = make_sim(preconditioner, warm_start, prescribed)
    opts = dataclasses.replace(phased.options, cuda_graphs=True)
    graphs = ie.StepGraphs(phased.system, opts, imposed=prescribed)
    monkeypatch.setattr("tensormass_torch.sim.simulator.implicit_euler_step",
                        lambda system, x, v, o, imposed=None, guess=None: graphs.step(x, v, imposed, guess)
                        if system is phased.system else ie.implicit_euler_step(system, x, v, o, imposed, guess))
    for _ in range(12):
        eager.step()
        phased.step()
        # (the phases fuse the right-hand side into the solve where the op can: other roundings)
        assert abs(int(phased.last_report.cg[0].iterations.max()) - int(eager.last_report.cg[0].iterations.max())) <= 2
    torch.testing.assert_close(phased.x, eager.x, rtol=0, atol=1e-9)
    torch.testing.assert_close(phased.v, eager.v, rtol=0, atol=1e-8)
    if preconditioner == "multigrid":
        assert graphs._predicted == int(eager.last_report.cg[0].iterations.max())
