"""The step's right-hand side pieces computed once per step: TensorMass.linearized_forces (one pass
for linear models), Planes.linearize, SystemMatvec.forces_along / tangent, against the separate
evaluations they replace (float64)."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.physics.contact import Planes
from tensormass_torch.solver.implicit_euler import DynamicsSystem


def _model(model, form="auto"):
    mesh = tm.beam_mesh(4, 2, 2, size=(0.4, 0.1, 0.1), dtype=torch.float64)
    return tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, model=model), form=form)


@pytest.mark.parametrize("model,form", [("hooke", "tensor"), ("hooke", "stress"), ("stvk", "stress"),
                                        ("stvk", "tensor"), ("corotational", "stress")])
def test_linearized_forces_equal_forces_plus_tangent(model, form):
    tm_model = _model(model, form)
    gen = torch.Generator().manual_seed(3)
    u = 0.02 * torch.randn(tm_model.rest.shape, generator=gen, dtype=torch.float64)
    w = 0.01 * torch.randn(tm_model.rest.shape, generator=gen, dtype=torch.float64)
    expected = tm_model.displacement_forces(u) + tm_model.displacement_tangent(u)(w)
    got = tm_model.linearized_forces(u, w)
    assert tm_model.is_linear == (model == "hooke")
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10 * float(expected.abs().max()))


def test_planes_linearize_matches_forces_and_stiffness():
    planes = Planes([tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4), tm.Plane((1.0, 1.0, 0.0), 0.1, 3e3)],
                    torch.float64, "cpu")
    x = torch.randn(50, 3, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 0.2
    forces, stiffness = planes.linearize(x)
    assert torch.equal(forces, planes.forces(x)) and torch.equal(stiffness, planes.node_stiffness(x))
    dx = torch.randn_like(x)
    torch.testing.assert_close(-torch.einsum("vab,vb->va", stiffness, dx), planes.dforces(x, dx))


@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_system_matvec_rhs_pieces(model):
    tm_model = _model(model)
    mass = tm_model.lumped_mass()
    external = mass.unsqueeze(-1) * torch.tensor([0.0, 0.0, -9.81], dtype=torch.float64)
    planes = Planes([tm.Plane((0.0, 0.0, 1.0), 0.02, 1e4)], torch.float64, "cpu")
    system = DynamicsSystem(tm_model, mass, external, Segments.from_lengths([tm_model.num_nodes], "cpu"),
                            torch.zeros(tm_model.num_nodes, dtype=torch.bool), planes)
    gen = torch.Generator().manual_seed(5)
    x = tm_model.rest + 0.03 * torch.randn(tm_model.rest.shape, generator=gen, dtype=torch.float64)
    w = torch.randn(x.shape, generator=gen, dtype=torch.float64)
    loaded = system.system_matvec(1.0, 1e-4).load(x)
    expected = system.forces(x) + system.dforces(x, w)
    torch.testing.assert_close(loaded.forces_along(w), expected, rtol=1e-9, atol=1e-9 * float(expected.abs().max()))
    torch.testing.assert_close(loaded.tangent(w), system.dforces(x, w), rtol=1e-10, atol=1e-6)
