"""Warm starts (StepOptions.warm_start): each step's CG from the extrapolation of the solutions of
the steps before (the projection on them: test_guess.py). The steps are converged steps (the same trajectory to the tolerance) in fewer
iterations, plain and preconditioned; the guess is 2 dv_1 - dv_2, and nothing after a state set
by hand or sub-steps; the scene key and bad input."""
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.sim import simulator as simulator_module

DT = torch.float64


def beam_sim(warm_start, preconditioner="none", model="hooke", cells=(12, 3, 3), **options):
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] == 0)
    options = {"cg_tol": 1e-10, "cuda_graphs": False, **options}
    return tm.Simulator([body], dt=0.01, preconditioner=preconditioner, warm_start=warm_start, **options)


@pytest.mark.parametrize("preconditioner,model", [("none", "hooke"), ("none", "corotational"),
                                                  ("multigrid", "hooke")])
def test_warm_steps_are_the_converged_steps_in_fewer_iterations(preconditioner, model):
    if preconditioner == "multigrid":
        pytest.importorskip("pyamg")
    runs, iterations = [], []
    for warm in (False, True):
        # (the multigrid's beam is large enough for a coarse level: a small one is solved directly)
        cells = (40, 4, 4) if preconditioner == "multigrid" else (12, 3, 3)
        sim = beam_sim(warm, preconditioner, model, cells, rayleigh_mass=0.1, planes=[tm.Plane((0, 0, 1), -0.05, 1e4)])
        counts = []
        for _ in range(15):
            sim.step()
            counts.append(int(sim.last_report.cg[0].iterations.max()))
        runs.append(sim.x.clone())
        iterations.append(counts)
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-8)
    assert iterations[1][0] == iterations[0][0]  # the first step has no history
    assert sum(iterations[1][2:]) < sum(iterations[0][2:]), iterations


def test_the_guess_is_the_extrapolation_of_the_last_steps(monkeypatch):
    guesses = []
    step = simulator_module.implicit_euler_step

    def spy(system, x, v, opts, imposed=None, guess=None):
        guesses.append(None if guess is None else guess.clone())
        return step(system, x, v, opts, imposed, guess)

    monkeypatch.setattr(simulator_module, "implicit_euler_step", spy)
    sim = beam_sim(True)
    solutions = []
    for _ in range(3):
        sim.step()
        solutions.append(sim.last_report.cg[0].solution.clone())
    assert guesses[0] is None
    torch.testing.assert_close(guesses[1], solutions[0], rtol=0, atol=0)
    torch.testing.assert_close(guesses[2], 2.0 * solutions[1] - solutions[0], rtol=0, atol=0)
    sim.x = sim.x.clone()  # a state set by hand: no history
    sim.step()
    assert guesses[3] is None
    sim.step()
    torch.testing.assert_close(guesses[4], sim._solutions[0][1], rtol=0, atol=0)
    cold = beam_sim(False)
    guesses.clear()
    cold.step(2)
    assert guesses == [None, None]


def test_sub_steps_keep_no_history(monkeypatch):
    sim = beam_sim(True, substeps_on_failure=2)
    sim.step(2)
    assert sim._guess() is not None
    real = simulator_module.Simulator._substeps

    def fail_once(self, count):
        if count == 1:
            raise tm.SolverError("forced", ["not converged"], None)
        return real(self, count)

    monkeypatch.setattr(simulator_module.Simulator, "_substeps", fail_once)
    sim.step()
    assert sim.last_report.substeps == 2 and sim._guess() is None


@pytest.mark.parametrize("value,mode", [("true", "extrapolate"), ('"extrapolate"', "extrapolate"),
                                        ('"project"', "project"), ("false", "none")])
def test_scene_key_and_bad_input(tmp_path, value, mode):
    path = tmp_path / "warm.toml"
    path.write_text(f"""
dt = 0.01
steps = 2
[solver]
warm_start = {value}
[[bodies]]
mesh = {{ generator = "beam", cells = [6, 2, 2], size = [1.0, 0.5, 0.5] }}
material = {{ model = "hooke", young = 1e5, poisson = 0.3, density = 1000.0 }}
fixed = {{ box = [[0.0, 0.0, 0.0], [0.0, 0.5, 0.5]] }}
""")
    scene = tm.load_scene(path)
    assert scene.simulator.options.warm_start == mode
    scene.simulator.step(2)
    path.write_text(path.read_text().replace(f"warm_start = {value}", 'warm_start = "yes"'))
    with pytest.raises(tm.SceneError, match="unknown warm start 'yes'"):
        tm.load_scene(path)
    path.write_text(path.read_text().replace('warm_start = "yes"', "warm_start = 1"))
    with pytest.raises(tm.SceneError, match="warm_start"):
        tm.load_scene(path)
    with pytest.raises(tm.SceneError, match="warm_start must be True, False or one of .*got 1"):
        beam_sim(1)
