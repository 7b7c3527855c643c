"""Adaptive sub-stepping of failed steps, and long runs that hold memory flat (issue 6).

A step whose CG needs more iterations than its cap fails at dt; at dt / 4 the system
M - h^2 K is closer to M and converges within the cap: the retried step must be exactly four
steps of dt / 4 (prescribed motion at the sub-step times), and the state must be untouched when
every retry fails. Memory: 2,000 steps must leave the live tensors (count and bytes) exactly as
they were after the warm-up, with process RSS growth within a bound far above noise; a CUDA
variant compares ``torch.cuda.memory_allocated`` (run by the lead on the GPU).
"""
from __future__ import annotations

import os

import pytest
import torch
from conftest import live_tensors, load_script

import tensormass_torch as tm

DT = torch.float64
#: CG iterations (tol 1e-8) of the scene below, measured: 27 at dt, 20-21 at dt/2, 14-15 at dt/4.
CAP = 18


def pushed_beam(dt=0.01, substeps=0, cap=CAP):
    """A stiff stvk beam clamped at x = 0 whose far end is moved up at 0.5 m/s (prescribed)."""
    mesh = tm.beam_mesh(4, 1, 1, size=(1.0, 0.25, 0.25), dtype=DT)
    far = mesh.vertices[:, 0] >= 1.0 - 1e-9
    start = mesh.vertices[far].clone()

    def motion(t):
        goal = start.clone()
        goal[:, 2] += 0.5 * t
        return goal

    body = tm.Body(mesh, tm.Material(young=1e6, poisson=0.3, density=1000.0, model="stvk"),
                   fixed=mesh.vertices[:, 0] <= 1e-9, prescribed=far, motion=motion)
    return tm.Simulator([body], dt=dt, dtype=DT, cg_tol=1e-8, cg_max_iter=cap, substeps_on_failure=substeps)


def test_failed_step_succeeds_in_four_substeps():
    plain = pushed_beam()
    with pytest.raises(tm.SolverError, match="not converged"):
        plain.step()
    sim = pushed_beam(substeps=3)
    report = sim.step()
    assert report.substeps == 4 and len(report.cg) == 4
    assert all(bool(r.converged.all()) for r in report.cg)
    assert sim.time == 0.01 and sim.steps_done == 1
    # the same as four steps of dt / 4, the prescribed nodes at the sub-step times
    quarter = pushed_beam(dt=0.0025)
    quarter.step(4)
    torch.testing.assert_close(sim.x, quarter.x, rtol=0, atol=1e-13)
    torch.testing.assert_close(sim.v, quarter.v, rtol=0, atol=1e-10)
    assert abs(float(sim.x[sim.prescribed][:, 2].max()) - (0.25 + 0.5 * 0.01)) < 1e-12
    # the next step starts over at dt (and needs sub-steps again)
    assert sim.step().substeps in (2, 4)


def test_state_is_kept_when_every_retry_fails():
    sim = pushed_beam(substeps=1)  # dt and dt/2 only: both above the cap
    x, v = sim.x.clone(), sim.v.clone()
    with pytest.raises(tm.SolverError, match=r"failed at dt = 0.01 and in 2 to 2 sub-steps; last: .*not converged") \
            as info:
        sim.step()
    assert info.value.status == ["not converged"]
    assert torch.equal(sim.x, x) and torch.equal(sim.v, v) and sim.time == 0.0 and sim.steps_done == 0
    assert sim.last_report is None


def test_inverting_step_is_retried_in_substeps():
    """check_inversion="error" makes an inverting step a failure, which sub-stepping can retry:
    a step that inverts at dt and whose sub-steps also invert is refused, state kept."""
    mesh = tm.beam_mesh(2, 1, 1, size=(1.0, 0.3, 0.3), dtype=DT)
    far = mesh.vertices[:, 0] >= 1.0 - 1e-9
    goal = mesh.vertices[far].clone()
    goal[:, 0] = -0.6  # through the clamp: every sub-division still ends inverted
    body = tm.Body(mesh, tm.Material(young=1e4, poisson=0.3, density=1000.0, model="hooke"),
                   fixed=mesh.vertices[:, 0] <= 1e-9, prescribed=far, motion=lambda t: goal)
    sim = tm.Simulator([body], dt=0.01, dtype=DT, check_inversion="error", substeps_on_failure=2)
    x = sim.x.clone()
    with pytest.raises(tm.SolverError,
                       match=r"2 to 4 sub-steps; last: the step to t = 0.0025 inverts elements \(object 0: \d+ inverted"):
        sim.step()
    assert torch.equal(sim.x, x) and sim.steps_done == 0


def test_plain_step_reports_one_substep():
    sim = pushed_beam(cap=200, substeps=3)
    report = sim.step()
    assert report.substeps == 1 and len(report.cg) == 1 and report.inverted is None


# ------------------------------------------------------------------------------ memory over long runs


def rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def busy_scene(device="cpu"):
    """Every per-step path: stvk + corotational + a membrane, prescribed motion, damping, a plane,
    inversion checks and sub-stepping on."""
    mesh = tm.beam_mesh(2, 1, 1, size=(1.0, 0.3, 0.3), dtype=DT, device=device)
    sheet = tm.beam_tri_mesh(2, 1, size=(1.0, 0.5), dim=3, dtype=DT, device=device)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, 0.0, 1.0], dtype=DT, device=device), sheet.elements)
    far = mesh.vertices[:, 0] >= 1.0 - 1e-9
    start = mesh.vertices[far].clone()
    bodies = [
        tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk"),
                fixed=mesh.vertices[:, 0] <= 1e-9, prescribed=far,
                motion=lambda t: start + 0.01 * torch.sin(torch.tensor(t))),
        tm.Body(sheet, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="corotational", thickness=0.01),
                fixed=sheet.vertices[:, 0] <= 1e-9),
    ]
    return tm.Simulator(bodies, dt=0.01, dtype=DT, device=device, rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                        planes=[tm.Plane((0.0, 0.0, 1.0), -0.2, 1e4)], cg_tol=1e-8, cg_max_iter=12,
                        require_convergence=False, check_inversion="warn", substeps_on_failure=2)


def test_live_tensor_census_sees_a_leak():
    sim = busy_scene()
    sim.step(5)
    before = live_tensors()
    kept = []
    for _ in range(20):
        sim.step()
        kept.append(sim.x.clone())  # a leak of one state per step
    after = live_tensors()
    assert after[0] == before[0] + 20
    assert after[1] >= before[1] + 20 * sim.x.numel() * sim.x.element_size()


# the membrane of the busy scene folds where it hits the plane: expected, and not what is tested
@pytest.mark.filterwarnings("ignore::tensormass_torch.sim.simulator.InvertedElementsWarning")
def test_memory_is_flat_over_2000_steps_cpu():
    sim = busy_scene()
    sim.step(50)  # warm-up: every lazily made buffer exists now
    tensors_before, rss_before = live_tensors(), rss_bytes()
    for _ in range(2000 // 250):
        sim.step(250)
    tensors_after, rss_after = live_tensors(), rss_bytes()
    assert sim.steps_done == 2050 and bool(torch.isfinite(sim.x).all())
    assert tensors_after == tensors_before
    # a leak of the C++ side shows in RSS; 32 MiB is far above allocator noise and far below
    # what leaking any per-step buffer 2,000 times would cost on a real scene
    assert rss_after - rss_before < 32 * 2**20, (rss_before, rss_after)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.filterwarnings("ignore::tensormass_torch.sim.simulator.InvertedElementsWarning")
def test_memory_is_flat_over_2000_steps_cuda():
    sim = busy_scene("cuda")
    sim.step(50)
    torch.cuda.synchronize()
    allocated, tensors_before = torch.cuda.memory_allocated(), live_tensors()
    sim.step(2000)
    torch.cuda.synchronize()
    assert bool(torch.isfinite(sim.x).all())
    # 64 KiB: the allocator's rounding of any one-off buffer; a leak of one [V, 3] state per step
    # would add 2,000 x 512 B = 1 MiB
    assert torch.cuda.memory_allocated() - allocated <= 64 * 2**10, (allocated, torch.cuda.memory_allocated())
    assert live_tensors() == tensors_before


# ------------------------------------------------------------------ the stability benchmark's judge


def load_stability_benchmark():
    return load_script("benchmarks/studies", "stability")


def test_benchmark_judges_stable_degraded_failed():
    bench = load_stability_benchmark()
    calm = bench.run_case(bench.swinging_beam("corotational", "cpu", DT, young=1e4), 3)
    assert calm["outcome"] == "stable" and calm["steps_done"] == 3
    assert calm["energy_gain"] < 1e-3 and calm["energy_drift"] <= 0.0  # implicit Euler only dissipates
    spun = bench.run_case(bench.spinning_beam("hooke", "cpu", DT, steps=10), 10)  # hooke grows when spun
    assert spun["outcome"] == "degraded" and spun["volume_error"] > 0.05 and "volume error" in spun["note"]
    crushed = bench.run_case(pushed_beam(), 2)  # CG cap below what a step needs
    assert crushed["outcome"] == "failed" and crushed["steps_done"] == 0 and "not converged" in crushed["error"]


def test_compressed_stvk_breakdown_is_reported_and_the_state_kept():
    """stvk crushed to half its length loses positive definiteness: the CG meets negative
    curvature, the step is refused as "breakdown" with the state of the step before."""
    bench = load_stability_benchmark()
    sim = bench.compressed_beam("stvk", "cpu", DT, squeeze=0.5, steps=25, cg_tol=1e-8, cg_max_iter=2000)
    for _ in range(25):
        x, v, t = sim.x.clone(), sim.v.clone(), sim.time
        try:
            sim.step()
        except tm.SolverError as exc:
            assert exc.status == ["breakdown"] and "breakdown" in str(exc)
            assert torch.equal(sim.x, x) and torch.equal(sim.v, v) and sim.time == t
            break
    else:
        pytest.fail("stvk crushed to half its length did not break down")
