"""The Cholesky preconditioner (solver.direct): the factor solves the rest matrix (dense float64),
a hooke step without contact takes one CG iteration and lands where plain CG's does, other
models and a floor take a few, objects of a batch converge each, CUDA equals the CPU, scene
files and bad input."""
import sys

import pytest
import torch
from conftest import beam_scene_file

import tensormass_torch as tm
from tensormass_torch.solver import direct, multigrid
from tensormass_torch.solver.implicit_euler import _coefficients

pytest.importorskip("cholespy")
DT = torch.float64


def beam_sim(model="hooke", preconditioner="cholesky", device="cpu", cells=(8, 2, 2), **options):
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] == 0)
    options = {"cg_tol": 1e-10, "cuda_graphs": False, **options}
    return tm.Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), preconditioner=preconditioner, device=device,
                        **options)


def test_the_factor_solves_the_rest_matrix():
    sim = beam_sim()
    system = sim.system
    mass_coef, stiffness_coef = _coefficients(sim.options)
    edges, blocks = sim.model.rest_stiffness_edges()
    matrix = multigrid.rest_system_matrix(edges, blocks, system.mass, mass_coef, stiffness_coef, system.free)
    factor = direct.RestCholesky(matrix, DT, "cpu")
    gen = torch.Generator().manual_seed(0)
    r = torch.randn(sim.x.shape, generator=gen, dtype=DT)
    expected = torch.linalg.solve(torch.from_numpy(matrix.toarray()), r.reshape(-1)).reshape(r.shape)
    torch.testing.assert_close(factor(r), expected, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("model,floor", [("hooke", False), ("hooke", True), ("corotational", True)])
def test_a_cholesky_step_is_the_plain_step(model, floor):
    """Hooke without contact: one iteration a step; a floor or a corotational tangent: a few."""
    planes = [tm.Plane((0, 0, 1), -0.005, 1e4)] if floor else []
    runs, iterations = [], []
    for preconditioner in ("none", "cholesky"):
        sim = beam_sim(model, preconditioner, planes=planes, rayleigh_mass=0.1)
        sim.step(10)
        runs.append(sim.x.clone())
        iterations.append(int(sim.last_report.cg[0].iterations.max()))
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)
    if model == "hooke" and not floor:
        assert iterations[1] == 1
    assert 3 * iterations[1] < iterations[0], iterations


def test_objects_of_a_batch_converge_each():
    meshes = [tm.beam_mesh(6, 2, 2, size=(1.0, 0.2, 0.2), dtype=DT), tm.beam_mesh(3, 2, 1, size=(0.5, 0.3, 0.1),
                                                                                   dtype=DT)]
    bodies = [tm.Body(m, tm.Material(young=e, poisson=0.3, density=1000.0), fixed=m.vertices[:, 0] == 0)
              for m, e in zip(meshes, (1e5, 1e7))]
    runs = []
    for preconditioner in ("none", "cholesky"):
        sim = tm.Simulator(bodies, dt=0.01, cg_tol=1e-10, cuda_graphs=False, preconditioner=preconditioner)
        sim.step(5)
        runs.append(sim.x.clone())
        assert sim.last_report.cg[0].converged.all()
    assert sim.last_report.cg[0].iterations.tolist() == [1, 1]
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_the_cpu():
    runs = []
    for device in ("cpu", "cuda"):
        sim = beam_sim("corotational", device=device, cuda_graphs=True, planes=[tm.Plane((0, 0, 1), -0.005, 1e4)])
        sim.step(10)
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)


def test_scene_file_and_bad_input(tmp_path, monkeypatch):
    path = beam_scene_file(tmp_path / "cholesky.toml", 'preconditioner = "cholesky"', cells=(4, 1, 1))
    scene = tm.load_scene(path)
    assert scene.simulator.options.preconditioner == "cholesky"
    scene.simulator.step(2)
    sim = beam_sim()
    x = sim.x.clone()
    monkeypatch.setitem(sys.modules, "cholespy", None)
    with pytest.raises(tm.SceneError, match="factorises with cholespy, which is not installed"):
        sim.step()
    assert torch.equal(sim.x, x) and sim.steps_done == 0
