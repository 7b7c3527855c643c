"""stvk with ``Material(tangent="definite")``: the geometric term of the force differential uses
S+ (the positive part of the second Piola-Kirchhoff stress), so the implicit system stays
positive definite under compression.

    1. S+ = the eigen-decomposition's positive part; the tangent = the exact one under tension,
       positive semi-definite under compression (where the exact one is not)
    2. forces and energy are those of stvk (forces = -grad energy; the force Jacobian stays exact)
    3. the extension (model id 3) = the reference, float64 and float32, every element kind
    4. a compressed beam: the exact tangent breaks CG down, the definite one runs; input checks
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import KINDS, build_scene, large_deformation, load_native, rel

import tensormass_torch as tm
from tensormass_torch import Material, MaterialError, TensorMass, ops
from tensormass_torch.ops.reference import stress_form

native = load_native("stress_dforces")


def group_of(scene, tangent, dtype=torch.float64, young=1e4):
    mat = Material(young=young, poisson=0.3, density=1000.0, model="stvk", tangent=tangent, thickness=0.1)
    (group,) = TensorMass(scene.mesh.to(dtype=dtype), mat, form="stress").groups
    return group


def quadratic_forms(group, u, trials, rng):
    """du . (-(dF/du) du) for random du: the tangent stiffness's quadratic form."""
    out = []
    for _ in range(trials):
        du = torch.tensor(rng.standard_normal(u.shape), dtype=u.dtype)
        out.append(float(-(du * ops.dforces(group, u, du)).sum()))
    return np.array(out)


def test_positive_part():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(50, 3, 3, generator=g, dtype=torch.float64)
    sym = a + a.transpose(1, 2)
    plus = stress_form.positive_part(sym)
    values = torch.linalg.eigvalsh(plus)
    assert float(values.min()) > -1e-12  # positive semi-definite
    torch.testing.assert_close(plus - stress_form.positive_part(-sym), sym)  # S = S+ - (-S)+


def test_positive_part_derivative_at_distinct_and_repeated_eigenvalues():
    """The derivative of S -> S+ (Daleckii-Krein) against central differences, for symmetric
    inputs with distinct eigenvalues, a repeated positive pair, and S = 0 (at rest: eigh's own
    backward divides by 0 there), where it is the derivative along every direction that keeps
    the eigenvalues' order, 1/2 of the identity map."""
    def of_symmetric(a):
        return stress_form.positive_part(a + a.transpose(-1, -2))

    g = torch.Generator().manual_seed(0)
    distinct = torch.randn(20, 3, 3, generator=g, dtype=torch.float64)
    repeated = torch.diag(torch.tensor([0.5, 0.5, -1.0], dtype=torch.float64)).expand(1, 3, 3).clone()
    for a in (distinct, repeated):
        assert torch.autograd.gradcheck(of_symmetric, (a.requires_grad_(True),))
    zero = torch.zeros(1, 3, 3, dtype=torch.float64, requires_grad=True)
    w = torch.randn(1, 3, 3, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad((w * stress_form.positive_part(zero)).sum(), zero)
    assert bool(torch.isfinite(grad).all())
    torch.testing.assert_close(grad, 0.5 * (w + w.transpose(-1, -2)) / 2)


@pytest.mark.parametrize("kind", KINDS)
def test_equals_exact_under_tension_and_is_semidefinite_under_compression(kind, monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    rng = np.random.default_rng(1)
    scene = build_scene(rng, kind)
    exact, definite = group_of(scene, "exact"), group_of(scene, "definite")
    du = torch.tensor(rng.standard_normal(scene.rest.shape))
    stretch = 0.2 * scene.rest  # u = 0.2 X: S positive definite, S+ = S
    assert rel(ops.dforces(definite, stretch, du), ops.dforces(exact, stretch, du)) < 1e-13
    squeeze = -0.5 * scene.rest  # strong compression: S negative definite
    assert quadratic_forms(exact, squeeze, 40, rng).min() < 0  # the exact tangent is indefinite here
    assert quadratic_forms(definite, squeeze, 40, rng).min() > -1e-12


@pytest.mark.parametrize("kind", KINDS)
def test_forces_energy_and_their_gradient_are_stvk(kind):
    rng = np.random.default_rng(2)
    scene = build_scene(rng, kind)
    x = large_deformation(rng, scene)
    mat = dict(young=2e4, poisson=0.3, density=1000.0, model="stvk", thickness=0.1)
    exact = TensorMass(scene.mesh, Material(**mat, tangent="exact"), form="stress")
    definite = TensorMass(scene.mesh, Material(**mat, tangent="definite"), form="stress")
    assert rel(definite(x), exact(x)) < 1e-14
    assert abs(float(definite.energy(x) - exact.energy(x))) <= 1e-12 * abs(float(exact.energy(x)))
    xg = x.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(definite.energy(xg), xg)
    assert rel(definite(x), -grad) < 1e-12
    # the Jacobian of the forces (what autograd differentiates) is the exact tangent, not the definite one
    v = torch.tensor(rng.standard_normal(x.shape))
    xg = x.clone().requires_grad_(True)
    (jv,) = torch.autograd.grad((definite(xg) * v).sum(), xg)
    assert rel(jv, exact.dforce(x, v)) < 1e-11


@pytest.mark.skipif(native is None, reason="tensormass_torch._C is not built")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_extension_matches_reference(kind, dtype, monkeypatch):
    rng = np.random.default_rng(3)
    scene = build_scene(rng, kind)
    group = group_of(scene, "definite", dtype)
    u = (-0.4 * scene.rest + 0.05 * torch.tensor(rng.standard_normal(scene.rest.shape))).to(dtype)
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    mass = torch.rand(u.shape[0], dtype=dtype) + 0.5
    tol = 1e-12 if dtype == torch.float64 else 2e-5

    def run():
        with torch.no_grad():
            return [ops.forces(group, u), ops.dforces(group, u, du), ops.element_dforces(group, u, du),
                    *ops.system_matvec([group], u, du, mass, None, 1.1, 0.01)]

    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext = run()
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    ref = run()
    for a, b in zip(ext, ref):
        assert rel(a, b) < tol


def compressed_beam(tangent):
    mesh = tm.beam_mesh(8, 2, 2, size=(1.0, 0.2, 0.2), dtype=torch.float64)
    mat = Material(young=1e5, poisson=0.3, density=1000.0, model="stvk", tangent=tangent)
    fixed = mesh.vertices[:, 0] < 1e-9
    end = mesh.vertices[:, 0] > 1 - 1e-9
    start = mesh.vertices[end].clone()
    motion = lambda t: start - torch.tensor([min(t, 0.2) / 0.2 * 0.7, 0.0, 0.0], dtype=torch.float64)  # noqa: E731
    return tm.Simulator([tm.Body(mesh, mat, fixed=fixed, prescribed=end, motion=motion)], dt=0.02,
                        gravity=(0, 0, 0), cg_tol=1e-6, cg_max_iter=2000)


def test_compressed_beam_runs_where_the_exact_tangent_breaks_down():
    exact = compressed_beam("exact")
    with pytest.raises(tm.SolverError, match="breakdown"):
        exact.step(12)
    definite = compressed_beam("definite")
    definite.step(12)  # pushed 70 % of its length in: no breakdown
    assert bool(torch.isfinite(definite.x).all())


def test_input_checks():
    with pytest.raises(MaterialError, match="stvk model only"):
        Material(young=1.0, poisson=0.3, model="hooke", tangent="definite")
    with pytest.raises(MaterialError, match="unknown tangent"):
        Material(young=1.0, poisson=0.3, model="stvk", tangent="projected")
    scene = build_scene(np.random.default_rng(4), "tet")
    with pytest.raises(MaterialError, match="stress form only"):
        TensorMass(scene.mesh, Material(young=1.0, poisson=0.3, model="stvk", tangent="definite"), form="tensor")


@pytest.mark.skipif(native is None or not torch.cuda.is_available(), reason="needs CUDA and the extension")
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_matches_cpu(kind, dtype):
    rng = np.random.default_rng(5)
    scene = build_scene(rng, kind)
    u = (-0.4 * scene.rest + 0.05 * torch.tensor(rng.standard_normal(scene.rest.shape))).to(dtype)
    du = torch.tensor(rng.standard_normal(u.shape), dtype=dtype)
    cpu_group = group_of(scene, "definite", dtype)
    gpu_group = group_of(scene, "definite", dtype).to("cuda")
    tol = 1e-12 if dtype == torch.float64 else 2e-5
    with torch.no_grad():
        for a, b in ((ops.dforces(cpu_group, u, du), ops.dforces(gpu_group, u.cuda(), du.cuda())),
                     (ops.forces(cpu_group, u), ops.forces(gpu_group, u.cuda()))):
            assert b.device.type == "cuda" and rel(b.cpu(), a) < tol
