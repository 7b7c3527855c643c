"""Corotational elasticity: the reference element math, and the model on the pure-torch path (issue 4)."""
import math

import pytest
import torch

from tensormass_torch.mesh import geometry
from tensormass_torch.ops.reference import corotational as co
from tensormass_torch.ops.reference import stress_form as sf

DT = torch.float64


def elements(seed, n=6):
    gen = torch.Generator().manual_seed(seed)
    rest = torch.randn(n, 4, 3, generator=gen, dtype=DT)
    m, vol = geometry.shape_vectors(rest)
    lam = torch.rand(n, generator=gen, dtype=DT) + 0.5
    mu = torch.rand(n, generator=gen, dtype=DT) + 0.5
    return rest, m, vol.abs(), lam, mu, gen


def rotation(axis, angle):
    axis = torch.as_tensor(axis, dtype=DT)
    axis = axis / axis.norm()
    k = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], dtype=DT)
    return torch.eye(3, dtype=DT) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


@pytest.mark.parametrize("angle", [0.3, math.pi / 2, math.pi, -2.5])
def test_zero_force_under_rigid_motion(angle):
    rest, m, vol, lam, mu, _ = elements(1)
    q = rotation((1.0, -2.0, 0.5), angle)
    u = rest @ q.T + torch.tensor([3.0, -1.0, 2.0], dtype=DT) - rest
    for rotations in (co.polar_rotations(co.deformation_gradient(u, m)), co.qr_rotations(rest + u, rest)):
        torch.testing.assert_close(rotations, q.expand_as(rotations), rtol=0, atol=1e-12)
        f = co.forces(u, m, vol, lam, mu, rotations)
        assert f.abs().max() < 1e-12


def test_equals_hooke_for_small_displacements():
    rest, m, vol, lam, mu, gen = elements(2)
    for scale in (1e-4, 1e-6):
        u = scale * torch.randn(rest.shape, generator=gen, dtype=DT)
        rotations = co.polar_rotations(co.deformation_gradient(u, m))
        f = co.forces(u, m, vol, lam, mu, rotations)
        ref = sf.hooke_forces(u, m, vol, lam, mu)
        assert (f - ref).norm() / ref.norm() < 10 * scale  # the difference is second order


def test_forces_and_dforces_are_derivatives_with_rotations_fixed():
    rest, m, vol, lam, mu, gen = elements(3)
    u = 0.4 * torch.randn(rest.shape, generator=gen, dtype=DT)
    rotations = co.polar_rotations(co.deformation_gradient(u, m))
    x = u.clone().requires_grad_()
    (grad,) = torch.autograd.grad(co.energy(x, m, vol, lam, mu, rotations).sum(), x)
    torch.testing.assert_close(co.forces(u, m, vol, lam, mu, rotations), -grad, rtol=1e-12, atol=1e-12)
    du = torch.randn(rest.shape, generator=gen, dtype=DT)
    jvp = torch.autograd.functional.jvp(lambda v: co.forces(v, m, vol, lam, mu, rotations), u, du)[1]
    torch.testing.assert_close(co.dforces(du, m, vol, lam, mu, rotations), jvp, rtol=1e-12, atol=1e-12)


def test_inverted_element_gets_a_proper_rotation():
    rest, m, _, _, _, _ = elements(4, n=1)
    mirror = torch.diag(torch.tensor([1.0, 1.0, -1.0], dtype=DT))
    u = rest @ mirror.T - rest  # reflected: det F < 0
    rotations = co.polar_rotations(co.deformation_gradient(u, m))
    assert torch.linalg.det(rotations).item() == pytest.approx(1.0, abs=1e-12)
    torch.testing.assert_close(rotations @ rotations.transpose(1, 2), torch.eye(3, dtype=DT)[None], atol=1e-12, rtol=0)


# ------------------------------------------------------------------ the model (reference path)

import tensormass_torch as tm  # noqa: E402


def _meshes():
    tet = tm.beam_mesh(3, 1, 1, size=(0.3, 0.1, 0.1), dtype=DT)
    tri = tm.beam_tri_mesh(3, 2, size=(0.3, 0.1), dim=3, dtype=DT)
    return {"tet": tet, "tri3d": tri}


@pytest.mark.parametrize("kind", ["tet", "tri3d"])
@pytest.mark.parametrize("rotation", ["polar", "qr"])
def test_model_rigid_motion_and_energy_gradient(kind, rotation):
    mesh = _meshes()[kind]
    model = tm.TensorMass(mesh, tm.Material(1e4, 0.3, 1000.0, "corotational", rotation=rotation, thickness=0.01))
    assert model.groups[0].model == "corotational" and model.groups[0].form == "stress"
    q = rotation_of(math.pi)
    x = mesh.vertices @ q.T + torch.tensor([0.5, -1.0, 2.0], dtype=DT)
    assert model(x).abs().max() < 1e-10 * 1e4
    gen = torch.Generator().manual_seed(7)
    x = (mesh.vertices @ rotation_of(0.7).T + 0.01 * torch.randn(mesh.vertices.shape, generator=gen, dtype=DT))
    x.requires_grad_(True)
    (grad,) = torch.autograd.grad(model.energy(x), x, create_graph=True)
    torch.testing.assert_close(model(x.detach()), -grad.detach(), rtol=1e-10, atol=1e-10)
    dx = torch.randn(x.shape, generator=gen, dtype=DT)
    (hvp,) = torch.autograd.grad((grad * dx).sum(), x)  # rotations held fixed in the energy
    torch.testing.assert_close(model.dforce(x.detach(), dx), -hvp, rtol=1e-10, atol=1e-10)


def rotation_of(angle):
    return rotation((0.3, 1.0, -0.4), angle)


def test_model_equals_hooke_for_small_displacements_and_runs_in_a_simulator():
    mesh = _meshes()["tet"]
    coro = tm.TensorMass(mesh, tm.Material(1e4, 0.3, model="corotational"))
    hooke = tm.TensorMass(mesh, tm.Material(1e4, 0.3, model="hooke"))
    gen = torch.Generator().manual_seed(8)
    x = mesh.vertices + 1e-6 * torch.randn(mesh.vertices.shape, generator=gen, dtype=DT)
    assert (coro(x) - hooke(x)).norm() / hooke(x).norm() < 1e-4
    fixed = mesh.vertices[:, 0] < 1e-9
    body = tm.Body(mesh, tm.Material(1e4, 0.3, 1000.0, "corotational"), fixed=fixed)
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-10, cg_max_iter=500)
    sim.step(3)
    assert sim.positions(0)[:, 2].min() < mesh.vertices[:, 2].min()  # it sags
    assert torch.all(sim.positions(0)[fixed] == mesh.vertices[fixed])


def test_corotational_options_are_checked():
    with pytest.raises(tm.MaterialError, match="rotation"):
        tm.Material(1e4, 0.3, model="corotational", rotation="svd")
    with pytest.raises(tm.MaterialError, match="stress form only"):
        tm.TensorMass(_meshes()["tet"], tm.Material(1e4, 0.3, model="corotational"), form="tensor")
    with pytest.raises(tm.MaterialError, match="3-D elements"):
        tm.TensorMass(tm.beam_tri_mesh(2, 2, dtype=DT), tm.Material(1e4, 0.3, model="corotational", rotation="qr"))
