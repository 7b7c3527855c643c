"""Gradients of the static equilibrium (``tm.solve_static``, by the implicit-function theorem)
against central differences of the solve in float64: the load (gravity, external forces) and the
material (per-element Young's modulus, Poisson ratio, density of a stress-form model)."""
import pytest
import torch

import tensormass_torch as tm
from tests.conftest import build_scene


def _setup(rng, model: str, plane: bool):
    scene = build_scene(rng, "tet")
    rest = scene.mesh.vertices
    fixed = rest[:, 0] < 0.1  # the jittered first layer of nodes
    N, V = scene.mesh.num_elements, rest.shape[0]
    values = {
        "young": 2e4 * (1 + 0.3 * torch.tensor(rng.uniform(size=N))),
        "poisson": 0.3 + 0.1 * torch.tensor(rng.uniform(size=N)),
        "density": 1000 * (1 + 0.3 * torch.tensor(rng.uniform(size=N))),
        "gravity": torch.tensor([0.5, 1.0, -9.81], dtype=torch.float64),
        "external": 0.1 * torch.tensor(rng.standard_normal((V, 3))),
    }
    planes = None
    if plane:  # just under the body, which gravity pushes into it
        from tensormass_torch.physics.contact import Planes

        floor = float(rest[:, 2].min()) - 0.002
        planes = Planes([tm.Plane((0, 0, 1), floor, 1e5)], torch.float64, "cpu")
    weights = torch.tensor(rng.standard_normal((V, 3)))

    def loss(**given):
        v = {**values, **given}
        material = tm.Material(young=v["young"], poisson=v["poisson"], density=v["density"], model=model)
        body = tm.TensorMass(scene.mesh, material, form="stress")
        u = tm.solve_static(body, fixed=fixed, gravity=v["gravity"], external=v["external"], tol=1e-13,
                            cg_tol=1e-14, planes=planes)
        return (weights * u).sum(), u

    if plane:
        return {**values, "rest_z": rest[:, 2], "floor": floor}, loss
    return values, loss


@pytest.mark.parametrize("model,plane", [("hooke", False), ("stvk", False), ("hooke", True), ("stvk", True)])
def test_static_gradients_match_finite_differences(rng, model, plane):
    values, loss = _setup(rng, model, plane)
    leaves = {name: value.clone().requires_grad_(True) for name, value in values.items()
              if name not in ("rest_z", "floor")}
    value, u = loss(**leaves)
    if plane:  # the plane holds some nodes: its stiffness is in the solve
        assert bool((u[:, 2] + values["rest_z"] < values["floor"]).any())
    values = {k: v for k, v in values.items() if k not in ("rest_z", "floor")}
    grads = dict(zip(leaves, torch.autograd.grad(value, list(leaves.values()))))
    for name, base in values.items():
        direction = torch.tensor(rng.standard_normal(tuple(base.shape)), dtype=torch.float64)
        eps = 1e-5 * float(base.abs().mean())
        with torch.no_grad():
            fd = (float(loss(**{name: base + eps * direction})[0]) - float(loss(**{name: base - eps * direction})[0])) \
                / (2 * eps)
        analytic = float((grads[name] * direction).sum())
        assert abs(analytic - fd) <= 1e-6 * abs(fd), (name, analytic, fd)


def test_a_static_solve_without_gradients_is_unchanged(rng):
    """Nothing requires grad: the plain solve, no autograd function."""
    values, loss = _setup(rng, "hooke", False)
    value, u = loss()
    assert u.grad_fn is None and not u.requires_grad


def test_what_the_static_gradient_does_not_cover_is_named(rng):
    """Corotational elements (their Jacobian through the rotations is not the solve's tangent):
    an error, not a wrong gradient."""
    scene = build_scene(rng, "tet")
    young = torch.tensor(2e4, dtype=torch.float64, requires_grad=True)
    model = tm.TensorMass(scene.mesh, tm.Material(young=young, poisson=0.3, model="corotational"), form="stress")
    with pytest.raises(tm.SolverError, match="corotational elements"):
        tm.solve_static(model, fixed=scene.mesh.vertices[:, 0] < 0.1)
    with torch.no_grad():  # no gradient asked: the solve itself is not refused
        tm.solve_static(model, fixed=scene.mesh.vertices[:, 0] < 0.1)
