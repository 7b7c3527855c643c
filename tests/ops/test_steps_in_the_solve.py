"""Whole implicit Euler steps in one solve kernel (hooke_node_steps through solve.StepRhs: each
step's right-hand side, its pipelined CG and its end, chained steps back to back in one kernel).

Its oracle is the same steps with the right-hand side as its own op (hooke_node_step_rhs, then
hooke_node_solve_step: ``KernelVariants(solve_step_rhs=False)``): bitwise the same states, summaries, ring rows,
u, rhs and contact stiffness, in every layout, with and without contact planes, chained (a fixed
CG budget) and one at a time (a tolerance). On the CPU the op returns False having changed
nothing; bad inputs are rejected with nothing changed."""
from __future__ import annotations

import pytest
import torch
from conftest import with_variants
from test_cg_solve_in_one_op import make_system
from test_pipelined_solve import layout, layout_variants  # noqa: F401, F811  (the fixtures)

import tensormass_torch as tm
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops import library, node_graph, solve
from tensormass_torch.ops.variants import KernelVariants
from tensormass_torch.sim import builtin as scenes

pytestmark = pytest.mark.skipif(not library.ensure_registered() or not hasattr(torch.ops.tensormass, "hooke_node_steps"),
                                reason="needs the extension with hooke_node_steps")
gpu = pytest.mark.skipif(not torch.cuda.is_available(), reason="the pipelined solve is a GPU kernel")


def beams(planes: bool, converge: bool):
    """Two hooke beams (two objects) on the GPU, damped, with or without a contact plane (through
    their lowest layer of nodes: in contact from the first step); a fixed
    CG budget or a tolerance."""
    bodies = []
    for k in range(2):
        mesh = tm.beam_mesh(6 + 2 * k, 2, 2, size=(0.6, 0.1, 0.1), origin=(0.0, 0.3 * k, 0.05), device="cuda")
        mat = tm.Material(young=2e4 * (k + 1), poisson=0.3, density=1000.0, model="hooke")
        bodies.append(tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-9))
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.06, 1e4)] if planes else None,
                       cg_tol=1e-5 if converge else 0.0, cg_max_iter=200 if converge else 10, check_every=1000,
                       cuda_graphs=True)
    sim.options.require_convergence = False
    return sim


def sofa_beam(planes: bool, converge: bool):
    """SOFA's beam at a third of its resolution (one object of 936 nodes: several chunks in every
    layout), without its plane or with it raised into the beam's lowest layer of nodes (the beam
    takes longer than these steps to reach the scene's)."""
    sim = scenes.sofa_beam(device="cuda", scale=3).simulator
    if planes:
        sim.system.planes.offsets.fill_(6.02)
    else:
        sim.system.planes = None
    if converge:
        sim.options.cg_tol, sim.options.cg_max_iter = 1e-5, 200
    return sim


def run(make, planes: bool, chained: bool, variants, monkeypatch):
    """Steps of a fresh simulator with the kernel ``variants``: 3 chains of 6 (a fixed budget) or 4
    single steps (a tolerance). Returns the simulator, its step graphs and how often the
    right-hand side's own op ran."""
    calls = []
    real = node_graph.step_rhs

    def counted(*args, **kwargs):
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(node_graph, "step_rhs", counted)
    sim = with_variants(make(planes, converge=not chained), variants)
    rows = []
    for _ in range(3 if chained else 4):
        sim.step(6 if chained else 1)
        (graphs,) = sim.system._step_graphs.values()
        rows.append((graphs.ring[:6] if chained else graphs.summary).clone())
    monkeypatch.setattr(node_graph, "step_rhs", real)
    return sim, graphs, torch.stack(rows), len(calls)


@gpu
@pytest.mark.parametrize("make", [beams, sofa_beam], ids=["two-beams", "sofa-beam"])
@pytest.mark.parametrize("planes", [False, True], ids=["free", "plane"])
@pytest.mark.parametrize("chained", [True, False], ids=["chained", "single"])
def test_steps_in_the_solve_equal_the_rhs_op_then_the_solve(monkeypatch, layout_variants, layout, make, planes,  # noqa: F811
                                                            chained):
    runs = {}
    for in_solve in (True, False):
        runs[in_solve] = run(make, planes, chained, layout_variants.replace(solve_step_rhs=in_solve), monkeypatch)
    (sim, graphs, rows, calls), (plain, plain_graphs, plain_rows, plain_calls) = runs[True], runs[False]
    assert calls == 0 and plain_calls > 0  # the solve computed every right-hand side itself
    assert graphs.cg.state.__dict__["_solve_work"].layout == layout
    assert torch.equal(sim.x, plain.x) and torch.equal(sim.v, plain.v)
    assert sim.steps_done == plain.steps_done == (18 if chained else 4)
    assert torch.equal(rows, plain_rows)  # status, iterations, r.r, b.b, |v|^2 of every step
    assert torch.equal(sim.last_report.cg[0].residual_norm, plain.last_report.cg[0].residual_norm)
    if chained:
        assert int(graphs.ring_pos) == int(plain_graphs.ring_pos) == 6
    else:  # a tolerance: the solves converged, in as many iterations
        assert bool((rows[:, 0] == cg_ops.CONVERGED).all()) and bool((rows[:, 1] > 1).all())
    # what the step leaves in the matvec: u, the last right-hand side, the contact stiffness
    matvec, plain_matvec = graphs.matvec, plain_graphs.matvec
    assert torch.equal(matvec.u, plain_matvec.u) and torch.equal(matvec._rhs, plain_matvec._rhs)
    assert (matvec.node_stiffness is None) == (not planes)
    if planes:
        assert torch.equal(matvec.node_stiffness, plain_matvec.node_stiffness)
        assert float(matvec.node_stiffness.abs().max()) > 0  # something touched the plane
    assert float(sim.v.abs().max()) > 0


def steps_call(system, matvec, device, **changes):
    """hooke_node_steps on a fresh state of ``system`` (its contact planes: ``matvec``'s stiffness),
    2 steps; keyword changes replace arguments. Returns (result, the tensors it may write)."""
    from tensormass_torch.solver.cg import CGSolver

    group = system.model.groups[0]
    like = system.model.rest
    cg = CGSolver(system.segments, like.shape, like.dtype, device, system.free, cuda_graphs=False)
    plan = solve.solve_plan(cg.plan)
    s = cg.state
    objects, planes = plan.object_chunk.numel() - 1, system.planes
    neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group)
    args = dict(neighbor=neighbor, node_k=node_k, incidences=incidences, row_node=rows, mass=system.mass.reshape(-1),
                free=system.free.reshape(-1), c_mass=1.02, c_stiff=2e-4, rest=like,
                external=system.external.contiguous(), w_coef=0.02, rayleigh_mass=0.1,
                plane_normals=planes.normals, plane_offsets=planes.offsets, plane_stiffness=planes.stiffness,
                u=torch.zeros_like(like), rhs=torch.zeros_like(like),
                node_stiffness=torch.zeros(like.shape[0], 3, 3, dtype=like.dtype, device=device), tol_sq=0.0,
                chunk_start=plan.chunk_start, chunk_object=plan.chunk_object, object_chunk=plan.object_chunk,
                chunk_nodes=int((plan.chunk_start[1:] - plan.chunk_start[:-1]).max()),
                chunk_slots=solve.chunk_slots(group, plan), max_iter=10, x=s.x, r=s.r, p=s.p,
                threshold=s.threshold, rhs_sq=s.rhs_sq, rr=s.rr, status=s.status, alpha=s.alpha, beta=s.beta,
                iterations=s.iterations,
                exchange=torch.zeros(2, like.shape[0], 4 * like.shape[1], dtype=like.dtype, device=device),
                sums=torch.zeros(4 * plan.num_chunks, dtype=torch.float64, device=device),
                counters=torch.zeros(3, dtype=torch.int32, device=device),
                state_x=like.clone(), state_v=torch.zeros_like(like), h=0.01, h_old=0.0, x_new=torch.zeros_like(like),
                v_new=torch.zeros_like(like), norms=torch.zeros(objects, dtype=like.dtype, device=device),
                summary=torch.zeros(5, objects, dtype=torch.float64, device=device),
                end_sums=torch.zeros(plan.num_chunks, dtype=torch.float64, device=device),
                end_counter=torch.zeros(objects + 1, dtype=torch.int32, device=device),
                ring=torch.zeros(4, 5, objects, dtype=torch.float64, device=device),
                ring_pos=torch.zeros(1, dtype=torch.long, device=device), carry=True, steps=2)
    args.update(changes)
    written = {k: v.clone() for k, v in args.items() if isinstance(v, torch.Tensor) and k not in ("rest", "external")}
    step_coefs = {k: args.pop(k) for k in ("h", "w_coef", "rayleigh_mass")}
    return (lambda: torch.ops.tensormass.hooke_node_steps(*library.pack("hooke_node_steps", **args, **step_coefs))), \
        args, written


def assert_unchanged(args, written):
    for k, before in written.items():
        assert torch.equal(args[k], before), k


@pytest.mark.parametrize("device", ["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
def test_bad_inputs_are_rejected_with_nothing_changed(device):
    system, matvec, _ = make_system(torch.float32, device)
    like = system.model.rest
    shared = torch.zeros_like(like)
    cases = [(dict(steps=0), "steps must be >= 1"),
             (dict(carry=False), "steps > 1 needs carry"),
             (dict(rest=like[:-1].contiguous()), "rest has shape"),
             (dict(external=system.external.double().contiguous()), "external is Double"),
             (dict(u=torch.zeros_like(like)[:, :2]), "u has shape"),
             (dict(u=shared, state_x=shared), "u shares memory with state_x"),
             (dict(rhs=shared, state_v=shared), "rhs shares memory with state_v"),
             (dict(plane_normals=None, plane_offsets=None, plane_stiffness=None), "node_stiffness is the contact"),
             (dict(node_stiffness=None), "plane_normals needs plane_offsets"),
             (dict(plane_offsets=None), "plane_normals needs plane_offsets"),
             (dict(end_counter=torch.zeros(1, dtype=torch.int32, device=device)), "end_counter has shape")]
    for change, message in cases:
        call, args, written = steps_call(system, matvec, device, **change)
        with pytest.raises(RuntimeError, match=message):
            call()
        assert_unchanged(args, written)


def test_the_cpu_has_no_such_kernel_and_changes_nothing():
    system, matvec, _ = make_system(torch.float32, "cpu")
    call, args, written = steps_call(system, matvec, "cpu")
    with pytest.raises(NotImplementedError, match="the CPU has no pipelined kernel"):
        call()
    assert_unchanged(args, written)


def test_steps_serve_only_what_the_kernel_computes():
    """solve.steps_serve: the switches (the variants given), the graph, contact stiffness exactly
    with planes, no imposed velocity, carry beyond one step."""
    system, _, _ = make_system(torch.float32, "cpu")
    group, like = system.model.groups[0], system.model.rest
    stiffness = torch.zeros(like.shape[0], 3, 3)

    def end(**changes):
        fields = dict(x=like.clone(), v=torch.zeros_like(like), dv_imposed=None, h=0.01, x_new=like.clone(),
                      v_new=like.clone(), norms=torch.zeros(3), summary=torch.zeros(5, 3, dtype=torch.float64),
                      carry=True, rhs=solve.StepRhs(like, system.external, 0.02, 0.1, torch.zeros_like(like),
                                                    system.planes), steps=3)
        fields.update(changes)
        return solve.StepEnd(**fields)

    assert solve.steps_serve(group, stiffness, None, end())
    assert not solve.steps_serve(group, None, None, end())  # planes without their stiffness buffer
    assert not solve.steps_serve(group, stiffness, torch.zeros(1), end())  # another tangent graph
    assert not solve.steps_serve(group, stiffness, None, end(dv_imposed=torch.zeros_like(like)))
    assert not solve.steps_serve(group, stiffness, None, end(carry=False))
    assert solve.steps_serve(group, stiffness, None, end(carry=False, steps=1))
    no_planes = solve.StepRhs(like, system.external, 0.02, 0.1, torch.zeros_like(like))
    assert solve.steps_serve(group, None, None, end(rhs=no_planes))
    assert not solve.steps_serve(group, stiffness, None, end(rhs=no_planes))
    for switch in ("solve_step_rhs", "fused_step_end"):  # either off: the step's parts run as their own ops
        assert not solve.steps_serve(group, stiffness, None, end(), KernelVariants(**{switch: False}))
    # the right-hand side's op serves only the node layout
    assert not solve.steps_serve(group, stiffness, None, end(), KernelVariants(hooke_matvec="padded"))
