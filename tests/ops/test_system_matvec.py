"""The fused CG matvec of implicit Euler: ``tensormass::gather_system`` (kernel 2 + epilogue) and
``ops.system_matvec``.

    1. the op = its pure-torch reference (library.REGISTRY[name].reference) = the unfused matvec
       c_M M p - c_K K p projected on the free nodes, for hooke/stvk, stress/tensor form, tets and
       triangles (2-D and 3-D membranes), with and without ``free``, float64 and float32,
       int32 and int64 incidences
    2. ops.system_matvec dispatches to the fused path where it applies (one group; every form, the
       hooke tensor form's vertex term as a node stiffness) and equals the composed path everywhere,
       with and without a node stiffness (contact penalties)
    3. a Simulator step with the fused path = TENSORMASS_BACKEND=torch
    4. input checks, no gradient, opcheck
    5. CUDA = CPU (skipped without CUDA)

Skipped when the extension is not built.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import CASES, DTYPES, FORMS, MODELS, build_scene, large_deformation, load_native, reference, rel, tol

import tensormass_torch as tm
from tensormass_torch import Material, TensorMass, ops
from tensormass_torch.ops import library, solve, stress, tensor_form

native = load_native("gather_system")
pytestmark = pytest.mark.skipif(native is None, reason="tensormass_torch._C (with gather_system) is not built")

C_MASS, C_STIFF = 1.03, 0.0123


@pytest.fixture(autouse=True)
def _extension_backend(monkeypatch):
    """These tests check which path runs: they need the default dispatch even when the suite
    runs under TENSORMASS_BACKEND=torch (a test that compares with torch sets it itself)."""
    monkeypatch.setenv("TENSORMASS_BACKEND", "auto")




def make_case(seed, kind, model, form, dtype, device="cpu"):
    rng = np.random.default_rng(seed)
    scene = build_scene(rng, kind)
    n = scene.elements.shape[0]
    mat = Material(young=torch.tensor(rng.uniform(1.0, 3.0, n)), poisson=torch.tensor(rng.uniform(0.1, 0.45, n)),
                   density=1.0, model=model, thickness=0.1)
    model_ = TensorMass(scene.mesh.to(dtype=dtype), mat, form=form).to(device)
    group = model_.groups[0]
    u = (large_deformation(rng, scene) - scene.rest).to(dtype=dtype, device=device).contiguous()
    p = torch.tensor(rng.standard_normal(u.shape), dtype=dtype, device=device)
    mass = torch.tensor(rng.uniform(0.5, 2.0, u.shape[0]), dtype=dtype, device=device)
    free = torch.tensor(rng.uniform(size=u.shape[0]) > 0.3, dtype=dtype, device=device)
    return model_, group, u, p, mass, free


def unfused(group, u, p, mass, free):
    """The solver's matvec before fusion: c_M M p - c_K K p, then CG's projection."""
    ap = C_MASS * mass.unsqueeze(-1) * p - C_STIFF * ops.dforces(group, u, p)
    if free is not None:
        ap = ap * free.unsqueeze(-1)
    return ap, (p * ap).sum(-1)


def padded_partial_dforces(group, u, p, index_dtype):
    """Kernel 1 (padded partial dforces along p) with the extension's op, and the incidences."""
    plan = group.plan
    idx, fi, inc = (t.to(index_dtype).contiguous() for t in (plan.index, plan.force_index, plan.incidences))
    T = torch.ops.tensormass
    if group.form == "stress":
        args = stress.stress_args(group)
        partial = T.stress_partial_dforces(u, p, idx, fi, plan.num_slots, *args)
    elif group.model == "stvk":
        partial = T.tensor_stvk_partial_dforces(u, p, idx, fi, plan.num_slots, *tensor_form.stvk_tensors(group))
    else:  # hooke tensor form: the edges carry the whole product (differences, no vertex term)
        partial = T.tensor_hooke_partial_forces(p, idx, fi, plan.num_slots, group.edge_k.contiguous())
    return partial, inc


@pytest.mark.parametrize("index_dtype", [torch.int64, torch.int32], ids=["i64", "i32"])
@pytest.mark.parametrize("with_free", [False, True], ids=["all-free", "free"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_op_matches_reference_and_unfused(kind, model, form, dtype, with_free, index_dtype):
    _, group, u, p, mass, free = make_case(3, kind, model, form, dtype)
    free = free if with_free else None
    partial, inc = padded_partial_dforces(group, u, p, index_dtype)
    ap, dot = torch.ops.tensormass.gather_system(partial, inc, p, mass, free, C_MASS, C_STIFF)
    assert ap.shape == u.shape and dot.shape == (u.shape[0],) and ap.dtype == dtype and dot.dtype == dtype
    # the reference on the same padded buffer (unused slots are never read by either)
    ref_ap, ref_dot = reference("gather_system")(partial, inc, p, mass, free, C_MASS, C_STIFF)
    torch.testing.assert_close(ap, ref_ap, rtol=1e-12 if dtype == torch.float64 else 1e-5, atol=0)
    assert rel(dot, ref_dot) < tol(dtype)
    if with_free:
        assert bool((ap[free == 0] == 0).all())
    # = the unfused matvec of the solver
    exp_ap, exp_dot = unfused(group, u, p, mass, free)
    assert rel(ap, exp_ap) < tol(dtype, group)
    assert rel(dot, exp_dot) < tol(dtype, group)


@pytest.mark.parametrize("with_free", [False, True], ids=["all-free", "free"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_system_matvec_dispatch(monkeypatch, kind, model, form, dtype, with_free):
    _, group, u, p, mass, free = make_case(5, kind, model, form, dtype)
    free = free if with_free else None
    calls = []
    real = native.system_matvec
    monkeypatch.setattr(native, "system_matvec", lambda *a, **k: calls.append(1) or real(*a, **k))
    ap, dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF)
    assert len(calls) == 1  # every form has a fused path
    exp_ap, exp_dot = unfused(group, u, p, mass, free)
    assert rel(ap, exp_ap) < tol(dtype, group)
    assert rel(dot, exp_dot) < tol(dtype, group)
    # [V, 1] mass / free (the solver's layout) give the same
    ap2, dot2 = ops.system_matvec([group], u, p, mass.unsqueeze(-1), None if free is None else free.unsqueeze(-1),
                                  C_MASS, C_STIFF)
    assert torch.equal(ap, ap2) and torch.equal(dot, dot2)
    # the composed path (forced torch) agrees
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    t_ap, t_dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF)
    assert rel(ap, t_ap) < tol(dtype, group)
    assert rel(dot, t_dot) < tol(dtype, group)


def random_node_stiffness(u, seed):
    """Symmetric positive semi-definite [V, d, d] blocks (as contact penalties k n n^T), zero on some nodes."""
    g = torch.Generator().manual_seed(seed)
    n = torch.randn(u.shape, generator=g, dtype=u.dtype)
    k = torch.rand(u.shape[0], generator=g, dtype=u.dtype) * (torch.rand(u.shape[0], generator=g) > 0.5)
    return (k[:, None, None] * n[:, :, None] * n[:, None, :]).to(u.device)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_node_stiffness(monkeypatch, kind, model, form, dtype):
    _, group, u, p, mass, free = make_case(17, kind, model, form, dtype)
    stiffness = random_node_stiffness(u, 3)
    ap, dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF, node_stiffness=stiffness)
    exp_ap = C_MASS * mass.unsqueeze(-1) * p - C_STIFF * (ops.dforces(group, u, p)
                                                          - torch.einsum("vab,vb->va", stiffness, p))
    exp_ap = exp_ap * free.unsqueeze(-1)
    assert rel(ap, exp_ap) < tol(dtype, group)
    assert rel(dot, (p * exp_ap).sum(-1)) < tol(dtype, group)
    # the op against its reference on the same padded buffer
    partial, inc = padded_partial_dforces(group, u, p, torch.int64)
    op = torch.ops.tensormass.gather_system(partial, inc, p, mass, free, C_MASS, C_STIFF, stiffness)
    ref = reference("gather_system")(partial, inc, p, mass, free, C_MASS, C_STIFF, stiffness)
    for a, b in zip(op, ref):
        assert rel(a, b) < tol(dtype)
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    t_ap, _ = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF, node_stiffness=stiffness)
    assert rel(ap, t_ap) < tol(dtype, group)


def test_system_matvec_two_groups_is_composed(monkeypatch):
    _, group, u, p, mass, free = make_case(7, "tet", "stvk", "stress", torch.float64)
    calls = []
    monkeypatch.setattr(native, "system_matvec", lambda *a, **k: calls.append(1))
    ap, dot = ops.system_matvec([group, group], u, p, mass, free, C_MASS, C_STIFF)
    assert not calls
    exp = (C_MASS * mass.unsqueeze(-1) * p - C_STIFF * 2 * ops.dforces(group, u, p)) * free.unsqueeze(-1)
    assert rel(ap, exp) < 1e-12


def test_system_matvec_with_gradients_stays_differentiable():
    _, group, u, p, mass, free = make_case(9, "tet", "stvk", "stress", torch.float64)
    p = p.clone().requires_grad_(True)
    ap, dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF)
    (g,) = torch.autograd.grad(dot.sum(), p)
    p_ = p.detach().clone().requires_grad_(True)
    ap_, dot_ = unfused(group, u, p_, mass, free)
    (g_,) = torch.autograd.grad(dot_.sum(), p_)
    assert rel(g, g_) < 1e-12 and rel(ap.detach(), ap_.detach()) < 1e-12


def test_op_has_no_gradient():
    _, group, u, p, mass, free = make_case(9, "tet", "hooke", "stress", torch.float64)
    partial, inc = padded_partial_dforces(group, u, p, torch.int64)
    p = p.clone().requires_grad_(True)
    ap, _ = torch.ops.tensormass.gather_system(partial, inc, p, mass, free, C_MASS, C_STIFF)
    with pytest.raises(RuntimeError, match="not differentiable"):
        ap.sum().backward()


def test_opcheck():
    _, group, u, p, mass, free = make_case(11, "tri2d", "stvk", "stress", torch.float64)
    partial, inc = padded_partial_dforces(group, u, p, torch.int64)
    partial = torch.where(library.slot_mask(partial.shape[0], inc), partial, partial.new_zeros(()))
    for fr in (None, free):
        for stiffness in (None, random_node_stiffness(u, 5)):
            torch.library.opcheck(torch.ops.tensormass.gather_system.default,
                                  (partial, inc, p, mass, fr, C_MASS, C_STIFF, stiffness),
                                  test_utils=("test_schema", "test_faketensor", "test_aot_dispatch_static"))


def test_input_checks():
    _, group, u, p, mass, free = make_case(13, "tet", "hooke", "stress", torch.float64)
    partial, inc = padded_partial_dforces(group, u, p, torch.int64)
    G = torch.ops.tensormass.gather_system
    with pytest.raises(RuntimeError, match="mass has shape"):
        G(partial, inc, p, mass[:-1], None, 1.0, 1.0)
    with pytest.raises(RuntimeError, match="p is float but partial is double|p is Float but partial is Double"):
        G(partial, inc, p.float(), mass, None, 1.0, 1.0)
    with pytest.raises(RuntimeError, match="free has shape"):
        G(partial, inc, p, mass, free[:3], 1.0, 1.0)
    with pytest.raises(RuntimeError, match="incidences has shape"):
        G(partial, inc[:-1], p, mass, None, 1.0, 1.0)
    with pytest.raises(RuntimeError, match="partial must be"):
        G(partial[0], inc, p, mass, None, 1.0, 1.0)
    with pytest.raises(RuntimeError, match="node_stiffness has shape"):
        G(partial, inc, p, mass, None, 1.0, 1.0, torch.zeros(u.shape[0], 3, dtype=u.dtype))


# --------------------------------------------------------------------- the solver


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("model", MODELS)
def test_simulator_step_matches_torch_backend(monkeypatch, model, form, dtype):
    def run():
        mesh = tm.beam_mesh(4, 1, 1, size=(0.4, 0.1, 0.1), dtype=dtype)
        mat = tm.Material(young=2e4, poisson=0.3, density=1000.0, model=model)
        fixed = mesh.vertices[:, 0] < 1e-9
        sim = tm.Simulator([tm.Body(mesh, mat, fixed=fixed)], dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.2,
                           rayleigh_stiffness=0.02, cg_tol=1e-10 if dtype == torch.float64 else 1e-5,
                           cg_max_iter=500, form=form)
        sim.step(4)
        return sim.x.clone(), sim.v.clone()

    calls, fused_calls = [], []
    # the solver's matvec: ops.system_matvec, its variant ending in the CG step length, or the one-op CG
    # (the group-level calls onto the compiled ops: native's products, the solve family's CG)
    for name, fused_module in (("system_matvec", native), ("system_matvec_alpha", native), ("system_cg", solve)):
        real, real_native = getattr(ops, name), getattr(fused_module, name)
        monkeypatch.setattr(ops, name, lambda *a, real=real, **k: calls.append(1) or real(*a, **k))
        monkeypatch.setattr(fused_module, name,
                            lambda *a, real=real_native, **k: fused_calls.append(1) or real(*a, **k))
    x, v = run()
    assert calls, "the solver did not use ops.system_matvec(_alpha)"
    assert fused_calls, "the solver did not use the fused matvec"
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    x_t, v_t = run()
    t = 1e-10 if dtype == torch.float64 else 1e-4
    assert rel(x, x_t) < t and rel(v, v_t) < t


# --------------------------------------------------------------------- CUDA


def _has_cuda_ext():
    if native is None or not torch.cuda.is_available():
        return False
    from tensormass_torch import _C

    return bool(_C.has_cuda())


@pytest.mark.skipif(not _has_cuda_ext(), reason="needs CUDA and an extension built with CUDA")
@pytest.mark.parametrize("with_free", [False, True], ids=["all-free", "free"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_cuda_matches_cpu(kind, model, form, dtype, with_free):
    _, group, u, p, mass, free = make_case(17, kind, model, form, dtype)
    free = free if with_free else None
    cpu_ap, cpu_dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF)
    _, g_cuda, u_c, p_c, mass_c, free_c = make_case(17, kind, model, form, dtype, device="cuda")
    free_c = free_c if with_free else None
    ap, dot = ops.system_matvec([g_cuda], u_c, p_c, mass_c, free_c, C_MASS, C_STIFF)
    torch.cuda.synchronize()
    assert ap.device.type == "cuda"
    assert rel(ap.cpu(), cpu_ap) < tol(dtype, group)
    assert rel(dot.cpu(), cpu_dot) < tol(dtype, group)
    # the op itself, on CUDA, against its reference
    for index_dtype in (torch.int32, torch.int64):
        partial, inc = padded_partial_dforces(g_cuda, u_c, p_c, index_dtype)
        op_ap, op_dot = torch.ops.tensormass.gather_system(partial, inc, p_c, mass_c, free_c, C_MASS, C_STIFF)
        ref_ap, ref_dot = reference("gather_system")(partial, inc, p_c, mass_c, free_c, C_MASS, C_STIFF)
        assert rel(op_ap, ref_ap) < tol(dtype) and rel(op_dot, ref_dot) < tol(dtype)
        op_ap2, op_dot2 = torch.ops.tensormass.gather_system(partial, inc, p_c, mass_c, free_c, C_MASS, C_STIFF)
        assert torch.equal(op_ap, op_ap2) and torch.equal(op_dot, op_dot2)  # deterministic
