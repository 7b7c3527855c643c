"""The step's integrators (``StepOptions.integrator``): Newmark's average acceleration (the
trapezoidal rule) against its own definition on a linear system (float64, dense), its energy and
amplitude against backward Euler's on a cantilever's first mode at dt = T/64, the order of
accuracy of both in the mode's frequency and amplitude, the CPU extension against pure torch,
CUDA against the CPU, scene files and bad input."""
import math

import pytest
import torch

import tensormass_torch as tm

DT = torch.float64


def cantilever(integrator, dt=0.01, damping=(0.0, 0.0), cells=(4, 1, 1), **options):
    """A hooke beam 1 x 0.25 x 0.25 m held at x = 0, no gravity (float64)."""
    mesh = tm.beam_mesh(*cells, size=(1.0, 0.25, 0.25), dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0), fixed=mesh.vertices[:, 0] == 0)
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), rayleigh_mass=damping[0],
                        rayleigh_stiffness=damping[1], cg_tol=1e-13, integrator=integrator, cuda_graphs=False,
                        **options)


def stiffness_matrix(sim):
    """-df/dx ``[3V, 3V]`` at rest (hooke: constant)."""
    rest = sim.model.rest
    return -torch.autograd.functional.jacobian(lambda y: sim.model(y.reshape(-1, 3)).reshape(-1), rest.reshape(-1))


def first_mode(sim):
    """(omega, shape [V, 3] with phi^T M phi = 1) of the free nodes' lowest mode."""
    K = stiffness_matrix(sim)
    free = (sim.system.free.expand(-1, 3).reshape(-1) > 0)
    m = sim.system.mass.expand(-1, 3).reshape(-1)
    scale = m[free].rsqrt()
    values, vectors = torch.linalg.eigh(scale[:, None] * K[free][:, free] * scale[None, :])
    shape = torch.zeros_like(m)
    shape[free] = scale * vectors[:, 0]
    return float(values[0].sqrt()), shape.reshape(-1, 3)


def test_a_newmark_step_is_the_trapezoidal_rule():
    """On a linear (hooke) system with Rayleigh damping and fixed nodes, one step solves
    M dv = h/2 (F(x, v) + F(x', v')), x' = x + h/2 (v + v'), F = f(x) - r_M M v - r_K K v: the
    equations themselves, not the solver's rearrangement of them."""
    sim = cantilever("newmark", damping=(0.3, 0.01))
    gen = torch.Generator().manual_seed(0)
    free = sim.system.free
    x = sim.x + 0.01 * torch.randn(sim.x.shape, generator=gen, dtype=DT) * free
    v = 0.3 * torch.randn(sim.x.shape, generator=gen, dtype=DT) * free
    sim.x, sim.v = x.clone(), v.clone()
    sim.step()
    K = stiffness_matrix(sim)
    m = sim.system.mass.expand(-1, 3)

    def F(pos, vel):
        return sim.model(pos) - 0.3 * m * vel - 0.01 * (K @ vel.reshape(-1)).reshape(-1, 3)

    h = sim.options.dt
    residual = m * (sim.v - v) - 0.5 * h * (F(x, v) + F(sim.x, sim.v))
    torch.testing.assert_close(residual * free, torch.zeros_like(x), rtol=0, atol=1e-10)
    torch.testing.assert_close(sim.x, x + 0.5 * h * (v + sim.v), rtol=0, atol=1e-13)


def modal_amplitudes(integrator, steps_per_period, periods, cells=(4, 1, 1)):
    """The first mode's amplitude sqrt(q^2 + (q'/omega)^2) at each period's end [periods + 1] and
    its phase after the last, released from rest in that mode at dt = T / steps_per_period."""
    sim = cantilever(integrator, cells=cells)
    omega, shape = first_mode(sim)
    sim.options = type(sim.options)(**{**sim.options.__dict__, "dt": 2 * math.pi / omega / steps_per_period})
    m = sim.system.mass.expand(-1, 3)
    rest = sim.model.rest
    sim.x = rest + 0.01 * shape
    sim.v = torch.zeros_like(sim.v)

    def modal():
        q = float((shape * m * (sim.x - rest)).sum())
        q_dot = float((shape * m * sim.v).sum())
        return q, q_dot

    amplitudes = [0.01]
    for _ in range(periods):
        sim.step(steps_per_period)
        q, q_dot = modal()
        amplitudes.append(math.hypot(q, q_dot / omega))
    return torch.tensor(amplitudes, dtype=DT), math.atan2(-q_dot / omega, q)


def test_newmark_keeps_the_first_modes_amplitude_where_backward_euler_loses_it():
    """dt = T/64 (T the first mode's period): backward Euler loses about a quarter of the
    amplitude per period, Newmark none (it keeps a linear system's energy)."""
    euler, _ = modal_amplitudes("backward_euler", 64, 3)
    newmark, _ = modal_amplitudes("newmark", 64, 3)
    loss = lambda a: 1 - float((a[-1] / a[0]) ** (1 / (len(a) - 1)))  # noqa: E731  (per period)
    assert 0.2 < loss(euler) < 0.35
    assert abs(loss(newmark)) < 1e-6


def test_orders_of_accuracy_in_frequency_and_amplitude():
    """Halving dt: backward Euler's logarithmic decrement per period halves (first order: pi
    omega h to leading order); Newmark's phase error after one period falls four times (second
    order)."""
    euler = [-math.log(float(modal_amplitudes("backward_euler", n, 1)[0][-1] / 0.01)) for n in (32, 64, 128)]
    phases = [abs(modal_amplitudes("newmark", n, 1)[1]) for n in (32, 64, 128)]
    for coarse, fine in zip(euler, euler[1:]):
        assert 1.8 < coarse / fine < 2.2
    for coarse, fine in zip(phases, phases[1:]):
        assert 3.8 < coarse / fine < 4.2
    # (Newmark's period elongation: the phase lags by (omega h)^2 / 12 per radian, to leading order)
    omega_h = 2 * math.pi / 64
    assert phases[1] == pytest.approx(2 * math.pi * omega_h ** 2 / 12, rel=0.02)


def test_the_cpu_extension_and_pure_torch_agree(monkeypatch):
    """Newmark steps of a corotational beam with damping and a floor, extension against pure torch."""
    from tensormass_torch import _backend

    if not _backend.use_extension("cpu"):
        pytest.skip("the CPU extension is not built")
    runs = []
    for mode in ("extension", "torch"):
        monkeypatch.setenv("TENSORMASS_BACKEND", mode)
        mesh = tm.beam_mesh(4, 1, 1, size=(1.0, 0.25, 0.25), dtype=DT)
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="corotational"),
                       fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.001, cg_tol=1e-12,
                           planes=[tm.Plane((0, 0, 1), -0.1, 1e4)], integrator="newmark", cuda_graphs=False)
        sim.step(20)
        runs.append(sim.x.clone())
    torch.testing.assert_close(runs[0], runs[1], rtol=0, atol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_cuda_matches_the_cpu(model):
    """Newmark on CUDA (captured steps, chained, the hooke tensor form's one-kernel steps) equals
    the CPU in float64."""
    runs = []
    for device in ("cpu", "cuda"):
        mesh = tm.beam_mesh(6, 2, 2, size=(1.0, 0.25, 0.25), dtype=DT)
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                       fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, rayleigh_mass=0.1, cg_tol=1e-12, integrator="newmark", device=device,
                           planes=[tm.Plane((0, 0, 1), -0.05, 1e4)])
        sim.step(40)
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)


def test_scene_file_and_bad_input(tmp_path):
    path = tmp_path / "newmark.toml"
    path.write_text("""
dt = 0.01
steps = 3
[solver]
integrator = "newmark"
[[bodies]]
mesh = { generator = "beam", cells = [2, 1, 1], size = [1.0, 0.5, 0.5] }
material = { model = "hooke", young = 1e5, poisson = 0.3, density = 1000.0 }
fixed = { box = [[0.0, 0.0, 0.0], [0.0, 0.5, 0.5]] }
""")
    scene = tm.load_scene(path)
    assert scene.simulator.options.integrator == "newmark"
    with pytest.raises(tm.SceneError, match="integrator must be one of 'backward_euler', 'newmark', got 'bdf3'"):
        cantilever("bdf3")
    with pytest.raises(tm.SceneError, match="newton_iters=2 needs integrator='backward_euler'"):
        cantilever("newmark", newton_iters=2)
    sim = cantilever("newmark")
    with pytest.raises(tm.SolverError, match="integrator='newmark'"):
        tm.rollout(sim, 2, x0=sim.x.clone().requires_grad_(True))
