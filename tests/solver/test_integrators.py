"""The step's integrators (``StepOptions.integrator``): Newmark's average acceleration (the
trapezoidal rule) and BDF2 against their own definitions on a linear system (float64, dense),
their energy and amplitude against backward Euler's on a cantilever's first mode at dt = T/64,
the orders of accuracy in the mode's frequency and amplitude, BDF2's history (its start, a state
set by hand, a cut, prescribed motion), the CPU extension against pure torch, CUDA against the
CPU, scene files and bad input."""
import math

import pytest
import torch
from conftest import beam_scene_file, on_each_cpu_backend

import tensormass_torch as tm
from tensormass_torch.solver.implicit_euler import implicit_euler_step

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


@pytest.mark.parametrize("integrator", ["newmark", "bdf2"])
def test_the_cpu_extension_and_pure_torch_agree(monkeypatch, integrator):
    """Steps of a corotational beam with damping and a floor, extension against pure torch."""
    def run():
        mesh = tm.beam_mesh(4, 1, 1, size=(1.0, 0.25, 0.25), dtype=DT)
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="corotational"),
                       fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.001, cg_tol=1e-12,
                           planes=[tm.Plane((0, 0, 1), -0.1, 1e4)], integrator=integrator, cuda_graphs=False)
        sim.step(20)
        return sim.x.clone()

    extension, pure = on_each_cpu_backend(monkeypatch, run)
    torch.testing.assert_close(extension, pure, rtol=0, atol=1e-10)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
@pytest.mark.parametrize("integrator", ["newmark", "bdf2"])
def test_cuda_matches_the_cpu(model, integrator):
    """Newmark and BDF2 on CUDA (captured steps, chained where they may be, the hooke tensor
    form's one-kernel steps) equal the CPU in float64."""
    runs = []
    for device in ("cpu", "cuda"):
        mesh = tm.beam_mesh(6, 2, 2, size=(1.0, 0.25, 0.25), dtype=DT)
        body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                       fixed=mesh.vertices[:, 0] == 0)
        sim = tm.Simulator([body], dt=0.01, rayleigh_mass=0.1, cg_tol=1e-12, integrator=integrator, device=device,
                           planes=[tm.Plane((0, 0, 1), -0.05, 1e4)])
        sim.step(40)
        runs.append(sim.x.cpu())
    torch.testing.assert_close(runs[1], runs[0], rtol=0, atol=1e-9)


def test_scene_file_and_bad_input(tmp_path):
    path = beam_scene_file(tmp_path / "newmark.toml", 'integrator = "newmark"', steps=3)
    scene = tm.load_scene(path)
    assert scene.simulator.options.integrator == "newmark"
    with pytest.raises(tm.SceneError, match="integrator must be one of 'backward_euler', 'newmark', 'bdf2', got 'bdf3'"):
        cantilever("bdf3")
    with pytest.raises(tm.SceneError, match="newton_iters=2 needs integrator='backward_euler' or 'bdf2'"):
        cantilever("newmark", newton_iters=2)
    cantilever("bdf2", newton_iters=2).step(3)  # BDF2's solves are backward Euler's: Newton applies
    for integrator in ("newmark", "bdf2"):
        sim = cantilever(integrator)
        with pytest.raises(tm.SolverError, match=f"integrator='{integrator}'"):
            tm.rollout(sim, 2, x0=sim.x.clone().requires_grad_(True))
    sim = cantilever("bdf2")
    with pytest.raises(ValueError, match="use bdf2_step"):
        implicit_euler_step(sim.system, sim.x, sim.v, sim.options)


def test_a_bdf2_step_is_its_formula():
    """After its backward Euler start, a step solves 3/2 x'' - 2 x' + 1/2 x = h v'' and
    M (3/2 v'' - 2 v' + 1/2 v) = h F(x'', v''), F = f(x) - r_M M v - r_K K v, on a linear system
    with Rayleigh damping and fixed nodes (the equations, not the extrapolation they become)."""
    sim = cantilever("bdf2", damping=(0.3, 0.01))
    gen = torch.Generator().manual_seed(4)
    free = sim.system.free
    sim.x = sim.x + 0.01 * torch.randn(sim.x.shape, generator=gen, dtype=DT) * free
    sim.v = 0.3 * torch.randn(sim.x.shape, generator=gen, dtype=DT) * free
    states = [(sim.x.clone(), sim.v.clone())]
    for _ in range(3):
        sim.step()
        states.append((sim.x.clone(), sim.v.clone()))
    K = stiffness_matrix(sim)
    m = sim.system.mass.expand(-1, 3)
    h = sim.options.dt

    def F(pos, vel):
        return sim.model(pos) - 0.3 * m * vel - 0.01 * (K @ vel.reshape(-1)).reshape(-1, 3)

    (x0, v0), (x1, v1) = states[:2]
    torch.testing.assert_close(x1, x0 + h * v1, rtol=0, atol=1e-13)  # the start: backward Euler
    torch.testing.assert_close((m * (v1 - v0) - h * F(x1, v1)) * free, torch.zeros_like(x0), rtol=0, atol=1e-10)
    for (xa, va), (xb, vb), (xc, vc) in zip(states, states[1:], states[2:]):
        torch.testing.assert_close(1.5 * xc - 2 * xb + 0.5 * xa, h * vc, rtol=0, atol=1e-13)
        residual = m * (1.5 * vc - 2 * vb + 0.5 * va) - h * F(xc, vc)
        torch.testing.assert_close(residual * free, torch.zeros_like(xc), rtol=0, atol=1e-10)


def test_bdf2_damps_at_third_order_and_keeps_the_amplitude():
    """BDF2's amplitude lost per period (after its first, which holds the backward Euler start)
    falls eight times when dt halves (damping O(h^3)); at dt = T/64 it is under 0.5 % (backward
    Euler: a quarter); its phase error is second order."""
    losses, phases = [], []
    for n in (32, 64, 128):
        amplitudes, phase = modal_amplitudes("bdf2", n, 3)
        losses.append(1 - float((amplitudes[3] / amplitudes[1]) ** 0.5))
        phases.append(abs(phase))
    for coarse, fine in zip(losses, losses[1:]):
        assert 6.5 < coarse / fine < 9.0, losses
    for coarse, fine in zip(phases, phases[1:]):
        assert 3.6 < coarse / fine < 4.4, phases
    assert 0 < losses[1] < 0.005


def test_bdf2_history_starts_again_where_it_must():
    """Setting ``sim.x`` by hand and a cut in place start BDF2 again (a backward Euler step, as
    the first); prescribed nodes reach their motion's targets at every step."""
    def started():
        sim = cantilever("bdf2", spare_nodes=16)
        sim.v = 0.1 * sim.system.free.expand(-1, 3).clone()
        sim.step(2)
        assert sim._previous_state() is not None
        return sim

    sim = started()
    x_set, v_now = sim.x + 1e-3 * sim.system.free, sim.v.clone()
    sim.x = x_set.clone()
    assert sim._previous_state() is None
    sim.step()
    reference = cantilever("backward_euler", spare_nodes=16)
    reference.x, reference.v = x_set.clone(), v_now.clone()
    reference.step()
    torch.testing.assert_close(sim.x, reference.x, rtol=0, atol=1e-13)
    assert sim._previous_state() is not None  # and BDF2 again from there

    sim = started()
    nodes = sim.x.shape[0]
    sim.cut(0, tm.Blade.swept([0.6, -1.0, 0.3], [0.6, 1.0, 0.3], [0.6, -1.0, 0.1], [0.6, 1.0, 0.1]))
    assert sim.x.shape[0] == nodes and sim.used_nodes[0] > 20  # in place, a node split
    assert sim._previous_state() is None
    sim.step(2)
    assert sim._previous_state() is not None

    mesh = tm.beam_mesh(4, 1, 1, size=(1.0, 0.25, 0.25), dtype=DT)
    far = mesh.vertices[:, 0] == 1.0
    start = mesh.vertices[far]
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0), fixed=mesh.vertices[:, 0] == 0,
                   prescribed=far, motion=lambda t: start + torch.tensor([0.0, 0.0, -0.5 * t * t], dtype=DT))
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-12, integrator="bdf2", cuda_graphs=False)
    for _ in range(4):
        sim.step()
        target = start + torch.tensor([0.0, 0.0, -0.5 * sim.time ** 2], dtype=DT)
        torch.testing.assert_close(sim.x[far], target, rtol=0, atol=1e-12)
