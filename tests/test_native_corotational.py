"""The corotational model with SOFA's QR frame (rotation="qr") in the compiled ops (model id 2).

    1. element, padded and fused ops = the pure-torch reference (reference/corotational.py with
       qr_rotations), forces and dforces, tetrahedra and 3-D triangles (membranes), float64 and
       float32, on jittered meshes at large deformations with large rotations (incl. 180 degrees)
    2. zero force under rigid motion through the native path
    3. dispatch: native.supports is True for rotation="qr" only (polar stays on the reference);
       ops.* and the fused CG matvec through the extension = TENSORMASS_BACKEND=torch
    4. autograd: the forces' u-gradient is the reference vjp (not dforces: the corotational forces
       are not an energy gradient through R), dforces' du-gradient is dforces(u, g); gradcheck
    5. a Simulator step with a corotational qr body = TENSORMASS_BACKEND=torch
    6. CUDA parity (skipped without CUDA)

Skipped when the extension is not built.
"""
from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch

from conftest import load_native, build_scene, large_deformation, rel
from tensormass_torch import Material, TensorMass, ops
from tensormass_torch.reference import corotational as co
from tensormass_torch.reference import gather as ref_gather


native = load_native()
pytestmark = pytest.mark.skipif(native is None, reason="tensormass_torch._C is not built")
T = torch.ops.tensormass if native is not None else None
KINDS = ("tet", "tri3d")
TOL = {torch.float64: 1e-12, torch.float32: 2e-5}


def rotation(axis, angle):
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def make_group(rng, kind, dtype=torch.float64, rot="qr", cells=None):
    scene = build_scene(rng, kind, cells=cells)
    n = scene.elements.shape[0]
    young = torch.tensor(rng.uniform(1.0, 3.0, n))
    poisson = torch.tensor(rng.uniform(0.1, 0.45, n))
    mat = Material(young=young, poisson=poisson, density=1.0, model="corotational", rotation=rot, thickness=0.1)
    tm = TensorMass(scene.mesh.to(dtype=dtype), mat, form="stress")
    return tm, tm.groups[0], scene


def deformations(rng, scene):
    """Positions [V, 3] float64: a large deformation with a random rotation, and one turned by 180 degrees."""
    x = large_deformation(rng, scene)
    X = scene.rest.numpy()
    c = X.mean(0)
    y = large_deformation(rng, scene, rotate=False).numpy()
    q = rotation(rng.uniform(-1, 1, 3), math.pi)
    x180 = torch.tensor((y - c) @ q.T + c + 0.3, dtype=torch.float64)
    return [x, x180]


def reference(group, u, du):
    """(element forces, element dforces, forces, dforces) of the reference in float64."""
    u, du = u.double(), du.double()
    rest = group.rest_elements.double()
    u_e, du_e = u[group.elements], du[group.elements]
    lam, mu = group.lame()
    lam, mu = lam.double(), mu.double()
    m, vol = group.shape_vectors.double(), group.measure.double()
    proj = None if group.projector is None else group.projector.double()
    rot = co.qr_rotations(rest + u_e, rest)
    ef = co.forces(u_e, m, vol, lam, mu, rot, proj)
    edf = co.dforces(du_e, m, vol, lam, mu, rot, proj)
    plan = group.plan
    gather = lambda f: ref_gather.node_gather(f, plan.index, plan.force_index, plan.num_slots, plan.num_nodes)
    return ef, edf, gather(ef), gather(edf)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_native_equals_reference(kind, dtype, rng):
    _, group, scene = make_group(rng, kind, dtype)
    assert native.supports(group, scene.rest.to(dtype))
    for x in deformations(rng, scene):
        u = (x - scene.rest).to(dtype).contiguous()
        du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
        ref = reference(group, u, du)
        got = (native.element_forces(group, u), native.element_dforces(group, u, du), native.forces(group, u),
               native.dforces(group, u, du))
        for a, b in zip(got, ref):
            assert a.dtype == dtype and a.shape == b.shape
            assert rel(a, b) < TOL[dtype]


@pytest.mark.parametrize("kind", KINDS)
def test_every_stress_op_equals_its_reference(kind, rng):
    """The six stress ops with model 2 and rest_elements = native.REFERENCE (padded: used slots)."""
    _, group, scene = make_group(rng, kind)
    u = (deformations(rng, scene)[1] - scene.rest).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    p = group.plan
    idx, fidx, inc = p.index, p.force_index, p.incidences
    lam, mu = group.lame()
    tail = (group.shape_vectors, group.measure, lam, mu, group.projector, 2, group.rest_elements)
    calls = {
        "stress_element_forces": (u, idx, *tail),
        "stress_element_dforces": (u, du, idx, *tail),
        "stress_partial_forces": (u, idx, fidx, p.num_slots, *tail),
        "stress_partial_dforces": (u, du, idx, fidx, p.num_slots, *tail),
        "stress_forces": (u, idx, fidx, p.num_slots, inc, *tail),
        "stress_dforces": (u, du, idx, fidx, p.num_slots, inc, *tail),
    }
    mask = (torch.arange(p.num_slots)[:, None] < inc[None, :])[:, :, None]
    for name, args in calls.items():
        a, b = getattr(T, name)(*args), native.REFERENCE[name](*args)
        if "_partial_" in name:
            a, b = torch.where(mask, a, 0.0), torch.where(mask, b, 0.0)
        assert rel(a, b) < 1e-12, name


@pytest.mark.parametrize("angle", [0.0, 0.9, math.pi / 2, math.pi])
@pytest.mark.parametrize("kind", KINDS)
def test_zero_force_under_rigid_motion(kind, angle, rng):
    _, group, scene = make_group(rng, kind)
    q = torch.tensor(rotation((1.0, -2.0, 0.5), angle))
    x = scene.rest @ q.T + torch.tensor([0.5, -1.0, 2.0], dtype=torch.float64)
    u = (x - scene.rest).contiguous()
    scale = float(group.young.max()) * float(group.measure.max())
    assert native.forces(group, u).abs().max() < 1e-12 * scale
    assert native.element_forces(group, u).abs().max() < 1e-12 * scale


def test_supports_qr_only(rng):
    _, polar, scene = make_group(rng, "tet", rot="polar")
    _, qr, _ = make_group(rng, "tet")
    u = torch.zeros_like(scene.rest)
    assert not native.supports(polar, u)  # polar (an SVD per element) stays on the reference path
    assert native.supports(qr, u)
    with pytest.raises(RuntimeError, match="rest_elements"):
        T.stress_element_forces(u, qr.plan.index, qr.shape_vectors, qr.measure, *qr.lame(), None, 2)
    with pytest.raises(RuntimeError, match="rest_elements"):
        T.stress_element_forces(u, qr.plan.index, qr.shape_vectors, qr.measure, *qr.lame(), None, 0,
                                qr.rest_elements)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_group_dispatch_matches_torch_backend(kind, dtype, rng, monkeypatch):
    _, group, scene = make_group(rng, kind, dtype)
    u = (deformations(rng, scene)[1] - scene.rest).to(dtype).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    mass = torch.tensor(rng.uniform(0.5, 2.0, u.shape[0]), dtype=dtype)
    free = (torch.tensor(rng.uniform(0, 1, u.shape[0])) > 0.2).to(dtype)
    calls = []
    real = native.system_matvec
    monkeypatch.setattr(native, "system_matvec", lambda *a: calls.append(1) or real(*a))

    def run():
        out = [ops.element_forces(group, u), ops.forces(group, u), ops.dforces(group, u, du),
               ops.dforces(group, u, du, ops.linearize(group, u))]
        with torch.no_grad():
            out += list(ops.system_matvec([group], u, du, mass, free, 1.3, 0.01))
        return out

    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext = run()
    assert calls == [1]  # the fused CG matvec ran
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    ref = run()
    for a, b in zip(ext, ref):
        assert a.shape == b.shape and a.dtype == b.dtype
        assert rel(a, b) < TOL[dtype]


@pytest.mark.parametrize("kind", KINDS)
def test_autograd(kind, rng):
    _, group, scene = make_group(rng, kind, cells=(1, 1, 1) if kind == "tet" else (2, 2))
    u = (0.5 * (deformations(rng, scene)[0] - scene.rest)).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    g = torch.tensor(rng.standard_normal(u.shape))
    p = group.plan
    lam, mu = group.lame()
    lam, mu = lam.detach().clone(), mu.detach().clone()
    tail = lambda la, m_: (group.shape_vectors, group.measure, la, m_, group.projector, 2, group.rest_elements)
    # forces: d(g . f)/du is the reference vjp, not dforces(u, g)
    uu, la, m_ = (t.clone().requires_grad_(True) for t in (u, lam, mu))
    f = T.stress_forces(uu, p.index, p.force_index, p.num_slots, p.incidences, *tail(la, m_))
    got = torch.autograd.grad((g * f).sum(), (uu, la, m_))
    uu2, la2, m2 = (t.clone().requires_grad_(True) for t in (u, lam, mu))
    f2 = native.REFERENCE["stress_forces"](uu2, p.index, p.force_index, p.num_slots, p.incidences, *tail(la2, m2))
    want = torch.autograd.grad((g * f2).sum(), (uu2, la2, m2))
    for a, b in zip(got, want):
        assert rel(a, b) < 1e-12
    kg = T.stress_dforces(u, g, p.index, p.force_index, p.num_slots, p.incidences, *tail(lam, mu))
    assert rel(got[0], kg) > 1e-6  # the corotational forces are not an energy gradient through R
    # dforces: d/d(du) = dforces(u, g); d/du through the reference
    uu, dd = u.clone().requires_grad_(True), du.clone().requires_grad_(True)
    df = T.stress_dforces(uu, dd, p.index, p.force_index, p.num_slots, p.incidences, *tail(lam, mu))
    got = torch.autograd.grad((g * df).sum(), (uu, dd))
    assert rel(got[1], kg) < 1e-12
    uu2, dd2 = u.clone().requires_grad_(True), du.clone().requires_grad_(True)
    df2 = native.REFERENCE["stress_dforces"](uu2, dd2, p.index, p.force_index, p.num_slots, p.incidences,
                                             *tail(lam, mu))
    want = torch.autograd.grad((g * df2).sum(), (uu2, dd2))
    for a, b in zip(got, want):
        assert rel(a, b) < 1e-12
    # gradcheck of the element ops
    small = u
    args = (small.clone().requires_grad_(True), p.index, group.shape_vectors, group.measure,
            lam.clone().requires_grad_(True), mu.clone().requires_grad_(True), group.projector, 2,
            group.rest_elements)
    assert torch.autograd.gradcheck(T.stress_element_forces, args)
    args = (small.clone().requires_grad_(True), du.clone().requires_grad_(True), p.index, group.shape_vectors,
            group.measure, lam, mu, group.projector, 2, group.rest_elements)
    assert torch.autograd.gradcheck(T.stress_element_dforces, args)


def test_opcheck(rng):
    _, group, scene = make_group(rng, "tet", cells=(1, 1, 1))
    u = (deformations(rng, scene)[1] - scene.rest).contiguous().requires_grad_(True)
    lam, mu = group.lame()
    args = (u, group.plan.index, group.shape_vectors, group.measure, lam.detach(), mu.detach(), None, 2,
            group.rest_elements)
    torch.library.opcheck(T.stress_element_forces.default, args,
                          test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))


@pytest.mark.parametrize("kind", KINDS)
def test_simulator_step_matches_torch_backend(kind, monkeypatch):
    import tensormass_torch as tm

    if kind == "tet":
        mesh = tm.beam_mesh(4, 1, 1, size=(0.4, 0.1, 0.1), dtype=torch.float64)
    else:
        mesh = tm.beam_tri_mesh(4, 2, size=(0.4, 0.1), dim=3, dtype=torch.float64)
    fixed = mesh.vertices[:, 0] < 1e-9

    def run(backend):
        monkeypatch.setenv("TENSORMASS_BACKEND", backend)
        body = tm.Body(mesh, tm.Material(1e4, 0.3, 1000.0, "corotational", rotation="qr", thickness=0.01),
                       fixed=fixed)
        sim = tm.Simulator([body], dt=0.01, cg_tol=1e-10, cg_max_iter=500)
        sim.step(3)
        return sim.positions(0)

    calls = []
    real = native.forces
    monkeypatch.setattr(native, "forces", lambda g, v: calls.append(1) or real(g, v))
    ext = run("extension")
    assert calls  # the native path ran
    ref = run("torch")
    assert ext[:, 2].min() < mesh.vertices[:, 2].min()  # it sags
    torch.testing.assert_close(ext, ref, rtol=1e-9, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_matches_cpu(kind, dtype, rng):
    if not importlib.import_module("tensormass_torch._C").has_cuda():
        pytest.skip("extension built without CUDA")
    _, group, scene = make_group(rng, kind, dtype)
    u = (deformations(rng, scene)[1] - scene.rest).to(dtype).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    cpu = (native.element_forces(group, u), native.forces(group, u), native.dforces(group, u, du))
    gg = group.to("cuda")
    uc, duc = u.cuda(), du.cuda()
    gpu = (native.element_forces(gg, uc), native.forces(gg, uc), native.dforces(gg, uc, duc))
    for a, b in zip(gpu, cpu):
        assert rel(a.cpu(), b) < TOL[dtype]
