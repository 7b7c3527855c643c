"""Physics of the element forces (docs/physics.md, sections 2 and 5), float64 on the CPU.

Parametrized over model (hooke, stvk) x form (stress, tensor) x element kind (tet, tri2d,
tri3d) where it applies, on small jittered meshes (see conftest.py) with random large
deformations and a fresh seed per parametrization.

    1. forces = -grad energy (autograd)
    2. dforce = Hessian-vector product (double backward); linear in dx; symmetric
    4. linear TM = P1 FEM stiffness assembled here, independently (B-matrix, Voigt D)
    5. rigid motions: translation (all), rotation (stvk), the ghost forces of hooke (measured)
    6. patch test: uniform strain reproduced exactly (interior forces, energy)
    7. energies: 1/2 u^T K u, StVK closed form, StVK -> Hooke for small displacements
    8. per-element material parameters
    9. lumped mass
   10. float32 path
   11. gradients to the material parameters (stress form)
(3., tensor form = stress form, is in physics/test_tensor_form.py.)
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from conftest import (
    FORMS,
    KINDS,
    MODELS,
    axis_rotation,
    element_measures,
    fem_stiffness,
    per_element,
    random_rotation,
    rel_err,
)

from tensormass_torch import Material, TensorMass, TetMesh, TriMesh

F64 = torch.float64
ALL = [pytest.param(m, f, k, id=f"{m}-{f}-{k}") for m in MODELS for f in FORMS for k in KINDS]
FORM_KIND = [pytest.param(f, k, id=f"{f}-{k}") for f in FORMS for k in KINDS]
MODEL_KIND = [pytest.param(m, k, id=f"{m}-{k}") for m in MODELS for k in KINDS]


def t64(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=F64)


def energy_grad(model, x):
    """Energy and its gradient (autograd) at x."""
    x = x.detach().clone().requires_grad_(True)
    e = model.energy(x)
    (g,) = torch.autograd.grad(e, x)
    return e.detach(), g


def hvp(model, x, dx):
    """Hessian of the energy times dx, by double backward."""
    x = x.detach().clone().requires_grad_(True)
    (g,) = torch.autograd.grad(model.energy(x), x, create_graph=True)
    (h,) = torch.autograd.grad(g, x, grad_outputs=dx)
    return h


def dforce_matrix(model, x) -> np.ndarray:
    """The matrix of dx -> model.dforce(x, dx), column by column (unit vectors e_k)."""
    V, d = x.shape
    cols = []
    for k in range(V * d):
        e = torch.zeros(V * d, dtype=x.dtype)
        e[k] = 1.0
        cols.append(model.dforce(x, e.view(V, d)).reshape(-1))
    return torch.stack(cols, dim=1).numpy()


def lame_of(kind, young, poisson):
    mu = young / (2 * (1 + poisson))
    if kind == "tet":
        lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    else:
        lam = young * poisson / (1 - poisson ** 2)
    return lam, mu


def energy_density(strain, lam, mu):
    return 0.5 * lam * np.trace(strain) ** 2 + mu * np.sum(strain * strain)


def total_measure(scene, mat):
    return element_measures(scene, mat.thickness if scene.kind != "tet" else 1.0).sum()


# ---------------------------------------------------------------------------------------------
# 1, 2. Forces and differentials against autograd of the energy
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_forces_are_minus_energy_gradient(model_name, form, kind, make_scene, make_material, deform):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    for x in (deform(scene), deform(scene, amplitude=(0.25, 0.3)), deform(scene, rotate=False)):
        _, grad = energy_grad(model, x)
        f = model(x)
        assert f.shape == x.shape and f.dtype == F64
        assert rel_err(f, -grad) < 1e-10


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_dforce_is_energy_hessian_vector_product(model_name, form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    x = deform(scene)
    for _ in range(2):
        dx = t64(rng.standard_normal(x.shape))
        df = model.dforce(x, dx)
        assert df.shape == x.shape
        assert rel_err(df, -hvp(model, x, dx)) < 1e-10


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_dforce_linear_and_symmetric(model_name, form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    x = deform(scene)
    a, b = (t64(rng.standard_normal(x.shape)) for _ in range(2))
    alpha, beta = rng.uniform(-3, 3, 2)
    ka, kb = model.dforce(x, a), model.dforce(x, b)
    assert rel_err(model.dforce(x, alpha * a + beta * b), alpha * ka + beta * kb) < 1e-12
    assert float(model.dforce(x, torch.zeros_like(x)).abs().max()) == 0.0  # zero in, zero out
    # a . K b == b . K a: the stiffness of a hyperelastic model is symmetric.
    ab, ba = float((a * kb).sum()), float((b * ka).sum())
    scale = float(torch.linalg.norm(a) * torch.linalg.norm(kb))
    assert abs(ab - ba) < 1e-12 * scale
    # and dforce is the derivative of the forces (finite differences, central, O(h^2)).
    h = 1e-6 * scene.size
    fd = (model(x + h * a) - model(x - h * a)) / (2 * h)
    assert rel_err(fd, ka) < 1e-6


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_momentum_conservation(model_name, form, kind, make_scene, make_material, deform):
    """Internal forces sum to zero (translation invariance); for stvk their torque sums to zero
    too (rotation invariance), about any point."""
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    x = deform(scene)
    f = model(x)
    scale = float(f.abs().sum())
    assert float(f.sum(0).abs().max()) < 1e-12 * scale
    if model_name == "stvk":
        arm = (x - x.mean(0)).numpy()
        if scene.dim == 2:
            torque = np.sum(arm[:, 0] * f[:, 1].numpy() - arm[:, 1] * f[:, 0].numpy())
        else:
            torque = np.cross(arm, f.numpy()).sum(0)
        assert np.abs(torque).max() < 1e-12 * scale * scene.size


# ---------------------------------------------------------------------------------------------
# 4. Linear Tensor-Mass = assembled P1 FEM stiffness
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_hooke_is_p1_fem_stiffness(form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    mat = make_material("hooke")
    model = TensorMass(scene.mesh, mat, form=form)
    K = fem_stiffness(scene, mat.young, mat.poisson, mat.thickness)
    assert np.abs(K - K.T).max() < 1e-12 * np.abs(K).max()
    # dforce columns are -K, and do not depend on x (linear model).
    for x in (scene.rest, deform(scene), deform(scene, amplitude=(0.3, 0.3))):
        kx = dforce_matrix(model, x)
        assert rel_err(kx, -K) < 1e-12
    # forces are -K u for any (large) displacement.
    x = deform(scene)
    u = (x - scene.rest).numpy().reshape(-1)
    assert rel_err(model(x).reshape(-1), -K @ u) < 1e-12


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_stvk_tangent_at_rest_is_p1_fem_stiffness(form, kind, make_scene, make_material):
    """The St Venant-Kirchhoff model linearised at the rest shape is linear elasticity."""
    scene = make_scene(kind)
    mat = make_material("stvk")
    model = TensorMass(scene.mesh, mat, form=form)
    K = fem_stiffness(scene, mat.young, mat.poisson, mat.thickness)
    assert rel_err(dforce_matrix(model, scene.rest), -K) < 1e-12


# ---------------------------------------------------------------------------------------------
# 5. Rigid motions
# ---------------------------------------------------------------------------------------------


def force_scale(model, scene, deform):
    """Norm of the forces at a generic deformation of comparable size (the yardstick of 'zero')."""
    return float(torch.linalg.norm(model(deform(scene, rotate=False))))


def rigid_tol(form):
    """Relative tolerance of 'zero' under rigid motions of about the object's size.

    The stress form works on grad U = sum u_j (x) m_j, where a rigid motion cancels element by
    element: float64 rounding (~1e-15). The tensor form is a polynomial in the absolute nodal
    displacements (degree 2 for hooke, 4 for stvk): a rigid motion of amplitude |t| cancels only
    in the sums, with rounding that grows like (|t| / h)^k (h the element size); ~1e-11 here.
    """
    return 1e-12 if form == "stress" else 1e-10


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_zero_force_under_rigid_translation(model_name, form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    scale = force_scale(model, scene, deform)
    e_scale = float(model.energy(deform(scene, rotate=False)))
    tol = rigid_tol(form)
    for t in (rng.uniform(-0.1, 0.1, scene.dim), rng.uniform(-2, 2, scene.dim)):
        x = scene.rest + t64(t * scene.size)
        assert float(torch.linalg.norm(model(x))) < tol * scale
        assert abs(float(model.energy(x))) < tol * e_scale
    # translating a deformed state changes nothing
    t = t64(rng.uniform(-2, 2, scene.dim) * scene.size)
    y = deform(scene)
    assert rel_err(model(y + t), model(y)) < tol
    dx = t64(rng.standard_normal(y.shape))
    assert rel_err(model.dforce(y + t, dx), model.dforce(y, dx)) < tol


def _rotations(rng, dim):
    if dim == 2:
        angles = [math.pi / 2, math.pi, -math.pi / 2, float(rng.uniform(-math.pi, math.pi))]
        return [axis_rotation(None, a) for a in angles]
    axes = [(1, 0, 0), (0, 1, 0), (0, 0, 1), rng.standard_normal(3)]
    rots = [axis_rotation(a, ang) for a in axes for ang in (math.pi / 2, math.pi)]
    return rots + [random_rotation(rng, 3) for _ in range(2)]


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_stvk_zero_force_under_rigid_rotation(form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material("stvk"), form=form)
    scale = force_scale(model, scene, deform)
    e_scale = float(model.energy(deform(scene, rotate=False)))
    c = scene.rest.mean(0)
    for R in _rotations(rng, scene.dim):  # about the centroid, plus a shift: |u| <~ 2 x size
        x = (scene.rest - c) @ t64(R).T + c + t64(rng.uniform(-0.5, 0.5, scene.dim) * scene.size)
        assert float(torch.linalg.norm(model(x))) < rigid_tol(form) * scale
        assert abs(float(model.energy(x))) < rigid_tol(form) * e_scale


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_stvk_is_objective(form, kind, rng, make_scene, make_material, deform):
    """Rotating a deformed state rotates its forces and differentials: f(Rx+t) = R f(x)."""
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material("stvk"), form=form)
    x = deform(scene)
    dx = t64(rng.standard_normal(x.shape))
    f, df, e = model(x), model.dforce(x, dx), model.energy(x)
    c = x.mean(0)
    for R in _rotations(rng, scene.dim)[-3:]:
        R = t64(R)
        y = (x - c) @ R.T + c + t64(rng.uniform(-0.5, 0.5, scene.dim) * scene.size)
        assert rel_err(model(y), f @ R.T) < 10 * rigid_tol(form)
        assert rel_err(model.dforce(y, dx @ R.T), df @ R.T) < 10 * rigid_tol(form)
        assert rel_err(model.energy(y), e) < 10 * rigid_tol(form)


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_hooke_ghost_forces_under_rotation(form, kind, rng, make_scene, make_material, deform):
    """Linear elasticity is not rotation invariant: a rigid rotation creates forces ("ghost forces").

    This is the known defect of the linear strain eps = sym(grad U), which is why corotational
    models exist: they factor a per-element rotation R out (f = -R K (R^T x - X)) so that the linear
    law only ever sees the deformation. Measured here, exactly: a rotation by theta about a unit
    axis a is R = I + sin(theta) W + (1 - cos(theta)) W^2 (W = [a]_x, skew), so u = (R - I) X and,
    the forces being linear in u,

        f(theta) = sin(theta) f(W X) + (1 - cos(theta)) f(W^2 X),

    where f(W X) = 0 (an infinitesimal rotation has sym(W) = 0: no strain) while
    W^2 = a a^T - I is a uniform contraction across the axis. So the ghost forces are those of the
    uniform strain -(1 - cos(theta)) (I - a a^T): |f(theta)| / (1 - cos(theta)) is constant and
    nonzero, |f| grows like theta^2 / 2 for small angles (|f| / theta -> 0 linearly, i.e. NOT like
    theta), and the worst case is the half turn, which the linear law reads as a uniform strain
    of -200% across the axis.
    (In 2-D, a is the out-of-plane axis and I - a a^T the in-plane identity.)
    """
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material("hooke"), form=form)
    scale = force_scale(model, scene, deform)
    d = scene.dim
    axis = None if d == 2 else rng.standard_normal(3)
    W = np.array([[0.0, -1.0], [1.0, 0.0]])  # 2-D: the generator of rotations about the origin
    if d == 3:
        a = axis / np.linalg.norm(axis)
        W = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    center = t64(rng.uniform(-1, 1, d))
    X = scene.rest - center
    f_inf = model(X @ t64(W).T + scene.rest)  # infinitesimal rotation: no force
    assert float(torch.linalg.norm(f_inf)) < 1e-12 * scale
    f_unit = model(X @ t64(W @ W).T + scene.rest)  # = f(theta) / (1 - cos theta)
    assert float(torch.linalg.norm(f_unit)) > 0.05 * scale  # ghost forces are real and large

    thetas = [1e-3, 1e-2, 1e-1, 0.5, math.pi / 2, math.pi]
    norms = []
    for theta in thetas:
        R = t64(axis_rotation(axis, theta))
        f = model(X @ R.T + center)
        one_minus_cos = 2.0 * math.sin(theta / 2) ** 2
        assert rel_err(f, one_minus_cos * f_unit) < 1e-8
        norms.append(float(torch.linalg.norm(f)))
    norms = np.array(norms)
    per_angle = norms / np.array(thetas)
    # |f| / theta is not constant: it vanishes linearly at small angles (|f| ~ c theta^2 / 2) ...
    assert per_angle[0] / per_angle[1] == pytest.approx(0.1, rel=1e-3)
    assert per_angle[1] / per_angle[2] == pytest.approx(0.1, rel=1e-2)
    # ... while |f| / theta^2 tends to a nonzero constant, |f_unit| / 2.
    per_angle2 = norms / np.array(thetas) ** 2
    assert per_angle2[0] == pytest.approx(0.5 * float(torch.linalg.norm(f_unit)), rel=1e-6)
    assert norms[-1] == pytest.approx(norms.max()) and norms[-1] == pytest.approx(2 * norms[-2], rel=1e-10)


# ---------------------------------------------------------------------------------------------
# 6. Patch test
# ---------------------------------------------------------------------------------------------


def patch_scene(make_scene, kind):
    if kind == "tet":
        return make_scene("tet", cells=(3, 3, 3), size=(1.0, 0.9, 0.8), jitter=0.15)
    return make_scene(kind, cells=(4, 4), jitter=0.15, flat=True)


def uniform_strain(scene, A, model_name):
    """Strain of the affine map x = X + A X: in the element plane for membranes ([2, 2])."""
    A = np.asarray(A)
    strain = 0.5 * (A + A.T) + (0.5 * A.T @ A if model_name == "stvk" else 0.0)
    if scene.frame is not None:
        strain = scene.frame.T @ strain @ scene.frame
    return strain


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_patch_test_uniform_strain(model_name, form, kind, rng, make_scene, make_material):
    scene = patch_scene(make_scene, kind)
    mat = make_material(model_name)
    model = TensorMass(scene.mesh, mat, form=form)
    d = scene.dim
    amp = 0.01 if model_name == "hooke" else 0.3
    A = rng.uniform(-amp, amp, (d, d))
    c = scene.rest.mean(0).numpy() + rng.uniform(-0.2, 0.2, d) * scene.size  # any fixed point
    x = scene.rest + (scene.rest - t64(c)) @ t64(A).T
    f = model(x)
    interior = scene.interior
    assert interior.sum() >= 4 and (~interior).sum() > 0
    f_int = torch.linalg.norm(f[interior], dim=1).max()
    f_bnd = torch.linalg.norm(f[~interior], dim=1).max()
    assert float(f_int) < 1e-9 * float(f_bnd)
    lam, mu = lame_of(kind, mat.young, mat.poisson)
    expected = total_measure(scene, mat) * energy_density(uniform_strain(scene, A, model_name), lam, mu)
    # (the tensor form, a polynomial in absolute displacements, rounds a little worse: rigid_tol)
    assert float(model.energy(x)) == pytest.approx(expected, rel=1e-12 if form == "stress" else 1e-11)


# ---------------------------------------------------------------------------------------------
# 7. Energies
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_hooke_energy_is_half_uKu(form, kind, make_scene, make_material, deform):
    scene = make_scene(kind)
    mat = make_material("hooke")
    model = TensorMass(scene.mesh, mat, form=form)
    K = fem_stiffness(scene, mat.young, mat.poisson, mat.thickness)
    for x in (deform(scene), deform(scene, rotate=False)):
        u = (x - scene.rest).numpy().reshape(-1)
        assert float(model.energy(x)) == pytest.approx(0.5 * u @ K @ u, rel=1e-12)
    assert float(model.energy(scene.rest)) == 0.0


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_stvk_energy_of_uniform_stretch(form, kind, rng, make_scene, make_material):
    """x = X + Q diag(s - 1) Q^T X: Green strain diag((s_i^2 - 1) / 2) in the frame Q, so
    W = V (lam/2 (sum e_i)^2 + mu sum e_i^2), lam plane-stress for triangles."""
    scene = make_scene(kind, flat=True)
    mat = make_material("stvk")
    model = TensorMass(scene.mesh, mat, form=form)
    k = 3 if kind == "tet" else 2
    Q = random_rotation(rng, 3) if kind == "tet" else (scene.frame if kind == "tri3d" else np.eye(2))
    for s in (rng.uniform(0.7, 1.4, k), np.full(k, 1.25), np.array([1.5] + [1.0] * (k - 1))):
        A = Q @ np.diag(s - 1.0) @ Q.T
        x = scene.rest + scene.rest @ t64(A).T
        e = 0.5 * (s ** 2 - 1.0)
        lam, mu = lame_of(kind, mat.young, mat.poisson)
        w = 0.5 * lam * e.sum() ** 2 + mu * (e ** 2).sum()
        assert float(model.energy(x)) == pytest.approx(total_measure(scene, mat) * w, rel=1e-12)


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_stvk_tends_to_hooke_for_small_displacements(form, kind, rng, make_scene, make_material):
    """|f_stvk - f_hooke| / |f_hooke| = O(|u|): the Green strain differs from the linear one by
    1/2 grad U^T grad U."""
    scene = make_scene(kind)
    mat = make_material("stvk")
    stvk = TensorMass(scene.mesh, mat, form=form)
    hooke = TensorMass(scene.mesh, Material(mat.young, mat.poisson, mat.density, "hooke", mat.thickness), form=form)
    direction = t64(rng.uniform(-1, 1, scene.rest.shape)) * scene.size
    ratios, energy_ratios = [], []
    for eps in (1e-3, 1e-4, 1e-5):
        x = scene.rest + eps * direction
        ratios.append(rel_err(stvk(x), hooke(x)) / eps)
        energy_ratios.append(abs(float(stvk.energy(x)) / float(hooke.energy(x)) - 1.0) / eps)
    ratios, energy_ratios = np.array(ratios), np.array(energy_ratios)
    assert ratios.max() < 100.0 and ratios.min() > 1e-2  # O(eps), with a nonzero constant
    assert ratios[2] == pytest.approx(ratios[1], rel=0.01)  # the constant has converged
    # the energy's first correction (the cubic term) may be small: it is O(eps), converging
    assert energy_ratios.max() < 100.0
    assert abs(energy_ratios[2] - energy_ratios[1]) < 0.05 * max(energy_ratios[1], 1.0)


# ---------------------------------------------------------------------------------------------
# 8. Per-element material parameters
# ---------------------------------------------------------------------------------------------


def sub_mesh(scene, mask):
    cls = TetMesh if scene.kind == "tet" else TriMesh
    return cls(scene.rest, scene.elements[mask])


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_per_element_materials_are_sums_of_parts(model_name, form, kind, rng, make_scene, deform):
    scene = make_scene(kind)
    n = scene.elements.shape[0]
    centroid = scene.rest[scene.elements].mean(1)[:, 0]
    left = centroid < centroid.median()
    young = torch.where(left, torch.tensor(3e3, dtype=F64), torch.tensor(8e4, dtype=F64))
    poisson = t64(rng.uniform(0.05, 0.45, n))
    thickness = t64(rng.uniform(0.02, 0.2, n))
    density = t64(rng.uniform(500, 2000, n))
    whole = TensorMass(scene.mesh, Material(young, poisson, density, model_name, thickness), form=form)
    parts = [TensorMass(sub_mesh(scene, mask), Material(young[mask], poisson[mask], density[mask], model_name,
                                                         thickness[mask]), form=form) for mask in (left, ~left)]
    x = deform(scene)
    dx = t64(rng.standard_normal(x.shape))
    assert rel_err(whole(x), parts[0](x) + parts[1](x)) < 1e-13
    assert rel_err(whole.energy(x), parts[0].energy(x) + parts[1].energy(x)) < 1e-13
    assert rel_err(whole.dforce(x, dx), parts[0].dforce(x, dx) + parts[1].dforce(x, dx)) < 1e-13
    assert rel_err(whole.lumped_mass(), parts[0].lumped_mass() + parts[1].lumped_mass()) < 1e-14
    # the halves really differ: scaling one half's young changes the result
    assert rel_err(parts[0](x), parts[1](x)) > 0.1
    if model_name == "hooke":  # and the heterogeneous stiffness is the FEM one
        K = fem_stiffness(scene, young, poisson, thickness)
        assert rel_err(dforce_matrix(whole, x), -K) < 1e-12


@pytest.mark.parametrize("form", FORMS)
@pytest.mark.parametrize("kind", KINDS)
def test_packed_mixed_models_are_sums_of_parts(kind, form, rng, make_scene, make_material, deform):
    """One packed model over the same nodes with a hooke half and a stvk half (two groups)."""
    scene = make_scene(kind)
    centroid = scene.rest[scene.elements].mean(1)[:, 0]
    left = centroid < centroid.median()
    mats = (make_material("hooke"), make_material("stvk"))
    halves = (scene.elements[left], scene.elements[~left])
    packed = TensorMass.packed(scene.rest, [(e, m, scene.mesh.kind) for e, m in zip(halves, mats)], form=form)
    assert len(packed.groups) == 2
    cls = TetMesh if kind == "tet" else TriMesh
    parts = [TensorMass(cls(scene.rest, e), m, form=form) for e, m in zip(halves, mats)]
    x = deform(scene)
    dx = t64(rng.standard_normal(x.shape))
    assert rel_err(packed(x), parts[0](x) + parts[1](x)) < 1e-13
    assert rel_err(packed.energy(x), parts[0].energy(x) + parts[1].energy(x)) < 1e-13
    assert rel_err(packed.dforce(x, dx), parts[0].dforce(x, dx) + parts[1].dforce(x, dx)) < 1e-13
    assert rel_err(packed.lumped_mass(), parts[0].lumped_mass() + parts[1].lumped_mass()) < 1e-14


# ---------------------------------------------------------------------------------------------
# 9. Lumped mass
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("form,kind", FORM_KIND)
def test_lumped_mass(form, kind, rng, make_scene, make_material):
    scene = make_scene(kind)
    n_elem, n = scene.elements.shape
    for density in (float(rng.uniform(500, 2000)), t64(rng.uniform(500, 2000, n_elem))):
        mat = make_material("hooke", density=density)
        model = TensorMass(scene.mesh, mat, form=form)
        mass = model.lumped_mass()
        assert mass.shape == (scene.rest.shape[0],) and mass.dtype == F64
        measures = element_measures(scene, mat.thickness if kind != "tet" else 1.0)
        rho = per_element(density, n_elem)
        expected = np.zeros(scene.rest.shape[0])
        np.add.at(expected, scene.elements.numpy().reshape(-1), np.repeat(rho * measures / n, n))
        assert rel_err(mass, expected) < 1e-14
        assert float(mass.sum()) == pytest.approx(float((rho * measures).sum()), rel=1e-14)
        if not isinstance(density, torch.Tensor):
            assert float(mass.sum()) == pytest.approx(density * measures.sum(), rel=1e-14)


# ---------------------------------------------------------------------------------------------
# 10. float32
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_float32_matches_float64(model_name, form, kind, rng, make_scene, make_material, deform):
    """float32 agrees with float64 to ~1e-5 (relative, norm-wise) at large deformations.

    With a rigid motion on top (here a rotation and a shift of up to half the size), the stvk
    tensor form loses one to two more digits (errors up to ~2e-4 seen): it is a quartic
    polynomial in the absolute displacements, whose rounding grows like (|u| / h)^3 (see
    physics/test_tensor_form.py::test_stvk_tensor_form_rounding_under_rigid_motion).
    """
    scene = make_scene(kind)
    mat = make_material(model_name)
    m64 = TensorMass(scene.mesh, mat, form=form)
    m32 = TensorMass(scene.mesh.to(dtype=torch.float32), mat, form=form)
    for rotate in (False, True):
        tol = 5e-4 if (rotate and form == "tensor" and model_name == "stvk") else 1e-5
        x = deform(scene, rotate=rotate)
        dx = t64(rng.standard_normal(x.shape))
        f32, e32, df32 = m32(x.float()), m32.energy(x.float()), m32.dforce(x.float(), dx.float())
        assert f32.dtype == e32.dtype == df32.dtype == m32.lumped_mass().dtype == torch.float32
        assert rel_err(f32, m64(x)) < tol
        assert rel_err(e32, m64.energy(x)) < tol
        assert rel_err(df32, m64.dforce(x, dx)) < tol
    assert rel_err(m32.lumped_mass(), m64.lumped_mass()) < 1e-6
    # the module follows .to(): a float64 model cast to float32 computes like one built in float32
    cast = TensorMass(scene.mesh, mat, form=form).to(torch.float32)
    x = deform(scene, rotate=False)
    assert rel_err(cast(x.float()), m64(x)) < 1e-5
    assert cast.lumped_mass().dtype == torch.float32


# ---------------------------------------------------------------------------------------------
# 11. Gradients to material parameters (stress form)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_name,kind", MODEL_KIND)
def test_material_gradients_stress_form(model_name, kind, rng, make_scene, deform):
    scene = make_scene(kind, cells=(1, 1, 1) if kind == "tet" else (1, 2))
    n = scene.elements.shape[0]
    x = deform(scene)
    thickness = 0.1

    def energy(young, poisson):
        mat = Material(young=young, poisson=poisson, density=1.0, model=model_name, thickness=thickness)
        return TensorMass(scene.mesh, mat, form="stress").energy(x)

    def forces(young, poisson):
        mat = Material(young=young, poisson=poisson, density=1.0, model=model_name, thickness=thickness)
        return TensorMass(scene.mesh, mat, form="stress")(x)

    # scalar and per-element parameters, well scaled for finite differences (energy ~ young)
    young_s = torch.tensor(float(rng.uniform(1, 3)), dtype=F64, requires_grad=True)
    poisson_s = torch.tensor(float(rng.uniform(0.1, 0.4)), dtype=F64, requires_grad=True)
    assert torch.autograd.gradcheck(energy, (young_s, poisson_s))
    young_e = t64(rng.uniform(1, 3, n)).requires_grad_(True)
    poisson_e = t64(rng.uniform(0.1, 0.4, n)).requires_grad_(True)
    assert torch.autograd.gradcheck(energy, (young_e, poisson_e))
    assert torch.autograd.gradcheck(forces, (young_e, poisson_e))
    # the energy is linear in young at fixed poisson: dW/dE = W / E
    (g,) = torch.autograd.grad(energy(young_s, poisson_s.detach()), young_s)
    expected = float(energy(young_s.detach(), poisson_s.detach())) / float(young_s.detach())
    assert float(g) == pytest.approx(expected, rel=1e-12)
