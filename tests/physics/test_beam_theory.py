"""Closed-form references (tensormass_torch.physics.analytic) against numbers derived here independently,
a simulation that approaches them, and a smoke run of benchmarks/studies/accuracy.py.

Independent derivations: deflections by the unit-load method (virtual work, integrated
numerically), the clamped-free root of 1 + cos b cosh b = 0 by bisection, Timoshenko frequencies
by a 1-D Timoshenko finite-element eigenproblem, and Richardson on sequences of known form.
"""
from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.physics import analytic

BENCH = Path(__file__).resolve().parents[2] / "benchmarks" / "studies"

E, NU, RHO, G = 1e8, 0.3, 1000.0, 9.81
L, WIDTH, HEIGHT = 1.0, 0.3, 0.2


@pytest.fixture(autouse=True)
def one_thread():
    """These meshes are small: one thread is fastest, and a shared machine's contention does not
    stall an OpenMP team."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def section(length_over_height=None):
    height = HEIGHT if length_over_height is None else L / length_over_height
    return analytic.rectangular_section(E, NU, RHO, WIDTH, height)


# ---------------------------------------------------------------------------------------------
# sections
# ---------------------------------------------------------------------------------------------


def test_cowper_coefficient_and_rectangle():
    assert analytic.cowper_shear_coefficient(0.0) == pytest.approx(5.0 / 6.0, rel=1e-15)
    assert analytic.cowper_shear_coefficient(0.3) == pytest.approx(13.0 / 15.3, rel=1e-15)
    s = analytic.rectangular_section(2e9, 0.25, 500.0, 0.4, 0.1)
    assert s.inertia == pytest.approx(0.4 * 0.1 ** 3 / 12, rel=1e-15)
    assert s.bending_stiffness == pytest.approx(2e9 * 0.4 * 0.1 ** 3 / 12, rel=1e-15)
    assert s.shear_stiffness == pytest.approx(12.5 / 14.75 * 2e9 / 2.5 * 0.04, rel=1e-15)
    assert (s.mass_per_length, s.rotary_inertia) == pytest.approx((20.0, 500.0 * 0.4 * 0.1 ** 3 / 12), rel=1e-15)
    with pytest.raises(tm.MaterialError, match="poisson"):
        analytic.cowper_shear_coefficient(0.5)
    with pytest.raises(ValueError, match="height"):
        analytic.rectangular_section(E, NU, RHO, 0.3, -0.2)


# ---------------------------------------------------------------------------------------------
# static deflection
# ---------------------------------------------------------------------------------------------


def unit_load_deflection(a, length, ei, kga, q, p, samples=2001):
    """w(a) by virtual work: integral of M m / EI + V v / kGA, with (m, v) = (a - x, 1) on [0, a]
    for a unit load at a and the real moment and shear M = q (L - x)^2 / 2 + P (L - x),
    V = q (L - x) + P. Composite Simpson, exact for these cubics."""
    x = np.linspace(0.0, a, samples)
    moment = q * (length - x) ** 2 / 2 + p * (length - x)
    shear = q * (length - x) + p
    integrand = moment * (a - x) / ei + (shear / kga if kga is not None else 0.0)
    h = x[1] - x[0]
    return h / 3 * (integrand[0] + integrand[-1] + 4 * integrand[1:-1:2].sum() + 2 * integrand[2:-1:2].sum())


@pytest.mark.parametrize("q,p", [(600.0, 0.0), (0.0, 250.0), (600.0, -90.0)])
def test_deflection_along_the_span_by_virtual_work(q, p):
    s = section()
    xs = np.array([0.0, 0.2, 0.55, 0.9, L])
    eb = analytic.euler_bernoulli_cantilever(xs, L, s.bending_stiffness, q, p)
    ti = analytic.timoshenko_cantilever(xs, L, s.bending_stiffness, s.shear_stiffness, q, p)
    for x, w_eb, w_ti in zip(xs, eb, ti):
        scale = abs(unit_load_deflection(L, L, s.bending_stiffness, s.shear_stiffness, q, p))
        assert w_eb == pytest.approx(unit_load_deflection(x, L, s.bending_stiffness, None, q, p), abs=1e-12 * scale)
        assert w_ti == pytest.approx(unit_load_deflection(x, L, s.bending_stiffness, s.shear_stiffness, q, p),
                                     abs=1e-12 * scale)
    tip = analytic.timoshenko_cantilever(L, L, s.bending_stiffness, s.shear_stiffness, q, p)
    assert isinstance(tip, float) and tip == pytest.approx(ti[-1])
    with pytest.raises(ValueError, match="span"):
        analytic.euler_bernoulli_cantilever(1.5, L, s.bending_stiffness, q)


def test_timoshenko_tends_to_euler_bernoulli_for_slender_beams():
    gaps = []
    for slenderness in (5, 50, 500):
        s = section(slenderness)
        q = s.mass_per_length * G
        eb = analytic.euler_bernoulli_cantilever(L, L, s.bending_stiffness, q)
        ti = analytic.timoshenko_cantilever(L, L, s.bending_stiffness, s.shear_stiffness, q)
        gaps.append(ti / eb - 1)
    assert gaps[0] > 0.03  # shear is visible in a stubby beam
    assert gaps[1] == pytest.approx(gaps[0] / 100, rel=1e-9) and gaps[2] == pytest.approx(gaps[0] / 1e4, rel=1e-9)


# ---------------------------------------------------------------------------------------------
# first bending frequency
# ---------------------------------------------------------------------------------------------


def test_beta1_is_the_first_clamped_free_root():
    lo, hi = 1.5, 2.5  # 1 + cos b cosh b changes sign once in here
    for _ in range(100):
        mid = 0.5 * (lo + hi)
        if (1 + math.cos(lo) * math.cosh(lo)) * (1 + math.cos(mid) * math.cosh(mid)) <= 0:
            hi = mid
        else:
            lo = mid
    assert analytic.BETA1_CLAMPED_FREE == pytest.approx(lo, rel=1e-14)
    s = section()
    f = analytic.euler_bernoulli_first_frequency(L, s.bending_stiffness, s.mass_per_length)
    assert f == pytest.approx(lo ** 2 / (2 * math.pi) * math.sqrt(E * HEIGHT ** 2 / (12 * RHO)), rel=1e-13)


def test_timoshenko_frequency_limits():
    s = section()
    eb = analytic.euler_bernoulli_first_frequency(L, s.bending_stiffness, s.mass_per_length)
    assert analytic.timoshenko_first_frequency(L, s.bending_stiffness, math.inf, s.mass_per_length) == \
        pytest.approx(eb, rel=1e-12)
    full = analytic.timoshenko_first_frequency(L, s.bending_stiffness, s.shear_stiffness, s.mass_per_length,
                                               s.rotary_inertia)
    shear_only = analytic.timoshenko_first_frequency(L, s.bending_stiffness, s.shear_stiffness, s.mass_per_length)
    rayleigh = analytic.timoshenko_first_frequency(L, s.bending_stiffness, math.inf, s.mass_per_length,
                                                   s.rotary_inertia)
    assert full < shear_only < rayleigh < eb  # each effect lowers the frequency
    gaps = []
    for slenderness in (5, 50, 500):
        t = section(slenderness)
        gaps.append(1 - analytic.timoshenko_first_frequency(L, t.bending_stiffness, t.shear_stiffness,
                                                            t.mass_per_length, t.rotary_inertia)
                    / analytic.euler_bernoulli_first_frequency(L, t.bending_stiffness, t.mass_per_length))
    assert gaps[0] > 0.02 and gaps[1] == pytest.approx(gaps[0] / 100, rel=0.1)  # ~ (h / L)^2
    assert gaps[2] == pytest.approx(gaps[1] / 100, rel=1e-3)


def timoshenko_fe_frequency(n, length, ei, kga, m, j):
    """First frequency (Hz) of n two-node Timoshenko elements (linear w and phi, one-point shear
    integration against locking, consistent mass), clamped at node 0: O(h^2)."""
    le = length / n
    k = np.zeros((2 * n + 2, 2 * n + 2))
    mass = np.zeros_like(k)
    shear = np.array([-1 / le, -0.5, 1 / le, -0.5])  # w' - phi at the element's midpoint
    pair = np.array([[2.0, 1.0], [1.0, 2.0]]) * le / 6
    for e in range(n):
        idx = np.arange(2 * e, 2 * e + 4)
        ke = kga * le * np.outer(shear, shear)
        ke[np.ix_([1, 3], [1, 3])] += ei / le * np.array([[1.0, -1.0], [-1.0, 1.0]])
        me = np.zeros((4, 4))
        me[np.ix_([0, 2], [0, 2])] = m * pair
        me[np.ix_([1, 3], [1, 3])] = j * pair
        k[np.ix_(idx, idx)] += ke
        mass[np.ix_(idx, idx)] += me
    k, mass = k[2:, 2:], mass[2:, 2:]
    # K^-1 M's largest eigenvalue is 1 / omega_1^2 (M is singular without rotary inertia; K is not)
    chol_inv = np.linalg.inv(np.linalg.cholesky(k))
    return 1.0 / math.sqrt(np.linalg.eigvalsh(chol_inv @ mass @ chol_inv.T)[-1]) / (2 * math.pi)


@pytest.mark.parametrize("rotary", [True, False])
def test_timoshenko_frequency_matches_a_beam_finite_element_model(rotary):
    s = section()  # L / h = 5: the correction is 2-3%, far above the tolerance
    j = s.rotary_inertia if rotary else 0.0
    exact = analytic.timoshenko_first_frequency(L, s.bending_stiffness, s.shear_stiffness, s.mass_per_length, j)
    coarse, fine = (timoshenko_fe_frequency(n, L, s.bending_stiffness, s.shear_stiffness, s.mass_per_length, j)
                    for n in (50, 100))
    assert fine / exact - 1 == pytest.approx((coarse / exact - 1) / 4, rel=0.01)  # O(h^2) towards `exact`
    assert (4 * fine - coarse) / 3 == pytest.approx(exact, rel=1e-7)


# ---------------------------------------------------------------------------------------------
# Richardson
# ---------------------------------------------------------------------------------------------


def test_richardson_recovers_a_known_sequence():
    hs = [0.5, 0.3, 0.2, 0.125]
    values = [2.0 + 3.0 * h ** 1.7 for h in hs]
    est = analytic.richardson(values, hs)
    assert est.value == pytest.approx(2.0, rel=1e-12) and est.order == pytest.approx(1.7, rel=1e-9)
    assert est.error_estimate == pytest.approx(3.0 * 0.125 ** 1.7, rel=1e-9)
    shuffled = analytic.richardson(values[::-1], hs[::-1])  # any order of refinements
    assert shuffled.value == pytest.approx(est.value, rel=1e-14)
    given = analytic.richardson([5.0 - 4.0 * h ** 2 for h in (0.4, 0.1)], [0.4, 0.1], order=2)
    assert (given.value, given.order) == pytest.approx((5.0, 2.0), rel=1e-13)


def test_richardson_refuses_what_it_cannot_extrapolate():
    with pytest.raises(ValueError, match="at least 3"):
        analytic.richardson([1.0, 2.0], [0.2, 0.1])
    with pytest.raises(ValueError, match="asymptotic"):
        analytic.richardson([1.0, 1.2, 1.1], [0.4, 0.2, 0.1])  # oscillating
    with pytest.raises(ValueError, match="distinct"):
        analytic.richardson([1.0, 1.2, 1.1], [0.4, 0.2, 0.2])
    with pytest.raises(ValueError, match="2 mesh sizes"):
        analytic.richardson([1.0, 1.2, 1.1], [0.4, 0.2])


# ---------------------------------------------------------------------------------------------
# the simulation approaches the reference
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("load", ["gravity", "tip"])
def test_cantilever_deflection_approaches_timoshenko(load):
    """P1 tets lock in bending: errors fall from ~40% (2 cells through the height) to ~9% (6 cells);
    the along-span profile follows Timoshenko's within the same bound."""
    s = section()
    tip_force = 300.0  # N, spread evenly over the tip face's nodes
    q = s.mass_per_length * G if load == "gravity" else 0.0
    p = 0.0 if load == "gravity" else tip_force
    errors = []
    for m in (1, 2, 3):
        mesh = tm.beam_mesh(10 * m, 3 * m, 2 * m, size=(L, WIDTH, HEIGHT), dtype=torch.float64)
        x = mesh.vertices[:, 0]
        tip = x > L - 1e-9
        external = torch.zeros_like(mesh.vertices)
        external[tip, 2] = -p / int(tip.sum())
        model = tm.TensorMass(mesh, tm.Material(E, NU, RHO))
        u = tm.solve_static(model, fixed=x < 1e-9, gravity=(0.0, 0.0, -G if q else 0.0), external=external, tol=1e-10)
        w_tip = -float(u[tip, 2].mean())
        exact = analytic.timoshenko_cantilever(L, L, s.bending_stiffness, s.shear_stiffness, q, p)
        errors.append(1 - w_tip / exact)
    assert 0 < errors[2] < errors[1] < errors[0]  # too stiff, improving
    assert errors[0] > 0.25 and errors[2] < 0.15
    for station in (0.3, 0.6):  # along the span, at the finest mesh
        w = -float(u[(x - station).abs() < 1e-9, 2].mean())
        exact = analytic.timoshenko_cantilever(station, L, s.bending_stiffness, s.shear_stiffness, q, p)
        assert 0 < 1 - w / exact < 0.2


# ---------------------------------------------------------------------------------------------
# benchmarks/studies/accuracy.py
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def accuracy():
    sys.path.insert(0, str(BENCH))
    try:
        import accuracy as module
    finally:
        sys.path.remove(str(BENCH))
    return module


def test_pareto_front_and_picks(accuracy):
    def rec(time_s, error, m):
        return dict(problem="static", family="mesh", model="hooke", dtype="float64", device="cpu", m=m,
                    elements=360 * m ** 3, tol=1e-8, time_s=time_s, rel_error=error)

    runs = [rec(1.0, 0.3, 1), rec(2.0, 0.5, 1), rec(3.0, 0.05, 2), rec(4.0, 0.004, 3), rec(5.0, 0.004, 4),
            rec(9.0, 0.0005, 5)]
    front = accuracy.pareto_front(runs)
    assert [r["m"] for r in front] == [1, 2, 3, 5]
    chosen = accuracy.picks(runs)["static"]
    assert [row["reached"] for row in chosen] == [True, True, False]
    assert chosen[0]["time_s"] == 4.0 and chosen[1]["time_s"] == 9.0 and chosen[2]["error"] == 0.0005
    assert "m = 3" in chosen[0]["settings"]


def test_fit_damped_mode_recovers_a_sampled_mode(accuracy):
    dt, frequency, decay = 0.01, 3.0, 0.8
    t = np.arange(40) * dt
    w = 1e-3 * decay ** (t * frequency) * np.sin(2 * math.pi * frequency * t)
    f, d, residual = accuracy.fit_damped_mode(w, dt)
    assert f == pytest.approx(frequency, rel=1e-10) and d == pytest.approx(decay, rel=1e-10) and residual < 1e-10
    noisy = w + 1e-3 * np.random.default_rng(0).standard_normal(w.size)
    assert accuracy.fit_damped_mode(noisy, dt)[0] is None  # not one damped mode: no frequency


def test_accuracy_script_quick(accuracy, tmp_path):
    solvers = "none,multigrid" if importlib.util.find_spec("pyamg") else "none"
    results = accuracy.main(["--quick", "--models", "hooke", "--dtypes", "float64", "--out", str(tmp_path),
                             "--solvers", solvers])
    data = json.loads((tmp_path / "accuracy.json").read_text())
    md = (tmp_path / "accuracy.md").read_text()
    assert "Which settings to pick" in md and "Pareto" in md
    assert (tmp_path / "accuracy.png").exists() or "not drawn" in md
    refs = data["meta"]["references"]
    assert refs["frequency_timoshenko_hz"] == pytest.approx(9.9123, rel=1e-4)
    static = sorted((r for r in results.records if r.get("problem") == "static" and r["family"] == "mesh"),
                    key=lambda r: r["m"])
    errors = [r["rel_error"] for r in static]
    assert len(errors) >= 3 and errors == sorted(errors, reverse=True)
    dynamic = [r for r in results.records if r.get("problem") == "dynamic" and r.get("value") is not None]
    assert dynamic
    for r in dynamic:
        if r["require_convergence"] and r["cg_tol"] <= 1e-6:
            # the measured frequency and decay are the integrator's exact ones for this mesh's mode
            integrator = r.get("integrator", "backward_euler")
            assert abs(r[f"{integrator}_check"]) < 1e-6
            assert r["decay_per_period"] == pytest.approx(r[f"decay_{integrator}"], rel=1e-5)
    assert {r.get("integrator") for r in dynamic} == {"backward_euler", "newmark"}
    assert set(data["meta"]["picks"]) == {"static", "frequency", "motion", "solver"}
    # the solver error: a budget's frequency against the same mesh and dt solved to convergence
    capped = [r for r in dynamic if r["family"].startswith("cg_cap")]
    assert capped and all(r["rel_error_solver"] >= 0 for r in capped)
    assert {r["family"] for r in capped} == {"cg_cap"} | ({"cg_cap multigrid"} if "multigrid" in solvers else set())
