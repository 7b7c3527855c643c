"""Materials: ranges checked with clear errors, Lamé constants, per-element parameters."""
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.physics.materials import lame


@pytest.mark.parametrize("kwargs, match", [
    (dict(young=0.0, poisson=0.3), "young"),
    (dict(young=-1.0, poisson=0.3), "young"),
    (dict(young=float("nan"), poisson=0.3), "young"),
    (dict(young=1e3, poisson=0.5), "poisson"),
    (dict(young=1e3, poisson=-1.0), "poisson"),
    (dict(young=1e3, poisson=0.3, density=0.0), "density"),
    (dict(young=1e3, poisson=0.3, thickness=-0.1), "thickness"),
    (dict(young=1e3, poisson=0.3, model="neohookean"), "unknown material model 'neohookean'"),
    (dict(young=torch.tensor([1e3, -2.0]), poisson=0.3), "young"),
])
def test_bad_parameters(kwargs, match):
    with pytest.raises(tm.MaterialError, match=match):
        tm.Material(**kwargs)


def test_lame_constants():
    lam, mu = lame(torch.tensor(1e3, dtype=torch.float64), torch.tensor(0.25, dtype=torch.float64))
    assert abs(mu.item() - 400.0) < 1e-12 and abs(lam.item() - 400.0) < 1e-12
    lam_ps, mu_ps = lame(torch.tensor(1e3, dtype=torch.float64), torch.tensor(0.25, dtype=torch.float64), True)
    assert abs(lam_ps.item() - 1e3 * 0.25 / (1 - 0.0625)) < 1e-12 and mu_ps == mu


def test_per_element_parameters_must_match_the_mesh():
    mesh = tm.beam_mesh(1, 1, 1)
    mat = tm.Material(young=torch.full((5,), 1e3), poisson=0.3)
    with pytest.raises(tm.MaterialError, match=r"young has shape \(5,\); expected a scalar or \[6\]"):
        tm.TensorMass(mesh, mat)
    tm.TensorMass(mesh, tm.Material(young=torch.full((6,), 1e3), poisson=0.3))


def test_unknown_form():
    with pytest.raises(tm.MaterialError, match="form"):
        tm.TensorMass(tm.beam_mesh(1, 1, 1), tm.Material(1e3, 0.3), form="fast")


def test_model_checks_positions():
    mesh = tm.beam_mesh(1, 1, 1)
    model = tm.TensorMass(mesh, tm.Material(1e3, 0.3))
    with pytest.raises(tm.SceneError, match=r"expected \[8, 3\]"):
        model(mesh.vertices[:5])
    with pytest.raises(tm.SceneError, match="float64"):
        model(mesh.vertices.double())


def test_tensor_form_refuses_material_gradients():
    young = torch.tensor(1e3, dtype=torch.float64, requires_grad=True)
    mesh = tm.beam_mesh(1, 1, 1, dtype=torch.float64)
    with pytest.raises(tm.MaterialError, match="form='stress'"):
        tm.TensorMass(mesh, tm.Material(young, 0.3), form="tensor")
    tm.TensorMass(mesh, tm.Material(young, 0.3), form="stress")


def test_auto_form_is_stress_when_material_needs_gradients():
    mesh = tm.beam_mesh(1, 1, 1, dtype=torch.float64)
    assert tm.TensorMass(mesh, tm.Material(1e3, 0.3, model="hooke")).groups[0].form == "tensor"
    young = torch.tensor(1e3, dtype=torch.float64, requires_grad=True)
    assert tm.TensorMass(mesh, tm.Material(young, 0.3, model="hooke")).groups[0].form == "stress"
