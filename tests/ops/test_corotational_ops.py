"""The corotational model in the compiled ops (model id 2), both rotation methods.

    1. tensormass::corotational_rotations (method 0 = SOFA's QR frame, 1 = polar) = the reference
       (library.REGISTRY[name].reference, ops.linearize on the torch path), tets, membranes and (polar) 2-D
       triangles, float64 and float32, at large deformations with large rotations (incl. 180
       degrees); polar on hard single elements against the closed form Q W^T of F = Q diag(s) W^T:
       rigid 180 degrees, nearly flat, inverted, inverted and nearly flat, needle-like
    2. element, padded and fused stress ops with the rotations given = the reference, forces and
       dforces; without them the ops recompute SOFA's QR frame (the older path, still served)
    3. zero force under rigid motion through the native path
    4. dispatch: native.supports both methods; ops.* and the fused CG matvec through the extension
       = TENSORMASS_BACKEND=torch; the stored rotations reach the kernels; input checks
    5. autograd: with R recomputed inside the op, the forces' u-gradient is the reference vjp;
       with R given, it is dforces(u, g, R) and R gets the reference vjp; the rotations op
       differentiates like the reference, so ops.forces has the torch path's gradient; gradcheck
    6. opcheck of the rotations op and of stress ops with rotations
    7. a Simulator with a corotational body (qr and polar) = TENSORMASS_BACKEND=torch; the
       rotations are computed a fixed number of times per step, not per CG iteration
    8. CUDA parity (skipped without CUDA)

Skipped when the extension is not built.
"""
from __future__ import annotations

import importlib
import math

import numpy as np
import pytest
import torch
from conftest import build_scene, large_deformation, load_native, rel, with_variants
from conftest import reference as op_reference

from tensormass_torch import Material, TensorMass, ops
from tensormass_torch.mesh import geometry
from tensormass_torch.ops import stress
from tensormass_torch.ops.reference import corotational as co
from tensormass_torch.ops.reference import gather as ref_gather

native = load_native("corotational_rotations")
pytestmark = pytest.mark.skipif(native is None,
                                reason="tensormass_torch._C is not built (or predates the rotations op)")
T = torch.ops.tensormass if native is not None else None
TOL = {torch.float64: 1e-12, torch.float32: 2e-5}
# (kind, rotation method): QR needs 3-D elements
CASES = [("tet", "qr"), ("tri3d", "qr"), ("tet", "polar"), ("tri3d", "polar"), ("tri2d", "polar")]
CASE_IDS = [f"{k}-{r}" for k, r in CASES]
DTYPES = [pytest.param(torch.float64, id="f64"), pytest.param(torch.float32, id="f32")]
METHOD = {"qr": 0, "polar": 1}


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
    """Positions [V, d] float64: a large deformation with a random rotation, and one turned by
    180 degrees (3-D: about a random axis; 2-D: in the plane)."""
    x = large_deformation(rng, scene)
    X = scene.rest.numpy()
    c = X.mean(0)
    y = large_deformation(rng, scene, rotate=False).numpy()
    q = rotation(rng.uniform(-1, 1, 3), math.pi) if X.shape[1] == 3 else -np.eye(2)
    x180 = torch.tensor((y - c) @ q.T + c + 0.3, dtype=torch.float64)
    return [x, x180]


def rest_of(group):
    rest = getattr(group, "rest_elements", None)
    return None if rest is None else rest.double()


def reference_rotations(group, u):
    """The reference rotations [N, d, d] in float64 (ops.linearize's torch path)."""
    proj = None if group.projector is None else group.projector.double()
    return op_reference("corotational_rotations")(u.double(), group.plan.index, group.shape_vectors.double(), proj,
                                                  rest_of(group), METHOD[group.rotation])


def reference(group, u, du):
    """(element forces, element dforces, forces, dforces) of the reference in float64."""
    u, du = u.double(), du.double()
    u_e, du_e = u[group.elements], du[group.elements]
    lam, mu = group.lame()
    lam, mu = lam.double(), mu.double()
    m, vol = group.shape_vectors.double(), group.measure.double()
    proj = None if group.projector is None else group.projector.double()
    rot = reference_rotations(group, u)
    ef = co.forces(u_e, m, vol, lam, mu, rot, proj)
    edf = co.dforces(du_e, m, vol, lam, mu, rot, proj)
    plan = group.plan
    gather = lambda f: ref_gather.node_gather(f, plan.index, plan.force_index, plan.num_slots, plan.num_nodes)
    return ef, edf, gather(ef), gather(edf)


def rotations_op(group, u, index=None):
    index = group.plan.index if index is None else index
    return T.corotational_rotations(u, index, group.shape_vectors, group.projector, getattr(group, "rest_elements", None),
                                    METHOD[group.rotation])


# ------------------------------------------------------------------ 1. the rotations op


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_rotations_op_equals_reference(kind, rot, dtype, rng, monkeypatch):
    _, group, scene = make_group(rng, kind, dtype, rot)
    d = scene.rest.shape[1]
    for x in deformations(rng, scene):
        u = (x - scene.rest).to(dtype).contiguous()
        want = reference_rotations(group, u)
        for index in (group.plan.index, group.plan.index.int()):
            got = rotations_op(group, u, index)
            assert got.dtype == dtype and got.shape == (group.elements.shape[0], d, d)
            assert (got.double() - want).abs().max() < TOL[dtype]
        eye = torch.eye(d, dtype=torch.float64)
        assert (got.double() @ got.double().transpose(1, 2) - eye).abs().max() < 10 * TOL[dtype]
        assert (torch.linalg.det(got.double()) - 1).abs().max() < 10 * TOL[dtype]
        # the group-level dispatch gives the same as the torch path's linearize
        monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
        torch_path = ops.linearize(group, u)
        monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
        assert (ops.linearize(group, u).double() - torch_path.double()).abs().max() < TOL[dtype]


def single_tets(rng, deformation_gradients):
    """Well-shaped rest tets [N, 4, 3] (a regular tet, randomly turned, moved and jittered by 10%)
    and displacements u [4 N, 3] such that each tet's deformation gradient is the given F
    [N, 3, 3]; returns (elements [N, 4], shape vectors [N, 4, 3], u)."""
    n = deformation_gradients.shape[0]
    regular = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]])
    turns = [np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(n)]
    rest = np.stack([regular @ (t * np.sign(np.linalg.det(t))).T for t in turns])
    rest = rest + 0.1 * rng.standard_normal(rest.shape) + rng.standard_normal((n, 1, 3))
    rest = torch.tensor(rest)
    m, _ = geometry.shape_vectors(rest)
    x = rest @ deformation_gradients.transpose(1, 2)
    return torch.arange(4 * n).reshape(n, 4), m, (x - rest).reshape(-1, 3)


HARD = {  # singular values (sigma_1, sigma_2, signed sigma_3) of F = Q diag(s) W^T
    "rigid": (1.0, 1.0, 1.0),
    "stretched": (2.5, 1.2, 0.4),
    "nearly_flat": (1.0, 0.7, 1e-4),
    "very_flat": (1.3, 0.8, 1e-7),
    "inverted": (1.3, 0.9, -0.4),
    "inverted_nearly_flat": (1.1, 0.8, -1e-4),
    "needle": (1.0, 2e-3, 1e-3),
    "huge": (3e20, 2e20, 1e20),  # |F|^2 overflows float32: F is scaled first
}


def random_turns(rng, n, half_turns=0):
    """[n, 3, 3] random proper rotations, the first ``half_turns`` of them by 180 degrees."""
    qs = [rotation(rng.standard_normal(3), math.pi) for _ in range(half_turns)]
    qs += [np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(n - half_turns)]
    return torch.tensor(np.stack([q * np.sign(np.linalg.det(q)) for q in qs]))


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("case", sorted(HARD))
def test_polar_hard_elements(case, dtype, rng):
    """Polar on single tets with a known answer: F = Q diag(s) W^T (Q, W random proper rotations,
    among them 180-degree turns; s_3 < 0: inverted) has the closest proper rotation Q W^T (for an
    inverted element: its smallest direction flipped back)."""
    n = 16
    q, w = random_turns(rng, n, half_turns=4), random_turns(rng, n)
    s = torch.tensor(HARD[case], dtype=torch.float64)
    F = q @ torch.diag_embed(s.expand(n, 3)) @ w.transpose(1, 2)
    want = q @ w.transpose(1, 2)
    elements, m, u = single_tets(rng, F)
    u, m = u.to(dtype).contiguous(), m.to(dtype).contiguous()
    got = T.corotational_rotations(u, elements, m, None, None, 1).double()
    # R's sensitivity to F is ~ 1 / (sigma_2 + |sigma_3|) (relative to |F|)
    eps = torch.finfo(dtype).eps
    tol = 100 * eps * s[0].item() / (s[1].item() + abs(s[2].item()))
    assert (got - want).abs().max() < tol
    assert (got @ got.transpose(1, 2) - torch.eye(3, dtype=torch.float64)).abs().max() < 100 * eps
    assert (torch.linalg.det(got) - 1).abs().max() < 100 * eps
    if dtype == torch.float64:  # = the reference's SVD
        ref = co.polar_rotations(co.deformation_gradient(u.reshape(n, 4, 3), m))
        assert (got - ref).abs().max() < tol


@pytest.mark.parametrize("dtype", DTYPES)
def test_polar_degenerate_elements_stay_finite_rotations(dtype, rng):
    """Elements collapsed onto a plane (sigma_3 = 0), a line or a point: R is not unique there,
    but it is a finite proper rotation (and exact where it is unique: the plane keeps its
    in-plane directions), and the forces are finite."""
    n = 6
    q, w = random_turns(rng, n), random_turns(rng, n)
    s = torch.tensor([[1.2, 0.7, 0.0]] * 2 + [[1.5, 0.0, 0.0]] * 2 + [[0.0, 0.0, 0.0]] * 2, dtype=torch.float64)
    F = q @ torch.diag_embed(s) @ w.transpose(1, 2)
    elements, m, u = single_tets(rng, F)
    u, m = u.to(dtype).contiguous(), m.to(dtype).contiguous()
    got = T.corotational_rotations(u, elements, m, None, None, 1).double()
    eps = torch.finfo(dtype).eps
    assert torch.isfinite(got).all()
    assert (got @ got.transpose(1, 2) - torch.eye(3, dtype=torch.float64)).abs().max() < 100 * eps
    assert (torch.linalg.det(got) - 1).abs().max() < 100 * eps
    assert (got[:2] - (q @ w.transpose(1, 2))[:2]).abs().max() < 1e3 * eps  # flat: still unique
    vol = torch.ones(n, dtype=dtype)
    f = T.stress_element_forces(u, elements, m, vol, vol, vol, None, 2, None, got.to(dtype).contiguous())
    assert torch.isfinite(f).all()


@pytest.mark.parametrize("dtype", DTYPES)
def test_polar_membranes_rigid_and_stretched(dtype, rng):
    """Membranes: a 180-degree turn (about an in-plane and about the normal axis) and a stretch
    plus rotation; R maps the rest frame onto the current one and equals the reference."""
    _, group, scene = make_group(rng, "tri3d", dtype, "polar")
    X = scene.rest
    c = X.mean(0)
    for axis in (X[group.elements[0, 1]] - X[group.elements[0, 0]], torch.tensor(rng.standard_normal(3))):
        q = torch.tensor(rotation(axis.numpy(), math.pi))
        u = ((X - c) @ q.T + c - X).to(dtype).contiguous()
        got = rotations_op(group, u).double()
        assert (got - q).abs().max() < 10 * TOL[dtype]
    x = large_deformation(rng, scene, amplitude=(0.3, 0.3))
    u = (x - X).to(dtype).contiguous()
    assert (rotations_op(group, u).double() - reference_rotations(group, u)).abs().max() < TOL[dtype]


# ------------------------------------------------------------------ 2. forces with the rotations


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_native_equals_reference(kind, rot, dtype, rng):
    _, group, scene = make_group(rng, kind, dtype, rot)
    assert native.supports(group, scene.rest.to(dtype))
    for x in deformations(rng, scene):
        u = (x - scene.rest).to(dtype).contiguous()
        du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
        ref = reference(group, u, du)
        r = native.corotational_rotations(group, u)
        got = (native.element_forces(group, u), native.element_dforces(group, u, du, r), native.forces(group, u),
               native.dforces(group, u, du, r))
        for a, b in zip(got, ref):
            assert a.dtype == dtype and a.shape == b.shape
            assert rel(a, b) < TOL[dtype]


@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_every_stress_op_equals_its_reference(kind, rot, rng):
    """The six stress ops with model 2 and the rotations given = their references (padded: used slots);
    for the QR frame, also without them (R recomputed from rest_elements inside the kernel)."""
    _, group, scene = make_group(rng, kind, rot=rot)
    u = (deformations(rng, scene)[1] - scene.rest).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    p = group.plan
    idx, fidx, inc = p.index, p.force_index, p.incidences
    lam, mu = group.lame()
    head = (group.shape_vectors, group.measure, lam, mu, group.projector, 2)
    tails = [(None, rotations_op(group, u))]
    if rot == "qr":
        tails += [(group.rest_elements, None), (group.rest_elements, rotations_op(group, u))]
    mask = (torch.arange(p.num_slots)[:, None] < inc[None, :])[:, :, None]
    for tail in tails:
        s = head + tail
        calls = {
            "stress_element_forces": (u, idx, *s),
            "stress_element_dforces": (u, du, idx, *s),
            "stress_partial_forces": (u, idx, fidx, p.num_slots, *s),
            "stress_partial_dforces": (u, du, idx, fidx, p.num_slots, *s),
            "stress_forces": (u, idx, fidx, p.num_slots, inc, *s),
            "stress_dforces": (u, du, idx, fidx, p.num_slots, inc, *s),
        }
        for name, args in calls.items():
            a, b = getattr(T, name)(*args), op_reference(name)(*args)
            if "_partial_" in name:
                a, b = torch.where(mask, a, 0.0), torch.where(mask, b, 0.0)
            assert rel(a, b) < 1e-12, (name, [t is None for t in tail])


def test_the_given_rotations_are_the_ones_used(rng):
    """The kernels read R as given: the forces with R are those of the reference with that R,
    also for an R that is not the element's own rotation (here a fixed turn of every element)."""
    _, group, scene = make_group(rng, "tet", rot="polar")
    u = (large_deformation(rng, scene) - scene.rest).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    turn = torch.tensor(rotation((0.2, -1.0, 0.4), 1.1)).expand(group.elements.shape[0], 3, 3).contiguous()
    lam, mu = group.lame()
    s = (group.shape_vectors, group.measure, lam, mu, None, 2, None, turn)
    f = T.stress_element_forces(u, group.plan.index, *s)
    df = T.stress_element_dforces(u, du, group.plan.index, *s)
    u_e = u[group.elements]
    assert rel(f, co.forces(u_e, group.shape_vectors, group.measure, lam, mu, turn)) < 1e-12
    assert rel(df, co.dforces(du[group.elements], group.shape_vectors, group.measure, lam, mu, turn)) < 1e-12
    assert rel(f, native.element_forces(group, u)) > 1e-3


# ------------------------------------------------------------------ 3. rigid motion


@pytest.mark.parametrize("angle", [0.0, 0.9, math.pi / 2, math.pi])
@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_zero_force_under_rigid_motion(kind, rot, angle, rng):
    _, group, scene = make_group(rng, kind, rot=rot)
    d = scene.rest.shape[1]
    if d == 3:
        q = torch.tensor(rotation((1.0, -2.0, 0.5), angle))
    else:
        q = torch.tensor([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]],
                         dtype=torch.float64)
    x = scene.rest @ q.T + torch.tensor([0.5, -1.0, 2.0][:d], dtype=torch.float64)
    u = (x - scene.rest).contiguous()
    scale = float(group.young.max()) * float(group.measure.max())
    assert native.forces(group, u).abs().max() < 1e-12 * scale
    assert native.element_forces(group, u).abs().max() < 1e-12 * scale
    assert (native.corotational_rotations(group, u) - q).abs().max() < 1e-12


# ------------------------------------------------------------------ 4. dispatch and checks


def test_supports_both_methods(rng):
    for kind, rot in CASES:
        _, group, scene = make_group(rng, kind, rot=rot)
        assert native.supports(group, torch.zeros_like(scene.rest)), (kind, rot)


def test_input_checks(rng):
    _, qr, scene = make_group(rng, "tet")
    _, polar, _ = make_group(rng, "tet", rot="polar")
    _, membrane, mscene = make_group(rng, "tri3d", rot="polar")
    _, planar, pscene = make_group(rng, "tri2d", rot="polar")
    u = torch.zeros_like(scene.rest)
    lam, mu = qr.lame()
    args = (u, qr.plan.index, qr.shape_vectors, qr.measure, lam, mu, None)
    r = rotations_op(qr, u)
    with pytest.raises(RuntimeError, match="rotations"):
        T.stress_element_forces(*args, 2)
    with pytest.raises(RuntimeError, match="rest_elements"):
        T.stress_element_forces(*args, 0, qr.rest_elements)
    with pytest.raises(RuntimeError, match="rotations is for the corotational"):
        T.stress_element_forces(*args, 0, None, r)
    with pytest.raises(RuntimeError, match="rotations has shape"):
        T.stress_element_forces(*args, 2, None, r[:-1])
    with pytest.raises(RuntimeError, match="rotations is Float"):
        T.stress_element_forces(*args, 2, None, r.float())
    with pytest.raises(RuntimeError, match="must be contiguous"):
        T.stress_element_forces(*args, 2, None, r.transpose(1, 2))
    with pytest.raises(RuntimeError, match="unknown rotation method"):
        T.corotational_rotations(u, qr.plan.index, qr.shape_vectors, None, qr.rest_elements, 2)
    with pytest.raises(RuntimeError, match="QR frame"):  # the QR frame needs the rest nodes
        T.corotational_rotations(u, qr.plan.index, qr.shape_vectors, None, None, 0)
    up = torch.zeros_like(pscene.rest)
    with pytest.raises(RuntimeError, match="3-D"):
        T.corotational_rotations(up, planar.plan.index, planar.shape_vectors, None, None, 0)
    with pytest.raises(RuntimeError, match="3-D"):  # without rotations the stress ops need the QR frame
        T.stress_element_forces(up, planar.plan.index, planar.shape_vectors, planar.measure, *planar.lame(), None, 2)
    um = torch.zeros_like(mscene.rest)
    with pytest.raises(RuntimeError, match="membranes"):  # the rest normals come from the rest nodes
        T.corotational_rotations(um, membrane.plan.index, membrane.shape_vectors, membrane.projector, None, 1)
    with pytest.raises(RuntimeError, match="projector"):
        T.corotational_rotations(um, membrane.plan.index, membrane.shape_vectors, None, membrane.rest_elements, 1)
    # polar tets need neither rest nodes nor a projector
    assert rel(T.corotational_rotations(u, polar.plan.index, polar.shape_vectors, None, None, 1),
               torch.eye(3, dtype=torch.float64).expand(polar.elements.shape[0], 3, 3)) < 1e-15


def count_rotations(monkeypatch, calls):
    """Appends to ``calls`` at every computation of the rotations by the ops: through
    ``native.corotational_rotations`` (ops.linearize's) and the stress family's own (its
    ``stress_args``, where no rotations are given)."""
    real = stress.corotational_rotations
    counted = lambda *a: calls.append(1) or real(*a)
    monkeypatch.setattr(native, "corotational_rotations", counted)
    monkeypatch.setattr(stress, "corotational_rotations", counted)


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_group_dispatch_matches_torch_backend(kind, rot, dtype, rng, monkeypatch):
    _, group, scene = make_group(rng, kind, dtype, rot)
    u = (deformations(rng, scene)[1] - scene.rest).to(dtype).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    mass = torch.tensor(rng.uniform(0.5, 2.0, u.shape[0]), dtype=dtype)
    free = (torch.tensor(rng.uniform(0, 1, u.shape[0])) > 0.2).to(dtype)
    fused, rotations_calls = [], []
    real_matvec = native.system_matvec
    monkeypatch.setattr(native, "system_matvec", lambda *a, **k: fused.append(a[7]) or real_matvec(*a, **k))
    count_rotations(monkeypatch, rotations_calls)

    def run():
        state = ops.linearize(group, u)
        out = [ops.element_forces(group, u), ops.forces(group, u), ops.dforces(group, u, du),
               ops.dforces(group, u, du, state), ops.element_dforces(group, u, du, state), state]
        with torch.no_grad():
            out += list(ops.system_matvec([group], u, du, mass, free, 1.3, 0.01))
            out += list(ops.system_matvec([group], u, du, mass, free, 1.3, 0.01, [state]))
        return out, state

    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext, state = run()
    assert len(fused) == 2 and fused[1] is state  # the fused CG matvec ran, with the stored rotations
    # linearize, forces x 2, dforces without state, system_matvec without states: 5; never with a state
    assert len(rotations_calls) == 5
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    ref, _ = run()
    assert len(fused) == 2 and len(rotations_calls) == 5
    for a, b in zip(ext, ref):
        assert a.shape == b.shape and a.dtype == b.dtype
        assert rel(a, b) < TOL[dtype]


# ------------------------------------------------------------------ 5. autograd


@pytest.mark.parametrize("kind", ["tet", "tri3d"])
def test_autograd_with_qr_recomputed_in_the_op(kind, rng):
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
    f2 = op_reference("stress_forces")(uu2, p.index, p.force_index, p.num_slots, p.incidences, *tail(la2, m2))
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
    df2 = op_reference("stress_dforces")(uu2, dd2, p.index, p.force_index, p.num_slots, p.incidences,
                                         *tail(lam, mu))
    want = torch.autograd.grad((g * df2).sum(), (uu2, dd2))
    for a, b in zip(got, want):
        assert rel(a, b) < 1e-12
    args = (u.clone().requires_grad_(True), p.index, group.shape_vectors, group.measure,
            lam.clone().requires_grad_(True), mu.clone().requires_grad_(True), group.projector, 2,
            group.rest_elements)
    assert torch.autograd.gradcheck(T.stress_element_forces, args)
    args = (u.clone().requires_grad_(True), du.clone().requires_grad_(True), p.index, group.shape_vectors,
            group.measure, lam, mu, group.projector, 2, group.rest_elements)
    assert torch.autograd.gradcheck(T.stress_element_dforces, args)


@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_autograd_with_rotations_given(kind, rot, rng):
    _, group, scene = make_group(rng, kind, rot=rot, cells=(1, 1, 1) if kind == "tet" else (2, 2))
    u = (0.5 * (deformations(rng, scene)[0] - scene.rest)).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    g = torch.tensor(rng.standard_normal(u.shape))
    p = group.plan
    lam, mu = (t.detach().clone() for t in group.lame())
    r = rotations_op(group, u)
    head = (group.shape_vectors, group.measure)
    fused = (p.index, p.force_index, p.num_slots, p.incidences)
    # forces: d/du with R given is dforces(u, g, R) (R fixed, K_R symmetric); R, lam, mu: reference
    uu, la, m_, rr = (t.clone().requires_grad_(True) for t in (u, lam, mu, r))
    f = T.stress_forces(uu, *fused, *head, la, m_, group.projector, 2, None, rr)
    got = torch.autograd.grad((g * f).sum(), (uu, la, m_, rr))
    kg = T.stress_dforces(u, g, *fused, *head, lam, mu, group.projector, 2, None, r)
    assert rel(got[0], kg) < 1e-12
    uu2, la2, m2, rr2 = (t.clone().requires_grad_(True) for t in (u, lam, mu, r))
    f2 = op_reference("stress_forces")(uu2, *fused, *head, la2, m2, group.projector, 2, None, rr2)
    want = torch.autograd.grad((g * f2).sum(), (uu2, la2, m2, rr2))
    for a, b in zip(got, want):
        assert rel(a, b) < 1e-12
    # dforces with R given: linear in du, independent of u
    uu, dd, rr = (t.clone().requires_grad_(True) for t in (u, du, r))
    df = T.stress_dforces(uu, dd, *fused, *head, lam, mu, group.projector, 2, None, rr)
    got = torch.autograd.grad((g * df).sum(), (uu, dd, rr), allow_unused=True)
    assert got[0] is None or got[0].abs().max() == 0
    assert rel(got[1], kg) < 1e-12
    rr2 = r.clone().requires_grad_(True)
    df2 = op_reference("stress_dforces")(u, du, *fused, *head, lam, mu, group.projector, 2, None, rr2)
    assert rel(got[2], torch.autograd.grad((g * df2).sum(), rr2)[0]) < 1e-12
    # gradcheck of the element ops, the rotations included
    args = (u.clone().requires_grad_(True), p.index, *head, lam.clone().requires_grad_(True), mu,
            group.projector, 2, None, r.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(T.stress_element_forces, args)
    args = (u, du.clone().requires_grad_(True), p.index, *head, lam, mu, group.projector, 2, None,
            r.clone().requires_grad_(True))
    assert torch.autograd.gradcheck(T.stress_element_dforces, args)


@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_rotations_op_gradient_and_model_gradient_match_the_torch_path(kind, rot, rng, monkeypatch):
    """The rotations op differentiates like the reference (at deformations with distinct singular
    values: the SVD's gradient is undefined at repeated ones), so ops.forces through the
    extension has the u-gradient of the pure-torch path, dR/du included."""
    _, group, scene = make_group(rng, kind, rot=rot, cells=(1, 1, 1) if kind == "tet" else (2, 2))
    u = (0.5 * (deformations(rng, scene)[0] - scene.rest)).contiguous()
    rest = getattr(group, "rest_elements", None)
    args = (u.clone().requires_grad_(True), group.plan.index, group.shape_vectors, group.projector, rest,
            METHOD[rot])
    assert torch.autograd.gradcheck(T.corotational_rotations, args)
    g = torch.tensor(rng.standard_normal(u.shape))

    def grad_of_forces():
        uu = u.clone().requires_grad_(True)
        return torch.autograd.grad((g * ops.forces(group, uu)).sum(), uu)[0]

    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext = grad_of_forces()
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    assert rel(ext, grad_of_forces()) < 1e-11


# ------------------------------------------------------------------ 6. opcheck


def test_opcheck(rng):
    """opcheck of the rotations op (polar tets with the AOT-dispatch check too; QR membranes) and
    of the stress ops with rotations (the older rest_elements path is checked the same way)."""
    _, tet, tscene = make_group(rng, "tet", rot="polar", cells=(1, 1, 1))
    _, tri, mscene = make_group(rng, "tri3d", rot="qr", cells=(1, 2))
    schema = ("test_schema", "test_autograd_registration", "test_faketensor")
    for group, scene, utils in ((tet, tscene, schema + ("test_aot_dispatch_dynamic",)), (tri, mscene, schema)):
        u = (0.5 * (deformations(rng, scene)[0] - scene.rest)).contiguous().requires_grad_(True)
        rest = getattr(group, "rest_elements", None)
        torch.library.opcheck(T.corotational_rotations.default,
                              (u, group.plan.index, group.shape_vectors, group.projector, rest,
                               METHOD[group.rotation]), test_utils=utils)
        lam, mu = (t.detach() for t in group.lame())
        r = rotations_op(group, u.detach()).requires_grad_(True)
        p = group.plan
        torch.library.opcheck(T.stress_element_forces.default,
                              (u, p.index, group.shape_vectors, group.measure, lam, mu, group.projector, 2, None, r),
                              test_utils=schema)
        torch.library.opcheck(T.stress_dforces.default,
                              (u, u.detach().clone().requires_grad_(True), p.index, p.force_index, p.num_slots,
                               p.incidences, group.shape_vectors, group.measure, lam, mu, group.projector, 2, None,
                               r), test_utils=schema)


# ------------------------------------------------------------------ 7. simulator


def _simulated(kind, rot, backend, monkeypatch, steps=3, **variants):
    """The positions of a corotational beam after ``steps`` steps, with the kernel variants
    ``KernelVariants(**variants)``, and its mesh."""
    import tensormass_torch as tm

    if kind == "tet":
        mesh = tm.beam_mesh(4, 1, 1, size=(0.4, 0.1, 0.1), dtype=torch.float64)
    else:
        mesh = tm.beam_tri_mesh(4, 2, size=(0.4, 0.1), dim=3, dtype=torch.float64)
    fixed = mesh.vertices[:, 0] < 1e-9
    monkeypatch.setenv("TENSORMASS_BACKEND", backend)
    body = tm.Body(mesh, tm.Material(1e4, 0.3, 1000.0, "corotational", rotation=rot, thickness=0.01), fixed=fixed)
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-10, cg_max_iter=500)
    with_variants(sim, **variants).step(steps)
    return sim.positions(0), mesh


@pytest.mark.parametrize("kind,rot", CASES[:4], ids=CASE_IDS[:4])  # the Simulator is 3-D
def test_simulator_matches_torch_backend(kind, rot, monkeypatch):
    calls = []
    real_forces = native.forces
    monkeypatch.setattr(native, "forces", lambda g, v, *rest: calls.append(1) or real_forces(g, v, *rest))
    ext, mesh = _simulated(kind, rot, "extension", monkeypatch)
    assert calls  # the native path ran
    ref, _ = _simulated(kind, rot, "torch", monkeypatch)
    assert ext[:, 2].min() < mesh.vertices[:, 2].min()  # it sags
    torch.testing.assert_close(ext, ref, rtol=1e-9, atol=1e-12)


def test_rotations_computed_per_step_not_per_cg_iteration(monkeypatch):
    """The rotations are computed once per step (the linearisation, shared by the forces, the
    right-hand side's dforce and the CG system) while the CG products only read them (element by
    element; on the node graph, the tangent reads them once: ops/test_node_tangent.py)."""
    rotations_calls, products = [], []
    count_rotations(monkeypatch, rotations_calls)
    for name in ("system_matvec", "system_matvec_alpha"):  # the CG's product, plain or ending in alpha
        real = getattr(native, name)
        monkeypatch.setattr(native, name, lambda *a, real=real, **k: products.append(a[7] is not None) or real(*a, **k))
    _simulated("tet", "polar", "extension", monkeypatch, steps=2, node_tangent=False)
    assert len(products) > 10 and all(products)  # many CG products, each given the stored rotations
    assert len(rotations_calls) <= 2


# ------------------------------------------------------------------ 8. CUDA


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("kind,rot", CASES, ids=CASE_IDS)
def test_cuda_matches_cpu(kind, rot, dtype, rng):
    if not importlib.import_module("tensormass_torch._C").has_cuda():
        pytest.skip("extension built without CUDA")
    _, group, scene = make_group(rng, kind, dtype, rot)
    u = (deformations(rng, scene)[1] - scene.rest).to(dtype).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    mass = torch.tensor(rng.uniform(0.5, 2.0, u.shape[0]), dtype=dtype)

    def run(g, v, dv, m):
        r = native.corotational_rotations(g, v)
        out = [r, native.element_forces(g, v), native.forces(g, v), native.dforces(g, v, dv, r)]
        with torch.no_grad():
            out += list(native.system_matvec(g, v, dv, m, None, 1.3, 0.01, r))
        return out

    cpu = run(group, u, du, mass)
    ref = reference_rotations(group, u)  # before the move: groups move in place
    gg = group.to("cuda")
    gpu = run(gg, u.cuda(), du.cuda(), mass.cuda())
    assert (gpu[0].cpu().double() - ref).abs().max() < TOL[dtype]
    for a, b in zip(gpu, cpu):
        assert a.device.type == "cuda" and rel(a.cpu(), b) < TOL[dtype]


def test_polar_rotation_derivative_where_singular_values_repeat():
    """The closest proper rotation (Newton's iteration, the SVD where det F <= 0) equals the
    SVD's; its derivative (the polar factor's own, not the SVD's) by gradcheck at random F (half
    of them inverted), at F = I (every singular value equal: the SVD's backward divides by 0) and
    in 2-D."""
    from tensormass_torch.ops.reference.corotational import _svd_rotation, polar_rotations

    g = torch.Generator().manual_seed(0)
    F = torch.randn(500, 3, 3, generator=g, dtype=torch.float64)
    for batch in (F, torch.eye(3, dtype=torch.float64) + 0.3 * F, F[:, :2, :2]):
        torch.testing.assert_close(polar_rotations(batch), _svd_rotation(batch), rtol=0, atol=1e-12)
    for F in (torch.randn(20, 3, 3, generator=g, dtype=torch.float64),
              torch.eye(3, dtype=torch.float64).expand(2, 3, 3).clone(),
              torch.randn(6, 2, 2, generator=g, dtype=torch.float64)):
        assert torch.autograd.gradcheck(polar_rotations, (F.requires_grad_(True),))
