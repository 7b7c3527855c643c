"""Mixed precision (``precision="mixed"``, ``solver.refine``): a float64 state whose solves are
iterative refinement, float64 residuals and float32 CG corrections. A mixed step is the float64
step (its float64 residual within cg_tol, the trajectory of a float64 solve), over batches, planes
with friction, a tool, Newmark, warm starts and removed elements; the CPU extension against pure torch;
CUDA's captured steps against the CPU; failures reported as a float64 solve's; bad input."""
import pytest
import torch
from conftest import beam_scene_file, on_each_cpu_backend

import tensormass_torch as tm
from tensormass_torch.solver import implicit_euler
from tensormass_torch.solver.refine import INNER_TOL, Refinement

DT = torch.float64


def beam(young=1e5, cells=(8, 2, 2), model="hooke", **options):
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=young, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] == 0)
    return body


def simulator(precision, bodies=None, **options):
    options = {"cg_tol": 1e-8, "cuda_graphs": False, **options}
    return tm.Simulator(bodies or [beam()], dt=0.01, precision=precision, **options)


def step_residual(sim, x, v, solution):
    """|b - A y| / |b| of the step from ``x, v`` for ``y`` (float64: the step's own system, made
    again here from the simulator's float64 product)."""
    opts = sim.options
    matvec = sim.system.system_matvec(*implicit_euler._coefficients(opts), opts.pipelined, opts.variants)
    rhs, _, _ = implicit_euler._step_system(sim.system, x, v, opts, None, matvec)
    free = 1.0 if sim.system.free is None else sim.system.free
    residual = (rhs - matvec(solution)[0]) * free
    return float(residual.norm() / (rhs * free).norm())


@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
@pytest.mark.parametrize("warm_start", ["none", "project"])
def test_a_mixed_step_is_the_float64_step(model, warm_start):
    """Each step's float64 residual, computed again outside the solver, is within cg_tol; the
    trajectory is the float64 solves' to the tolerance; the corrections ran in float32."""
    plane = [tm.Plane((0, 0, 1), -0.02, 1e4, friction=0.3)]
    runs = {}
    for precision in ("full", "mixed"):
        sim = simulator(precision, [beam(model=model)], planes=plane, warm_start=warm_start, rayleigh_mass=0.1)
        for _ in range(12):
            x, v = sim.x.clone(), sim.v.clone()
            sim.step()
            result = sim.last_report.cg[0]
            assert bool(result.converged.all())
            if precision == "mixed":
                assert step_residual(sim, x, v, result.solution) <= 1e-8 * (1 + 1e-6)
                assert float(result.relative_residual.max()) <= 1e-8
        runs[precision] = sim
    torch.testing.assert_close(runs["mixed"].x, runs["full"].x, rtol=0, atol=1e-9)
    (refinement,) = [kept[2] for kept in runs["mixed"].system._refinements.values()]
    assert refinement.cg32.state.x.dtype == torch.float32 and runs["mixed"].x.dtype == DT


def test_a_tool_pressing_is_the_float64_step():
    """A sphere pressing into the beam, with friction, and a floor: the tool's penalties reach the
    float32 corrections through the float64 product's node stiffness; the trajectory and the
    tool's reaction are the float64 solves'."""
    sphere = tm.Sphere(0.08, times=[0.0, 0.1], positions=[[0.8, 0.125, 0.3], [0.8, 0.125, 0.2]], stiffness=1e4,
                       friction=0.3)
    runs = {}
    for precision in ("full", "mixed"):
        sim = simulator(precision, tools=[sphere], planes=[tm.Plane((0, 0, 1), -0.05, 1e4)], warm_start="project")
        sim.step(10)
        assert bool(sim.last_report.cg[0].converged.all())
        runs[precision] = sim
    torch.testing.assert_close(runs["mixed"].x, runs["full"].x, rtol=0, atol=1e-9)
    reaction = [sim.last_report.contact.tool_force for sim in (runs["full"], runs["mixed"])]
    assert float(reaction[0].abs().max()) > 0
    # (the trajectories agree to 1e-9 m, times the tool's stiffness 1e4 N/m)
    torch.testing.assert_close(reaction[1], reaction[0], rtol=0, atol=1e-5)


def test_rounds_cut_the_residual_by_the_inner_tolerance(monkeypatch):
    """To 1e-10 from zero a step takes the rounds that INNER_TOL per round needs (four, from a
    residual of 1 to 1e-10: the last needs only tol |b| / 2), each a float32 solve."""
    rounds = []
    real = Refinement.round

    def spy(self, cg, *args, **kwargs):
        before = cg.state.rr.sqrt().clone()
        real(self, cg, *args, **kwargs)
        rounds.append((float(before.max()), float(cg.state.rr.sqrt().max()), int(self.cg32.state.iterations.max())))

    monkeypatch.setattr(Refinement, "round", spy)
    sim = simulator("mixed", cg_tol=1e-10)
    sim.step()
    assert 3 <= len(rounds) <= 5, rounds
    for before, after, iterations in rounds[:-1]:
        assert after <= 2 * INNER_TOL * before and iterations > 0
    assert int(sim.last_report.cg[0].iterations) == sum(r[2] for r in rounds)


def test_a_batch_stops_each_object_on_its_own():
    """Two beams of stiffness 100x apart: each converges on its own residual, and equals its
    float64 trajectory."""
    runs = {}
    for precision in ("full", "mixed"):
        sim = simulator(precision, [beam(1e5), beam(1e7, cells=(6, 2, 2))])
        sim.step(5)
        assert bool(sim.last_report.cg[0].converged.all())
        runs[precision] = sim
    torch.testing.assert_close(runs["mixed"].x, runs["full"].x, rtol=0, atol=1e-9)


def test_newmark_and_removed_elements():
    """Newmark's coefficients, and elements removed between steps (the float32 copy made again
    from the edited model)."""
    runs = {}
    for precision in ("full", "mixed"):
        sim = simulator(precision, integrator="newmark")
        sim.step(3)
        before = list(sim.system._refinements.values())
        sim.remove_elements(0, list(range(40, 60)))
        sim.step(3)
        runs[precision] = sim
        if precision == "mixed":  # a copy of the edited model replaced the first
            (after,) = sim.system._refinements.values()
            assert len(before) == 1 and after[2] is not before[0][2]
            assert after[2].system32.model.num_elements == sim.model.num_elements
    torch.testing.assert_close(runs["mixed"].x, runs["full"].x, rtol=0, atol=1e-9)


def test_the_cpu_extension_and_pure_torch_agree(monkeypatch):
    def run():
        sim = simulator("mixed", [beam(model="corotational")], planes=[tm.Plane((0, 0, 1), -0.02, 1e4)],
                        warm_start="project")
        sim.step(8)
        return sim.x.clone()

    extension, pure = on_each_cpu_backend(monkeypatch, run)
    torch.testing.assert_close(extension, pure, rtol=0, atol=1e-9)


def test_a_solve_short_of_the_tolerance_fails_as_a_float64_one():
    """Corrections capped at 3 float32 iterations: the step is not converged and raises naming the
    residual, the state unchanged; with require_convergence=False it is accepted."""
    sim = simulator("mixed", cg_max_iter=3)
    x = sim.x.clone()
    with pytest.raises(tm.SolverError, match="not converged: relative residual"):
        sim.step()
    assert torch.equal(sim.x, x)
    relaxed = simulator("mixed", cg_max_iter=3, require_convergence=False)
    relaxed.step()
    assert not bool(relaxed.last_report.cg[0].converged.any())


def test_scene_key_and_bad_input(tmp_path):
    path = beam_scene_file(tmp_path / "mixed.toml", 'precision = "mixed"', header='dtype = "float64"')
    scene = tm.load_scene(path)
    assert scene.simulator.options.precision == "mixed"
    scene.simulator.step(2)
    with pytest.raises(tm.SceneError, match="precision must be one of 'full', 'mixed', got 'half'"):
        simulator("half")
    with pytest.raises(tm.SceneError, match="needs dtype=torch.float64, got torch.float32"):
        simulator("mixed", dtype=torch.float32)
    with pytest.raises(tm.SceneError, match="preconditioner must be 'auto' or 'none', got 'jacobi'"):
        simulator("mixed", preconditioner="jacobi")
    with pytest.raises(tm.SceneError, match="does not take contact between bodies"):
        simulator("mixed", contact=tm.Contact())
    with pytest.raises(ValueError, match="unknown precision 'half'"):
        implicit_euler.StepOptions(dt=0.01, precision="half")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("warm_start", ["none", "project"])
@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_cuda_captured_steps_match_the_cpu(warm_start, model):
    """CUDA's captured mixed steps (the first round inside the start's graph, the rounds replayed)
    equal the CPU's float64 steps; the rounds' graphs were replayed."""
    runs = []
    for device in ("cpu", "cuda"):
        sim = tm.Simulator([beam(model=model)], dt=0.01, cg_tol=1e-8, device=device, precision="mixed",
                           warm_start=warm_start, planes=[tm.Plane((0, 0, 1), -0.02, 1e4)])
        for _ in range(20):
            sim.step()
            assert bool(sim.last_report.cg[0].converged.all())
        runs.append(sim)
    torch.testing.assert_close(runs[1].x.cpu(), runs[0].x, rtol=0, atol=1e-8)
    (graphs,) = runs[1].system._step_graphs.values()
    assert graphs.refinement is not None and any(g not in (None, False) for g in graphs._graphs.values())


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_captured_steps_after_removed_elements():
    """Elements removed between captured mixed steps: the float32 copy is made again, the step's
    graphs captured again over it, and the steps still equal the CPU's."""
    runs = []
    for device in ("cpu", "cuda"):
        sim = tm.Simulator([beam()], dt=0.01, cg_tol=1e-8, device=device, precision="mixed", warm_start="project")
        sim.step(5)
        first = sim.system.refinement(sim.options)
        sim.remove_elements(0, list(range(40, 60)))
        sim.step(5)
        assert sim.system.refinement(sim.options) is not first
        if device == "cuda":
            (graphs,) = sim.system._step_graphs.values()
            assert graphs.refinement is sim.system.refinement(sim.options)
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-8)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_captured_steps_with_a_tool_match_the_cpu():
    """A moving sphere with friction: its penalties reach the captured float32 corrections through
    the copied node stiffness, as on the CPU."""
    runs = []
    for device in ("cpu", "cuda"):
        sphere = tm.Sphere(0.08, times=[0.0, 0.1], positions=[[0.8, 0.125, 0.3], [0.8, 0.125, 0.2]],
                           stiffness=1e4, friction=0.3)
        sim = tm.Simulator([beam()], dt=0.01, cg_tol=1e-8, device=device, precision="mixed", warm_start="project",
                           tools=[sphere])
        for _ in range(12):
            sim.step()
            assert bool(sim.last_report.cg[0].converged.all())
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-8)
