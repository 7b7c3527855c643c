"""The device-resident CG: ``tensormass::cg_alpha / cg_update / cg_direction``, the per-object
``cg_start_status`` and ``cg_round_end``, and ``CGSolver``.

    1. each op = its pure-torch reference (solver.cg_ops), on objects in every status
    2. the solver with the ops = the solver with the reference = a dense solve; results do not
       depend on the chunk size
    3. opcheck, input checks
    4. CUDA: ops = CPU, graph replay = eager, bitwise run to run (skipped without CUDA)
"""
from __future__ import annotations

import pytest
import torch
from conftest import load_native

from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops.cg import ACTIVE, BREAKDOWN, CAPPED, CONVERGED, NONFINITE, CGState
from tensormass_torch.ops.segments import ChunkPlan
from tensormass_torch.solver import Segments
from tensormass_torch.solver.cg import CGSolver, batched_cg

native = load_native("cg_update")
needs_ext = pytest.mark.skipif(native is None, reason="tensormass_torch._C (with the CG ops) is not built")
OPS = torch.ops.tensormass if native is not None else None
LENGTHS = [7, 1, 12, 5, 9]


def random_state(plan: ChunkPlan, dtype, device="cpu", seed=0):
    g = torch.Generator().manual_seed(seed)
    v = int(plan.segments.lengths.sum())
    b = plan.segments.num_objects
    s = CGState.empty(plan, (v, 3), dtype, device)
    for t in (s.x, s.r, s.p):
        t.copy_(torch.randn(v, 3, generator=g, dtype=dtype))
    s.rr.copy_(torch.rand(b, generator=g, dtype=dtype) + 0.5)
    s.alpha.copy_(torch.rand(b, generator=g, dtype=dtype))
    s.beta.copy_(torch.rand(b, generator=g, dtype=dtype))
    s.threshold.copy_(torch.rand(b, generator=g, dtype=dtype) * 1e-3)
    s.iterations.copy_(torch.tensor([3, 0, 5, 9, 2], dtype=torch.int32).repeat(b)[:b])
    s.status.copy_(torch.tensor([ACTIVE, CONVERGED, ACTIVE, ACTIVE, BREAKDOWN], dtype=torch.int32).repeat(b)[:b])
    return s


def clone_state(s: CGState) -> CGState:
    return CGState(*[t.clone() for t in vars(s).values()])


def assert_states_close(a: CGState, b: CGState, dtype):
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for name in ("x", "r", "p", "rr", "alpha", "beta"):
        torch.testing.assert_close(getattr(a, name), getattr(b, name), rtol=tol, atol=tol, msg=name)
    assert torch.equal(a.status, b.status) and torch.equal(a.iterations, b.iterations)


@needs_ext
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
def test_ops_match_reference(dtype, chunk):
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), chunk)
    s = random_state(plan, dtype)
    v = s.x.shape[0]
    g = torch.Generator().manual_seed(1)
    p_dot_ap = torch.randn(v, generator=g, dtype=dtype).abs()
    p_dot_ap[plan.segments.node_object == 2] *= -1  # object 2: negative curvature -> breakdown
    p_dot_ap[plan.segments.node_object == 3] = float("nan")  # object 3: non-finite
    ap = torch.randn(v, 3, generator=g, dtype=dtype)
    ref, ext = clone_state(s), clone_state(s)
    cg_ops.cg_alpha(p_dot_ap, plan, ref)
    cg_ops.cg_alpha(p_dot_ap, plan, ext, OPS)
    assert_states_close(ref, ext, dtype)
    assert ref.status.tolist() == [ACTIVE, CONVERGED, BREAKDOWN, NONFINITE, BREAKDOWN]
    for max_iter in (100, 4):  # object 0 has done 3: the cap of 4 stops it
        ref_u, ext_u = clone_state(ref), clone_state(ext)
        cg_ops.cg_update(ap, plan, ref_u, max_iter)
        cg_ops.cg_update(ap, plan, ext_u, max_iter, OPS)
        assert_states_close(ref_u, ext_u, dtype)
        assert ref_u.status[0] == (ACTIVE if max_iter == 100 else CAPPED)
        assert torch.equal(ref_u.x[plan.segments.node_object != 0], s.x[plan.segments.node_object != 0])
        cg_ops.cg_direction(plan, ref_u)
        cg_ops.cg_direction(plan, ext_u, OPS)
        assert_states_close(ref_u, ext_u, dtype)
    assert int(ext.counter.abs().sum()) == 0


def inverse_blocks_of(v: int, dtype, seed=3):
    """Symmetric positive definite blocks ``[V, 3, 3]`` (a block diagonal's B^-1)."""
    g = torch.Generator().manual_seed(seed)
    half = torch.randn(v, 3, 3, generator=g, dtype=torch.float64)
    return (half @ half.transpose(1, 2) + 0.5 * torch.eye(3, dtype=torch.float64)).to(dtype)


@needs_ext
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
def test_block_update_matches_reference(dtype, chunk):
    """cg_update with inverse blocks = its reference: x and r as the plain update's, z = B^-1 r on
    the active objects' nodes (the others' z untouched), rr = r.z per object, and the stops and
    beta from r.z."""
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), chunk)
    s = random_state(plan, dtype)
    v = s.x.shape[0]
    ap = torch.randn(v, 3, generator=torch.Generator().manual_seed(1), dtype=dtype)
    inverse = inverse_blocks_of(v, dtype)
    node_object = plan.segments.node_object
    for max_iter in (100, 4):  # object 0 has done 3: the cap of 4 stops it
        ref, ext, plain = clone_state(s), clone_state(s), clone_state(s)
        z_ref, z_ext = torch.full_like(s.x, 7.0), torch.full_like(s.x, 7.0)
        cg_ops.cg_update(ap, plan, ref, max_iter, None, inverse, z_ref)
        cg_ops.cg_update(ap, plan, ext, max_iter, OPS, inverse, z_ext)
        cg_ops.cg_update(ap, plan, plain, max_iter, OPS)
        assert_states_close(ref, ext, dtype)
        tol = 1e-12 if dtype == torch.float64 else 1e-5
        torch.testing.assert_close(z_ext, z_ref, rtol=tol, atol=tol)
        torch.testing.assert_close(ext.x, plain.x, rtol=0, atol=0)
        torch.testing.assert_close(ext.r, plain.r, rtol=0, atol=0)
        active = (s.status == ACTIVE)[node_object]
        expected_z = (inverse.double() @ ext.r.double()[..., None])[..., 0]
        torch.testing.assert_close(z_ext[active].double(), expected_z[active], rtol=tol, atol=tol)
        assert bool((z_ext[~active] == 7.0).all())
        rz = torch.zeros(plan.segments.num_objects, dtype=torch.float64).index_add_(
            0, node_object, (ext.r.double() * expected_z).sum(-1))
        was_active = s.status == ACTIVE
        torch.testing.assert_close(ext.rr[was_active].double(), rz[was_active], rtol=tol, atol=tol)
        assert ext.status[0] == (ACTIVE if max_iter == 100 else CAPPED)
        if max_iter == 100:  # beta = r'.z' / r.z
            torch.testing.assert_close(ext.beta[0].double(), rz[0] / s.rr[0].double(), rtol=tol, atol=tol)
    assert int(ext.counter.abs().sum()) == 0


#: bodies splitting LENGTHS' objects (7 = 4 + 3, 1, 12 = 4 + 4 + 4, 5, 9 = 5 + 4): a coarse term's items
BODY_LENGTHS = [4, 3, 1, 4, 4, 4, 5, 5, 4]
BODY_ITEMS = [0, 2, 3, 6, 7, 9]  # each object's range of bodies


def coarse_term_of(dtype, scalar=True, device="cpu", seed=5, weight=0.5) -> cg_ops.CoarseTerm:
    """A rigid correction's coarse term over BODY_LENGTHS: N the free mask (node 2 fixed) or 3 x 3
    blocks, random lever arms and coarse values."""
    g = torch.Generator().manual_seed(seed)
    v = sum(BODY_LENGTHS)
    if scalar:
        node_inverse = torch.ones(v, dtype=dtype)
        node_inverse[2] = 0.0
    else:
        node_inverse = torch.randn(v, 3, 3, generator=g, dtype=torch.float64).to(dtype)
    node_body = Segments.from_lengths(BODY_LENGTHS).node_object.to(torch.int32)
    arm = torch.randn(v, 3, generator=g, dtype=torch.float64).to(dtype)
    coarse = torch.randn(6 * len(BODY_LENGTHS), generator=g, dtype=torch.float64).to(dtype)
    return cg_ops.CoarseTerm(*(t.to(device) for t in (node_inverse, arm, node_body, coarse)), weight)


@needs_ext
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
@pytest.mark.parametrize("scalar", [True, False], ids=["mask", "blocks"])
def test_coarse_direction_matches_reference_and_the_prolongation(dtype, chunk, scalar):
    """cg_direction with a coarse term = its reference = the rigid prolongation's z + w Z' c, then
    p = z + beta p, on the active objects; the others' p untouched."""
    from tensormass_torch.ops.multigrid import rigid_prolong

    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), chunk)
    s = random_state(plan, dtype)
    term = coarse_term_of(dtype, scalar)
    ref, ext = clone_state(s), clone_state(s)
    cg_ops.cg_direction(plan, ref, None, term)
    cg_ops.cg_direction(plan, ext, OPS, term)
    assert_states_close(ref, ext, dtype)
    corrected = rigid_prolong(*term.tensors(), s.r.reshape(-1), term.weight).view_as(s.r)
    expected = clone_state(s)
    expected.r.copy_(corrected)
    cg_ops.cg_direction(plan, expected, OPS)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(ext.p, expected.p, rtol=tol, atol=tol)
    active = (s.status == ACTIVE)[plan.segments.node_object]
    assert torch.equal(ext.p[~active], s.p[~active]) and not torch.equal(ext.p[active], s.p[active])


def coarse_vectors(dtype, seed=6):
    """(r [V, 3], z = B^-1 r, g = Z'^T r [B, 6], y = E^-1 g [B, 6], the corrected z + w Z' y) for
    the coarse term of :func:`coarse_term_of` (float64 maths, then ``dtype``)."""
    from tensormass_torch.ops.multigrid import rigid_prolong, rigid_restrict

    g = torch.Generator().manual_seed(seed)
    term = coarse_term_of(torch.float64)
    v, bodies = sum(BODY_LENGTHS), len(BODY_LENGTHS)
    r = torch.randn(v, 3, generator=g, dtype=torch.float64)
    z = (inverse_blocks_of(v, torch.float64) @ r[..., None])[..., 0]
    body_ptr = Segments.from_lengths(BODY_LENGTHS).ptr.to(torch.int32)
    restricted = rigid_restrict(term.node_inverse, term.arm, body_ptr, r.reshape(-1)).view(bodies, 6)
    half = torch.randn(bodies, 6, 6, generator=g, dtype=torch.float64)
    solution = ((half @ half.transpose(1, 2) + torch.eye(6, dtype=torch.float64)) @ restricted[..., None])[..., 0]
    corrected = rigid_prolong(term.node_inverse, term.arm, term.node_body, solution.reshape(-1), z.reshape(-1),
                              term.weight).view_as(z)
    return tuple(t.to(dtype) for t in (r, z, restricted, solution, corrected)), term.weight


@needs_ext
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_coarse_beta_is_r_dot_the_corrected_z(dtype):
    """cg_coarse_beta from r.B^-1 r and the coarse vectors (r.z = r.B^-1 r + w (Z'^T r) . y) =
    cg_dot_beta over the nodes of the corrected z, and = its reference; objects that are not
    active keep their rz and beta."""
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), 4)
    s = random_state(plan, dtype)
    (r, z, restricted, solution, corrected), weight = coarse_vectors(dtype)
    items = torch.tensor(BODY_ITEMS, dtype=torch.int64)
    cg_ops.object_dot(r, z, plan, s.rr, s, OPS)  # cg_update's r.B^-1 r
    rz0 = torch.rand(plan.segments.num_objects, generator=torch.Generator().manual_seed(8), dtype=dtype) + 1.0
    over_nodes, ref, ext = clone_state(s), clone_state(s), clone_state(s)
    rz_nodes, rz_ref, rz_ext = rz0.clone(), rz0.clone(), rz0.clone()
    cg_ops.pcg_beta(r, corrected, plan, rz_nodes, over_nodes, OPS)
    cg_ops.coarse_beta(restricted, solution, items, weight, rz_ref, ref)
    cg_ops.coarse_beta(restricted, solution, items, weight, rz_ext, ext, OPS)
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    for rz, state in ((rz_ref, ref), (rz_ext, ext)):
        torch.testing.assert_close(rz, rz_nodes, rtol=tol, atol=tol)
        torch.testing.assert_close(state.beta, over_nodes.beta, rtol=tol, atol=tol)
    stopped = s.status != ACTIVE
    assert torch.equal(rz_ext[stopped], rz0[stopped]) and torch.equal(ext.beta[stopped], s.beta[stopped])


@needs_ext
def test_coarse_term_input_checks():
    """A coarse term given in part, or of the wrong shape or dtype, and cg_coarse_beta's bad
    arguments raise one error naming them, and change nothing."""
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), 4)
    s = random_state(plan, torch.float64)
    term = coarse_term_of(torch.float64)
    before = clone_state(s)
    direction = (s.p, s.r, s.beta, s.status, *plan.tensors())
    with pytest.raises(RuntimeError, match="node_inverse, arm, node_body and coarse together"):
        OPS.cg_direction(*direction, term.node_inverse, term.arm, None, term.coarse, 0.5)
    with pytest.raises(RuntimeError, match="node_body is"):
        OPS.cg_direction(*direction, term.node_inverse, term.arm, term.node_body.long(), term.coarse, 0.5)
    with pytest.raises(RuntimeError, match="coarse must be"):
        OPS.cg_direction(*direction, term.node_inverse, term.arm, term.node_body, term.coarse[:5], 0.5)
    with pytest.raises(RuntimeError, match="arm has shape"):
        OPS.cg_direction(*direction, term.node_inverse, term.arm[:3], term.node_body, term.coarse, 0.5)
    u = torch.randn(len(BODY_LENGTHS), 6, dtype=torch.float64)
    items = torch.tensor(BODY_ITEMS, dtype=torch.int64)
    rz = torch.ones_like(s.rr)
    with pytest.raises(RuntimeError, match="item_ptr has shape"):
        OPS.cg_coarse_beta(s.rr, u, u, items[:3], 0.5, s.status, rz, s.beta)
    with pytest.raises(RuntimeError, match="v has shape"):
        OPS.cg_coarse_beta(s.rr, u, u[:, :3].contiguous(), items, 0.5, s.status, rz, s.beta)
    with pytest.raises(RuntimeError, match="rz must be a buffer of its own"):
        OPS.cg_coarse_beta(s.rr, u, u, items, 0.5, s.status, s.beta, s.beta)
    assert_states_close(s, before, torch.float64)
    assert bool((rz == 1).all())


def alpha_dot_inputs(plan: ChunkPlan, dtype, device="cpu", seed=2):
    """(ap [V, 3], free [V, 1]) for cg_alpha_dot: object 2's p.Ap negative (breakdown), object 3's
    non-finite, every third node fixed."""
    g = torch.Generator().manual_seed(seed)
    v = int(plan.segments.lengths.sum())
    ap = torch.randn(v, 3, generator=g, dtype=dtype)
    free = (torch.arange(v) % 3 != 0).to(dtype).unsqueeze(1)
    return ap.to(device), free.to(device)


@needs_ext
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
@pytest.mark.parametrize("masked", [True, False], ids=["free", "all-free"])
def test_alpha_dot_matches_reference_and_cg_alpha(dtype, chunk, masked):
    """cg_alpha_dot = its reference = the projection, the per-node dots and cg_alpha as three
    steps: Ap projected on the active objects' nodes only, the same step lengths and stops."""
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), chunk)
    s = random_state(plan, dtype)
    ap, free = alpha_dot_inputs(plan, dtype)
    s.p.copy_(ap)  # p . Ap > 0 but where made otherwise below
    node_object = plan.segments.node_object
    s.p[node_object == 2] *= -1  # breakdown
    ap[node_object == 3, 0] = float("nan")  # non-finite
    free = free if masked else None
    ref, ext, steps = clone_state(s), clone_state(s), clone_state(s)
    ap_ref, ap_ext = ap.clone(), ap.clone()
    cg_ops.cg_alpha_dot(ap_ref, free, plan, ref)
    cg_ops.cg_alpha_dot(ap_ext, free, plan, ext, OPS)
    assert_states_close(ref, ext, dtype)
    torch.testing.assert_close(ap_ext, ap_ref, rtol=0, atol=0, equal_nan=True)
    projected = ap if free is None else ap * free
    cg_ops.cg_alpha((steps.p * projected).sum(-1), plan, steps)
    assert_states_close(ref, steps, dtype)
    assert ref.status.tolist() == [ACTIVE, CONVERGED, BREAKDOWN, NONFINITE, BREAKDOWN]
    active = (s.status == ACTIVE)[node_object].unsqueeze(1)  # objects 0, 2 and 3 at the start
    torch.testing.assert_close(ap_ext, torch.where(active, projected, ap), rtol=0, atol=0, equal_nan=True)
    assert int(ext.counter.abs().sum()) == 0


@needs_ext
def test_solver_takes_unfused_products_in_one_op(monkeypatch):
    """A product without its dots goes through cg_alpha_dot (not the projection, dots and
    cg_alpha), with the reference's iterates; one with autograd history, or a mask of another
    dtype, takes the three steps."""
    sizes = [6, 4]
    a = spd_blocks(sizes, torch.float64, seed=5)
    seg = Segments.from_lengths(sizes)
    rhs = torch.randn(10, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    free = torch.ones(10, 1, dtype=torch.float64)
    free[[0, 7]] = 0
    calls = []
    alpha_dot = cg_ops.cg_alpha_dot
    monkeypatch.setattr(cg_ops, "cg_alpha_dot", lambda *a, **k: calls.append(1) or alpha_dot(*a, **k))
    matvec = lambda p: (a @ p.reshape(-1)).view_as(p)  # noqa: E731
    native_run = batched_cg(matvec, rhs, seg, free=free, tol=1e-10, max_iter=300)
    assert calls
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    reference = batched_cg(matvec, rhs, seg, free=free, tol=1e-10, max_iter=300)
    torch.testing.assert_close(native_run.solution, reference.solution, rtol=1e-9, atol=1e-12)
    assert torch.equal(native_run.iterations, reference.iterations)
    monkeypatch.setenv("TENSORMASS_BACKEND", "auto")
    calls.clear()
    batched_cg(matvec, rhs, seg, free=free.float(), tol=1e-10, max_iter=300)
    assert not calls


@needs_ext
def test_update_detects_convergence_and_nonfinite_residual():
    plan = ChunkPlan.from_segments(Segments.from_lengths([3, 3]), 2)
    for native_ops in (None, OPS):
        s = random_state(plan, torch.float64)
        s.status.zero_()
        s.alpha.fill_(1.0)
        ap = s.r.clone()  # alpha 1: r -= ap makes r exactly 0 for object 0 ...
        ap[3:] = float("inf")  # ... and non-finite for object 1
        cg_ops.cg_update(ap, plan, s, 100, native_ops)
        assert s.status.tolist() == [CONVERGED, NONFINITE]


def start_inputs(dtype, device="cpu"):
    """Six objects, one of each start: non-finite r.r, converged by tol^2 b.b, converged by the
    floor only, active, held by the gate (r.r above any threshold), non-finite and gated."""
    plan = ChunkPlan.from_segments(Segments.from_lengths([1] * 6), 1)
    s = CGState.empty(plan, (6, 3), dtype, device)
    nan, inf = float("nan"), float("inf")
    s.rr.copy_(torch.tensor([nan, 1e-6, 0.5, 2.0, 9.0, inf]))
    s.rhs_sq.fill_(4.0)
    s.iterations.fill_(7)
    s.alpha.fill_(0.5)
    s.beta.fill_(0.25)
    floor = torch.tensor([0.0, 0.0, 1.0, 1.0, 1.0, 0.0], dtype=dtype, device=device)
    gate = torch.tensor([ACTIVE, ACTIVE, ACTIVE, ACTIVE, CONVERGED, CAPPED], dtype=torch.int32, device=device)
    return s, floor, gate


@pytest.mark.parametrize("backend", [None, "ext"], ids=["torch", "ext"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
def test_start_status_takes_the_floor_and_the_gate(backend, dtype):
    """cg_start_status: threshold tol^2 b.b raised to the floor, infinite where the gate holds the
    object; statuses against it (also capped for max_iter 0); counts and step scalars zero."""
    if backend == "ext" and OPS is None:
        pytest.skip("the extension is not built")
    ops = OPS if backend == "ext" else None
    s, floor, gate = start_inputs(dtype)
    cg_ops.start_status(s, 1e-4, 50, ops, floor=floor, gate=gate)
    assert s.status.tolist() == [NONFINITE, CONVERGED, CONVERGED, ACTIVE, CONVERGED, NONFINITE]
    assert s.threshold.tolist() == pytest.approx([4e-4, 4e-4, 1.0, 1.0, float("inf"), float("inf")])
    assert s.iterations.tolist() == [0] * 6 and s.alpha.tolist() == [0.0] * 6 and s.beta.tolist() == [0.0] * 6
    s, _, _ = start_inputs(dtype)
    cg_ops.start_status(s, 1e-4, 0, ops)  # no floor, no gate; max_iter 0: the active ones are capped
    assert s.status.tolist() == [NONFINITE, CONVERGED, CAPPED, CAPPED, CAPPED, NONFINITE]


@pytest.mark.parametrize("backend", [None, "ext"], ids=["torch", "ext"])
def test_round_end_takes_the_rounds_failures_and_the_new_residuals_status(backend):
    """cg_round_end: active objects add the round's iterations and take its breakdown or
    non-finite status, else their new r.r's status; stopped objects are left as they are."""
    if backend == "ext" and OPS is None:
        pytest.skip("the extension is not built")
    ops = OPS if backend == "ext" else None
    plan = ChunkPlan.from_segments(Segments.from_lengths([1] * 6), 1)
    s, rounds = (CGState.empty(plan, (6, 3), torch.float64, "cpu") for _ in range(2))
    s.rr.copy_(torch.tensor([0.5, 2.0, float("nan"), 0.5, 0.5, 2.0], dtype=torch.float64))
    s.threshold.fill_(1.0)
    s.status.copy_(torch.tensor([ACTIVE, ACTIVE, ACTIVE, ACTIVE, CONVERGED, CAPPED], dtype=torch.int32))
    s.iterations.fill_(10)
    rounds.status.copy_(torch.tensor([CONVERGED, CAPPED, CONVERGED, BREAKDOWN, NONFINITE, CONVERGED],
                                     dtype=torch.int32))
    rounds.iterations.copy_(torch.tensor([1, 2, 3, 4, 5, 6], dtype=torch.int32))
    cg_ops.round_end(s, rounds, ops)
    assert s.status.tolist() == [CONVERGED, ACTIVE, NONFINITE, BREAKDOWN, CONVERGED, CAPPED]
    assert s.iterations.tolist() == [11, 12, 13, 14, 10, 10]


@needs_ext
def test_start_status_and_round_end_input_checks():
    """Bad shapes, dtypes or aliases: one error naming the argument, nothing written."""
    s, floor, gate = start_inputs(torch.float64)
    s.rr.fill_(2.0)  # (finite: the comparison below)
    before = clone_state(s)
    start = (s.rr, s.rhs_sq, 1e-4, 50, s.threshold, s.status, s.iterations, s.alpha, s.beta)
    with pytest.raises(RuntimeError, match="floor has shape"):
        OPS.cg_start_status(*start, floor[:2], gate)
    with pytest.raises(RuntimeError, match="gate is"):
        OPS.cg_start_status(*start, floor, gate.long())
    with pytest.raises(RuntimeError, match="gate must be another solve's statuses"):
        OPS.cg_start_status(*start, floor, s.status)
    with pytest.raises(RuntimeError, match="max_iter must be >= 0"):
        OPS.cg_start_status(s.rr, s.rhs_sq, 1e-4, -1, *start[4:])
    with pytest.raises(RuntimeError, match="threshold is"):
        OPS.cg_round_end(s.rr, s.threshold.float(), s.status.clone(), s.iterations.clone(), s.status, s.iterations)
    with pytest.raises(RuntimeError, match="must be the round's"):
        OPS.cg_round_end(s.rr, s.threshold, s.status, s.iterations.clone(), s.status, s.iterations)
    assert_states_close(s, before, torch.float64)
    assert torch.equal(s.threshold, before.threshold)


def spd_blocks(lengths, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    blocks = []
    for n in lengths:
        q = torch.randn(3 * n, 3 * n, generator=g, dtype=dtype)
        blocks.append(q @ q.T + 3 * n * torch.eye(3 * n, dtype=dtype))
    return torch.block_diag(*blocks)


@pytest.mark.parametrize("backend", ["ext", "torch"])
def test_solver_matches_dense_solve(monkeypatch, backend):
    if backend == "ext" and native is None:
        pytest.skip("extension not built")
    monkeypatch.setenv("TENSORMASS_BACKEND", "auto" if backend == "ext" else "torch")
    a = spd_blocks(LENGTHS, torch.float64)
    rhs = torch.randn(sum(LENGTHS), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    matvec = lambda p: (a @ p.reshape(-1)).view_as(p)  # noqa: E731
    seg = Segments.from_lengths(LENGTHS)
    solver = CGSolver(seg, rhs.shape, rhs.dtype, rhs.device)
    assert (solver.native is not None) == (backend == "ext")
    res = solver.solve(matvec, rhs, tol=1e-12, max_iter=500)
    exact = torch.linalg.solve(a, rhs.reshape(-1)).view_as(rhs)
    assert bool(res.converged.all()) and float((res.solution - exact).abs().max()) < 1e-9
    again = solver.solve(matvec, rhs, tol=1e-12, max_iter=500)  # buffers reused: same answer
    assert torch.equal(again.solution, res.solution) and torch.equal(again.iterations, res.iterations)


@needs_ext
def test_native_and_reference_iterates_agree_for_any_chunk(monkeypatch):
    a = spd_blocks(LENGTHS, torch.float64, seed=3)
    rhs = torch.randn(sum(LENGTHS), 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    matvec = lambda p: (a @ p.reshape(-1)).view_as(p)  # noqa: E731
    seg = Segments.from_lengths(LENGTHS)
    results = []
    for chunk in (1, 5, 512):
        solver = CGSolver(seg, rhs.shape, rhs.dtype, rhs.device, chunk_nodes=chunk)
        results.append(solver.solve(matvec, rhs, tol=0.0, max_iter=6))
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    results.append(batched_cg(matvec, rhs, seg, tol=0.0, max_iter=6))
    for r in results[1:]:
        assert float((r.solution - results[0].solution).abs().max()) < 1e-12
        # 6 iterations, or 3 n for an object of n nodes: exact in 3 n, then converged to roundoff
        assert r.iterations.tolist() == [min(6, 3 * n) for n in LENGTHS]


@needs_ext
def test_opcheck():
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), 4)
    s = random_state(plan, torch.float64)
    p_dot_ap = torch.rand(s.x.shape[0], dtype=torch.float64)
    utils = ("test_schema", "test_faketensor")
    torch.library.opcheck(OPS.cg_alpha.default, (p_dot_ap, *plan.tensors(), s.rr, s.status, s.alpha, s.scratch,
                                                 s.counter), test_utils=utils)
    torch.library.opcheck(OPS.cg_update.default, (s.x, s.r, s.p, s.p.clone(), s.alpha, *plan.tensors(), s.threshold,
                                                  50, s.rr, s.status, s.beta, s.iterations, s.scratch, s.counter),
                          test_utils=utils)
    torch.library.opcheck(OPS.cg_direction.default, (s.p, s.r, s.beta, s.status, *plan.tensors()), test_utils=utils)
    z = torch.zeros_like(s.x)
    torch.library.opcheck(OPS.cg_update.default, (s.x, s.r, s.p, s.p.clone(), s.alpha, *plan.tensors(), s.threshold,
                                                  50, s.rr, s.status, s.beta, s.iterations, s.scratch, s.counter,
                                                  inverse_blocks_of(s.x.shape[0], torch.float64), z),
                          test_utils=utils)
    ap, free = alpha_dot_inputs(plan, torch.float64)
    for mask in (free, None):
        torch.library.opcheck(OPS.cg_alpha_dot.default, (s.p, ap.clone(), mask, *plan.tensors(), s.rr, s.status,
                                                         s.alpha, s.scratch, s.counter), test_utils=utils)


@needs_ext
def test_input_checks():
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), 4)
    s = random_state(plan, torch.float64)
    with pytest.raises(RuntimeError, match="rr has shape"):
        OPS.cg_alpha(s.x[:, 0].contiguous(), *plan.tensors(), s.rr[:2], s.status, s.alpha, s.scratch, s.counter)
    with pytest.raises(RuntimeError, match="status is"):
        OPS.cg_direction(s.p, s.r, s.beta, s.status.long(), *plan.tensors())
    with pytest.raises(RuntimeError, match="ap has shape"):
        OPS.cg_update(s.x, s.r, s.p, s.p[:2], s.alpha, *plan.tensors(), s.threshold, 5, s.rr, s.status, s.beta,
                      s.iterations, s.scratch, s.counter)
    update = (s.x, s.r, s.p, s.p.clone(), s.alpha, *plan.tensors(), s.threshold, 5, s.rr, s.status, s.beta,
              s.iterations, s.scratch, s.counter)
    inverse = inverse_blocks_of(s.x.shape[0], torch.float64)
    before = clone_state(s)
    with pytest.raises(RuntimeError, match="inverse_blocks and z together"):
        OPS.cg_update(*update, inverse, None)
    with pytest.raises(RuntimeError, match="inverse_blocks has shape"):
        OPS.cg_update(*update, inverse[:, :2, :2].contiguous(), torch.zeros_like(s.x))
    with pytest.raises(RuntimeError, match="z must be a buffer of its own"):
        OPS.cg_update(*update, inverse, s.r)
    assert_states_close(s, before, torch.float64)  # nothing changed
    ap, free = alpha_dot_inputs(plan, torch.float64)
    with pytest.raises(RuntimeError, match="free has shape"):
        OPS.cg_alpha_dot(s.p, ap, free[:, 0].contiguous(), *plan.tensors(), s.rr, s.status, s.alpha, s.scratch,
                         s.counter)
    with pytest.raises(RuntimeError, match="ap is"):
        OPS.cg_alpha_dot(s.p, ap.float(), free, *plan.tensors(), s.rr, s.status, s.alpha, s.scratch, s.counter)
    with pytest.raises(ValueError, match="chunk_nodes"):
        ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), 0)


# --------------------------------------------------------------------- CUDA


def _cuda_ready():
    return native is not None and torch.cuda.is_available() and cg_ops.native_ops_for(
        torch.zeros(1, device="cuda")) is not None


needs_cuda = pytest.mark.skipif(not _cuda_ready(), reason="needs CUDA and the CUDA build of the extension")


@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
def test_cuda_ops_match_cpu(dtype, chunk):
    lengths = LENGTHS + [3000, 1]
    plan = ChunkPlan.from_segments(Segments.from_lengths(lengths), chunk)
    s = random_state(plan, dtype)
    s.status.copy_(torch.tensor([ACTIVE, CONVERGED, ACTIVE, ACTIVE, BREAKDOWN, ACTIVE, ACTIVE], dtype=torch.int32))
    s.iterations.zero_()
    v = s.x.shape[0]
    g = torch.Generator().manual_seed(7)
    p_dot_ap = torch.rand(v, generator=g, dtype=dtype)
    ap = torch.randn(v, 3, generator=g, dtype=dtype)
    cpu, gpu = clone_state(s), CGState(*[t.cuda() for t in vars(s).values()])
    gplan = ChunkPlan.from_segments(Segments.from_lengths(lengths, device="cuda"), chunk)
    for _ in range(3):
        cg_ops.cg_alpha(p_dot_ap, plan, cpu, OPS)
        cg_ops.cg_update(ap, plan, cpu, 50, OPS)
        cg_ops.cg_direction(plan, cpu, OPS)
        cg_ops.cg_alpha(p_dot_ap.cuda(), gplan, gpu, OPS)
        cg_ops.cg_update(ap.cuda(), gplan, gpu, 50, OPS)
        cg_ops.cg_direction(gplan, gpu, OPS)
    assert_states_close(cpu, CGState(*[t.cpu() for t in vars(gpu).values()]), dtype)
    assert int(gpu.counter.abs().sum()) == 0
    ap, free = alpha_dot_inputs(plan, dtype)
    ap_gpu = ap.cuda()
    cg_ops.cg_alpha_dot(ap, free, plan, cpu, OPS)
    cg_ops.cg_alpha_dot(ap_gpu, free.cuda(), gplan, gpu, OPS)
    assert_states_close(cpu, CGState(*[t.cpu() for t in vars(gpu).values()]), dtype)
    torch.testing.assert_close(ap_gpu.cpu(), ap, rtol=0, atol=0)
    inverse = inverse_blocks_of(v, dtype)
    z_cpu, z_gpu = torch.zeros_like(ap), torch.zeros_like(ap_gpu)
    cg_ops.cg_update(ap, plan, cpu, 50, OPS, inverse, z_cpu)
    cg_ops.cg_update(ap_gpu, gplan, gpu, 50, OPS, inverse.cuda(), z_gpu)
    assert_states_close(cpu, CGState(*[t.cpu() for t in vars(gpu).values()]), dtype)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(z_gpu.cpu(), z_cpu, rtol=tol, atol=tol)


@needs_cuda
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("chunk", [1, 4, 512])
def test_cuda_coarse_ops_match_cpu(dtype, chunk):
    """cg_direction with a coarse term (both forms of N) and cg_coarse_beta: CUDA = CPU."""
    plan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS), chunk)
    gplan = ChunkPlan.from_segments(Segments.from_lengths(LENGTHS, device="cuda"), chunk)
    s = random_state(plan, dtype)
    for scalar in (True, False):
        term, gterm = coarse_term_of(dtype, scalar), coarse_term_of(dtype, scalar, "cuda")
        cpu, gpu = clone_state(s), CGState(*[t.cuda() for t in vars(s).values()])
        cg_ops.cg_direction(plan, cpu, OPS, term)
        cg_ops.cg_direction(gplan, gpu, OPS, gterm)
        assert_states_close(cpu, CGState(*[t.cpu() for t in vars(gpu).values()]), dtype)
    (_, _, restricted, solution, _), weight = coarse_vectors(dtype)
    items = torch.tensor(BODY_ITEMS, dtype=torch.int64)
    cpu, gpu = clone_state(s), CGState(*[t.cuda() for t in vars(s).values()])
    rz_cpu = torch.ones_like(s.rr)
    rz_gpu = rz_cpu.cuda()
    cg_ops.coarse_beta(restricted, solution, items, weight, rz_cpu, cpu, OPS)
    cg_ops.coarse_beta(restricted.cuda(), solution.cuda(), items.cuda(), weight, rz_gpu, gpu, OPS)
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    torch.testing.assert_close(rz_gpu.cpu(), rz_cpu, rtol=tol, atol=tol)
    assert_states_close(cpu, CGState(*[t.cpu() for t in vars(gpu).values()]), dtype)


@needs_cuda
def test_cuda_graph_replay_equals_eager_and_is_bitwise_reproducible():
    lengths = [500, 2000, 37]
    a = spd_blocks([n // 10 + 1 for n in lengths], torch.float64).cuda()
    sizes = [n // 10 + 1 for n in lengths]
    seg = Segments.from_lengths(sizes, device="cuda")
    rhs = torch.randn(sum(sizes), 3, dtype=torch.float64, device="cuda")
    matvec = lambda p: (a @ p.reshape(-1)).view_as(p)  # noqa: E731 (reads only a: capturable)
    eager = CGSolver(seg, rhs.shape, rhs.dtype, rhs.device, cuda_graphs=False).solve(matvec, rhs, tol=1e-10,
                                                                                     max_iter=300, check_every=4)
    graphed = CGSolver(seg, rhs.shape, rhs.dtype, rhs.device)
    runs = [graphed.solve(matvec, rhs, tol=1e-10, max_iter=300, check_every=4, graph_key="dense") for _ in range(3)]
    assert graphed.graph_replays > 0
    for r in runs:
        assert torch.equal(r.solution, eager.solution) and torch.equal(r.iterations, eager.iterations)
        assert bool(r.converged.all())


def test_run_captured_runs_eagerly_then_replays(monkeypatch):
    """The capture-and-replay bookkeeping shared by CGSolver and StepGraphs, with a stand-in for
    torch.cuda's graphs (the real ones run in the CUDA tests)."""
    from contextlib import contextmanager

    from tensormass_torch.solver.capture import run_captured

    class FakeGraph:
        def __init__(self):
            self.recorded = None

        def replay(self):
            self.recorded()

    capturing = []

    @contextmanager
    def fake_capture(graph):
        capturing.append(graph)
        try:
            yield
        finally:
            capturing.pop()

    monkeypatch.setattr(torch.cuda, "CUDAGraph", FakeGraph)
    monkeypatch.setattr(torch.cuda, "graph", fake_capture)
    calls = []

    def work():
        if capturing:  # what a capture records is replayed later
            capturing[-1].recorded = lambda: calls.append("replayed")
        else:
            calls.append("eager")

    graphs = {}
    assert run_captured(graphs, "k", work) is False and calls == ["eager"]  # warm-up, then captured
    assert run_captured(graphs, "k", work) is True and calls == ["eager", "replayed"]

    def uncapturable():
        if capturing:
            raise RuntimeError("operation not permitted when stream is capturing")
        calls.append("eager")

    calls.clear()
    assert run_captured(graphs, "u", uncapturable) is False and graphs["u"] is False
    assert run_captured(graphs, "u", uncapturable) is False and calls == ["eager", "eager"]
