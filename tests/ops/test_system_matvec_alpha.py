"""The CG matvec fused with the step length (gather_system_alpha, hooke_node_system_alpha via
SystemMatvec.matvec_alpha): A p and alpha / status bitwise those of the matvec followed by
cg_alpha, per object of a batch, inactive objects skipped; bad inputs rejected. On the CPU, and
on CUDA when there is one."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops import library, native
from tensormass_torch.ops.variants import DEFAULT, KernelVariants

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
pytestmark = pytest.mark.skipif(not library.ensure_registered() or not hasattr(torch.ops.tensormass,
                                                                                "gather_system_alpha"),
                                reason="needs the extension with the fused matvec ops")


def make_system(model, form, dtype, device, variants=DEFAULT):
    bodies = []
    for k in range(3):
        mesh = tm.beam_mesh(5 + k, 2, 2, size=(0.5, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.01), dtype=dtype, device=device)
        mat = tm.Material(young=1e4 * (k + 1), poisson=0.3, density=1000.0, model=model)
        bodies.append(tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9))
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), planes=[tm.Plane((0.0, 0.0, 1.0), 0.02, 1e4)],
                       form=form, device=device, dtype=dtype)
    gen = torch.Generator().manual_seed(7)
    x = sim.x + 0.01 * torch.randn(sim.x.shape, generator=gen, dtype=dtype).to(device)
    matvec = sim.system.system_matvec(1.02, 2e-4, variants=variants).load(x)
    rhs = torch.randn(sim.x.shape, generator=gen, dtype=dtype).to(device)
    return sim.system, matvec, rhs


def started(system, matvec, rhs):
    cg = system.cg_solver(rhs, cuda_graphs=False)
    cg.start(matvec, rhs, tol=1e-8, max_iter=50)
    return cg


def snapshot(state):
    return {k: getattr(state, k).clone() for k in ("alpha", "status", "rr", "counter")}


CASES = [("hooke", "tensor", "node"), ("hooke", "tensor", "padded"), ("stvk", "stress", None),
         ("corotational", "stress", None), ("stvk", "tensor", None)]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("model,form,layout", CASES)
@pytest.mark.parametrize("window", [0, DEFAULT.node_graph_window], ids=["node-order", "rows"])
def test_fused_alpha_equals_matvec_then_cg_alpha(device, dtype, model, form, layout, window):
    """Bitwise where the node graph's rows are in node order; with rows sorted by slot count the
    fused alpha sums the chunk's p . Ap in row order (node_graph.node_graph_rows): the same to rounding."""
    variants = KernelVariants(node_graph_window=window, **({} if layout is None else {"hooke_matvec": layout}))
    system, matvec, rhs = make_system(model, form, dtype, device, variants)
    cg = started(system, matvec, rhs)
    s = cg.state
    s.status[1] = cg_ops.CONVERGED  # an object that stopped: skipped by both
    s.alpha.fill_(-3.0)
    before = snapshot(s)
    sentinel = torch.full_like(s.p, 12345.0)
    matvec._ap = sentinel.clone()
    ap_fused = matvec.matvec_alpha(s.p, cg.plan, s)
    assert ap_fused is not None, "no fused path"
    fused = snapshot(s)
    for k, v in before.items():
        getattr(s, k).copy_(v)
    ap, p_dot_ap = matvec(s.p)
    cg_ops.cg_alpha(p_dot_ap, cg.plan, s, cg.native)
    for k in ("status", "counter"):
        assert torch.equal(fused[k], getattr(s, k)), k
    if window > 1:
        assert torch.allclose(fused["alpha"], s.alpha, rtol=1e-12 if dtype == torch.float64 else 1e-5, atol=0)
    else:
        assert torch.equal(fused["alpha"], s.alpha)
    assert float(fused["alpha"][1]) == -3.0 and int(fused["status"][1]) == cg_ops.CONVERGED
    nodes = cg.plan.segments.spread(torch.tensor([1.0, 0.0, 1.0], dtype=dtype, device=device)) > 0  # active objects
    assert torch.equal(ap_fused[nodes.squeeze(-1)], ap[nodes.squeeze(-1)])
    assert bool((ap_fused[~nodes.squeeze(-1)] == 12345.0).all()), "Ap of a stopped object was computed"


@pytest.mark.parametrize("device", DEVICES)
def test_cg_solve_with_fused_alpha_equals_unfused(monkeypatch, device):
    system, matvec, rhs = make_system("hooke", "tensor", torch.float64, device)
    monkeypatch.setattr(type(matvec), "solves_in_one_op", lambda self, cg: False)  # iterations op by op
    fused = system.cg_solver(rhs, cuda_graphs=False).solve(matvec, rhs, tol=1e-9, max_iter=200)
    monkeypatch.setattr(type(matvec), "matvec_alpha", lambda self, p, plan, state: None)
    system._cg = None
    plain = system.cg_solver(rhs, cuda_graphs=False).solve(matvec, rhs, tol=1e-9, max_iter=200)
    assert torch.equal(fused.solution, plain.solution) and torch.equal(fused.iterations, plain.iterations)
    assert bool(fused.converged.all())


def test_bad_inputs_are_rejected():
    system, matvec, rhs = make_system("stvk", "stress", torch.float64, "cpu")
    cg = started(system, matvec, rhs)
    s = cg.state
    group = system.model.groups[0]
    args = dict(p=s.p, u=matvec.u, ap=torch.empty_like(s.p))

    def call(**override):
        a = {**args, **override}
        native.system_matvec_alpha(group, a["u"], a["p"], system.mass.reshape(-1), system.free.reshape(-1), 1.0,
                                   1e-4, None, matvec.node_stiffness, a["ap"], cg.plan.tensors(), a.get("state", s))

    alpha_before, status_before = s.alpha.clone(), s.status.clone()
    with pytest.raises(RuntimeError, match="ap has shape"):
        call(ap=torch.empty(3, 3, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="ap is Float but partial is Double"):
        call(ap=torch.empty_like(s.p, dtype=torch.float32))
    bad_state = cg_ops.CGState(**{**s.__dict__, "rr": s.rr.float()})
    with pytest.raises(RuntimeError, match="rr is Float"):
        call(state=bad_state)
    assert torch.equal(s.alpha, alpha_before) and torch.equal(s.status, status_before)  # nothing changed
