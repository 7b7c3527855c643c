"""Accuracy against run time (issue 6): a cantilever's static deflection and its first bending
frequency, against references nobody can tune to, over the settings a user chooses.

    python benchmarks/studies/accuracy.py --out benchmarks/results/accuracy        # default: < 10 min, 2-core CPU
    python benchmarks/studies/accuracy.py --quick --out /tmp/acc                   # seconds
    python benchmarks/studies/accuracy.py --device cuda --out $OUT/accuracy --static-m 1,2,3,4,6,8,12 \
        --dynamic-m 1,2,3,4,6

The beam (``BEAM``): L = 1 m, width 0.3 m (y), height 0.2 m (z), E = 1e8 Pa, nu = 0.3,
rho = 1000 kg/m^3, clamped on its face x = 0; ``m`` refines it as 10m x 3m x 2m cubic cells x 6
tets (alternating cut). Gravity -9.81 z deflects the tip by 3.8 mm (0.4% of L: geometrically
linear, so hooke, stvk and corotational share one answer to ~1e-5). The section is wider than
tall so that the first mode (bending in z) is not degenerate with bending in y.

References (``tensormass_torch.physics.analytic``):
  static   tip deflection (mean of u_z over the tip face): Timoshenko (Cowper's shear
           coefficient) and the converged 3-D value, Richardson over the finest meshes of the
           hooke float64 "mesh" family (a clamped 3-D block differs from beam theory near the
           clamp, so the converged value, not Timoshenko, is what a fine mesh must reach).
  dynamic  first bending frequency: Timoshenko with rotary inertia, and the converged 3-D value,
           Richardson over the modal frequencies of the finest meshes (inverse iteration with
           solve_static, lumped mass, float64). Each mesh's own modal frequency separates the
           error of time stepping from the error of the mesh.

Static runs: ``tm.solve_static`` (Newton + CG; one CG for hooke). Dynamic runs: ``tm.Simulator``
without gravity, started with the velocity of the mesh's first mode (tip amplitude 1 mm), for
``--periods`` periods of dt = T / N (T the converged period); the frequency and the amplitude
decay per period come from a least-squares fit of w_{k+1} = a w_k + b w_{k-1} to the tip
displacement (Prony; exact for one damped mode sampled at any rate, where zero crossings of a
one-period record would resolve the period to a fraction of a step only). Implicit Euler damps:
its frequency is atan(omega dt) / dt and its decay per period (1 + omega^2 dt^2)^(-pi / atan(omega dt))
for a mode omega; both are in the json (``*_backward_euler``; Newmark's, atan(omega dt / 2) / (dt / 2) and
no decay, as ``*_newmark``) as a check of the measurement.

Families (one curve each, per model and dtype): static "mesh" (m), "tol" (Newton tolerance,
CG at tol / 10), "aspect" (cells 2x longer / shorter along x); dynamic "mesh N=..." (m at N
steps per period), "dt" (N), "cg_tol", "cg_cap" (a fixed CG budget, require_convergence=False,
SOFA's way), "newton" (iterations per step at a large step), "dt newmark" (N, with
``integrator="newmark"``: no numerical damping, ``--integrators``), and per solver of
``--solvers`` other than plain CG, "cg_tol <solver>" and "cg_cap <solver>" (multigrid
preconditioned, warm started: ``SOLVERS``). Time: the solve (static) or the
steps of one simulated period (dynamic), synchronised wall clock after a warm-up, the fastest of
up to 3 repeats for runs under 2 s; setup excluded.

Errors, all against the converged 3-D values: static |w / w_conv - 1|. Dynamic "frequency":
|mesh error| + |time-stepping error| (the mesh's modal frequency against the converged one, the
run's frequency against the mesh's modal one): the mesh makes the frequency too high and
implicit Euler too low, and their signed sum vanishes at some dt by coincidence; the sum of
magnitudes does not. Dynamic "motion": the larger of that and the amplitude lost per period.
"Solver error": a cg_tol or cg_cap run's frequency against the same mesh and dt solved to
convergence (the "dt" family): what the solver's settings cost, apart from mesh and time step.
A target below the reference's own uncertainty (how far Richardson's estimate moves when the
finest refinement is left out) is reported as not judgeable.

Writes accuracy.md (references, the settings to pick for 1%, 0.1%, 0.01%, the Pareto fronts,
every run), accuracy.json ({"meta", "references", "picks", "records"}) and accuracy.png (error
against time, log-log, Pareto fronts marked; skipped with a note when matplotlib is missing).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Optional, Sequence

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import numpy as np
import torch
from common import Budget, Results, metadata, record, release, sync

import tensormass_torch as tm
from tensormass_torch.physics import analytic


@dataclass(frozen=True)
class Beam:
    length: float = 1.0
    width: float = 0.3    # y
    height: float = 0.2   # z, the load direction
    young: float = 1e8
    poisson: float = 0.3
    density: float = 1000.0
    gravity: float = 9.81
    tip_amplitude: float = 1e-3  # m, of the dynamic runs

    def cells(self, m: int, aspect: float = 1.0):
        """(nx, ny, nz) of refinement m: cubic cells of L / (10 m), or cells ``aspect`` times
        longer along x."""
        return max(1, round(10 * m / aspect)), 3 * m, 2 * m

    def section(self) -> analytic.BeamSection:
        return analytic.rectangular_section(self.young, self.poisson, self.density, self.width, self.height)


BEAM = Beam()

# Per preset: the refinements and settings each family sweeps. "reference" meshes run only in
# hooke float64 (the converged values); the others for every model and dtype.
PRESETS = {
    "quick": dict(static_m=[1], static_ref_m=[1, 2, 3], static_tol_m=1, static_tols=[1e-2],
                  aspect_m=1, aspects=[2.0], modal_ref_m=[1, 2, 3], dynamic_m=[1, 2], dynamic_mesh_n=[8],
                  dyn_m=1, dyn_n=[8, 16], dyn_mid_n=8, cg_tols=[1e-2], cg_caps=[10],
                  newton_n=8, newtons=[2], periods=1.0, solver_caps={"multigrid": [1, 2]}),
    "default": dict(static_m=[1, 2, 3, 4, 6], static_ref_m=[1, 2, 3, 4, 6, 8, 10], static_tol_m=3,
                    static_tols=[1e-1, 1e-2, 1e-3, 1e-4, 1e-6], aspect_m=3, aspects=[2.0, 0.5],
                    modal_ref_m=[1, 2, 3, 4, 6, 8], dynamic_m=[1, 2, 3], dynamic_mesh_n=[16, 64],
                    dyn_m=2, dyn_n=[8, 16, 32, 64, 128], dyn_mid_n=32, cg_tols=[1e-1, 1e-2, 1e-3, 1e-4],
                    cg_caps=[5, 10, 20, 40], newton_n=8, newtons=[2, 3], periods=1.0,
                    solver_caps={"multigrid": [1, 2, 4, 8]}),
}

#: Newton tolerance of the static runs where the family does not sweep it, and the CG tolerance
#: of the dynamic runs: float32 cannot resolve a residual much below 1e-5 of the load; the
#: corotational tangent leaves out the rotations' derivative, so its Newton converges linearly.
STATIC_TOL = {("float64", "hooke"): 1e-10, ("float64", "stvk"): 1e-8, ("float64", "corotational"): 1e-6,
              ("float32", "hooke"): 1e-5, ("float32", "stvk"): 1e-5, ("float32", "corotational"): 1e-5}
DYNAMIC_CG_TOL = {"float64": 1e-6, "float32": 1e-5}
MAX_NEWTON = 8
TARGETS = (1e-2, 1e-3, 1e-4)
TITLE = "Accuracy against run time: cantilever statics and first frequency"

COLUMNS = [("problem", "problem", None), ("family", "family", None), ("model", "model", None),
           ("dtype", "dtype", None), ("m", "m", None), ("elements", "elements", ","),
           ("steps_per_period", "N=T/dt", None), ("tol", "tol", ".0e"), ("cg_tol", "CG tol", ".0e"),
           ("cg_max_iter", "CG cap", None), ("solver", "solver", None), ("newton_iters", "Newton", None),
           ("value", "value", ".6g"),
           ("rel_error", "error", ".2e"), ("rel_error_timoshenko", "vs Timoshenko", "+.2e"),
           ("rel_error_mesh", "mesh error", "+.2e"), ("rel_error_time", "time-stepping error", "+.2e"),
           ("amplitude_loss_per_period", "amplitude lost/period", ".2e"),
           ("rel_error_solver", "solver error", ".2e"), ("time_s", "time s", ".3f"),
           ("cg_iterations", "CG it", None)]


# ---------------------------------------------------------------------------------------------
# the cantilever
# ---------------------------------------------------------------------------------------------


def cantilever(m: int, dtype, device, aspect: float = 1.0):
    """(mesh, fixed [V] bool, tip [V] bool) of refinement m."""
    nx, ny, nz = BEAM.cells(m, aspect)
    mesh = tm.beam_mesh(nx, ny, nz, size=(BEAM.length, BEAM.width, BEAM.height), dtype=dtype, device=device)
    x = mesh.vertices[:, 0]
    half_cell = 0.5 * BEAM.length / nx  # node planes are a cell apart: robust in float32
    return mesh, x <= half_cell, x >= BEAM.length - half_cell


def material(model: str, rotation: str = "polar") -> tm.Material:
    return tm.Material(BEAM.young, BEAM.poisson, BEAM.density, model=model, rotation=rotation)


class CountingModel:
    """A ``TensorMass`` seen through ``solve_static``, counting its linearisations (Newton steps)
    and the products with them (CG iterations): solve_static reports neither."""

    def __init__(self, model):
        self.model = model
        self.linearisations = 0
        self.products = 0

    def __getattr__(self, name):
        return getattr(self.model, name)

    def __call__(self, x):
        return self.model(x)

    def tangent(self, x):
        self.linearisations += 1
        stiffness = self.model.tangent(x)

        def apply(dx):
            self.products += 1
            return stiffness(dx)

        return apply


def timed(fn, device, repeat_below_s: float = 2.0, repeats: int = 3):
    """(fn(), seconds): synchronised wall clock. A call shorter than ``repeat_below_s`` is run up
    to ``repeats`` times and the fastest kept: on a shared machine the minimum is the run the
    other processes disturbed least (``fn`` must start from the same state each time)."""
    best, out = math.inf, None
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        out = fn()
        sync(device)
        best = min(best, time.perf_counter() - start)
        if best >= repeat_below_s:
            break
    return out, best


# ---------------------------------------------------------------------------------------------
# static runs
# ---------------------------------------------------------------------------------------------


def static_run(model_name: str, dtype_name: str, device, m: int, tol: float, aspect: float = 1.0) -> dict:
    """Tip deflection of one static solve: a record (value in m, time in s)."""
    dtype = getattr(torch, dtype_name)
    mesh, fixed, tip = cantilever(m, dtype, device, aspect)
    model = CountingModel(tm.TensorMass(mesh, material(model_name)))
    rec = record(scene="cantilever", problem="static", model=model_name, kind="tet", elements=mesh.num_elements,
                 nodes=mesh.num_vertices, objects=1, backend=tm.backend_info().get(torch.device(device).type),
                 device=torch.device(device).type, dtype=dtype_name, m=m, cells=list(BEAM.cells(m, aspect)),
                 aspect=aspect, tol=tol, cg_tol=tol / 10.0, quantity="tip deflection (m)")
    def solve():
        model.linearisations = model.products = 0
        return tm.solve_static(model, fixed=fixed, gravity=(0.0, 0.0, -BEAM.gravity), tol=tol, max_newton=MAX_NEWTON)

    try:
        u, seconds = timed(solve, device)
    except tm.SolverError as exc:
        rec["error"] = common.error_text(exc)
        return rec
    rec.update(value=-float(u[tip, 2].double().mean()), time_s=seconds,
               newton_iters=model.linearisations or None, cg_iterations=model.products or None)
    return rec


def modal_frequency(m: int, device, tol: float = 1e-9, max_iter: int = 30):
    """First mode of refinement m (hooke, lumped mass, float64) by inverse iteration.

    Returns (frequency in Hz, mode [V, 3] with the tip's mean u_z = 1, seconds). Each iteration
    is one ``solve_static`` with the mass-weighted mode as load, phi <- K^-1 M phi; the Rayleigh
    quotient phi.K phi / phi.M phi converges with the square of (omega_1 / omega_2)^2 = 0.44^2
    per iteration (the second mode bends in y, 1.5x stiffer). Start: the gravity deflection.
    """
    mesh, fixed, tip = cantilever(m, torch.float64, device)
    model = tm.TensorMass(mesh, material("hooke"))
    mass = model.lumped_mass().unsqueeze(-1)
    free = ~fixed

    def solve(load):
        return tm.solve_static(model, fixed=fixed, gravity=(0.0, 0.0, 0.0), external=load, tol=1e-10)

    start = time.perf_counter()
    phi = solve(mass * torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64, device=device))
    previous = None
    for _ in range(max_iter):
        phi = phi / phi[tip, 2].mean()
        k_phi = -model.dforce(mesh.vertices, phi)
        omega_sq = float((phi * k_phi)[free].sum() / (mass * phi * phi)[free].sum())
        if previous is not None and abs(omega_sq - previous) <= tol * omega_sq:
            break
        previous = omega_sq
        phi = solve(mass * phi)
    return math.sqrt(omega_sq) / (2 * math.pi), phi.cpu(), time.perf_counter() - start


# ---------------------------------------------------------------------------------------------
# dynamic runs
# ---------------------------------------------------------------------------------------------


#: Largest relative residual of the two-term fit for a record to count as one damped mode.
FIT_TOLERANCE = 1e-2


def fit_damped_mode(signal: np.ndarray, dt: float):
    """(frequency Hz, amplitude decay per period, fit residual) of a sampled damped oscillation ``[K]``.

    Least squares of w_{k+1} = a w_k + b w_{k-1} over the record; the roots of z^2 - a z - b are
    the mode's per-step multipliers lambda: frequency arg(lambda) / (2 pi dt), decay per period
    |lambda|^(2 pi / arg(lambda)). The residual (relative to the record's norm) says whether the
    record is one damped mode at all; (None, None, residual) when it is not or does not oscillate.
    """
    w = np.asarray(signal, dtype=np.float64)
    if w.size < 5 or not np.all(np.isfinite(w)) or not np.any(w):
        return None, None, math.inf
    a_mat = np.stack([w[1:-1], w[:-2]], axis=1)
    (a, b), *_ = np.linalg.lstsq(a_mat, w[2:], rcond=None)
    residual = float(np.linalg.norm(a_mat @ np.array([a, b]) - w[2:]) / np.linalg.norm(w[2:]))
    roots = np.roots([1.0, -a, -b])
    lam = roots[np.argmax(np.abs(np.angle(roots)))]
    angle = abs(float(np.angle(lam)))
    if angle == 0.0 or residual > FIT_TOLERANCE:
        return None, None, residual
    return angle / (2 * math.pi * dt), float(abs(lam) ** (2 * math.pi / angle)), residual


def backward_euler_mode(frequency: float, dt: float):
    """(frequency Hz, decay per period) of implicit Euler on an undamped mode of ``frequency``:
    per step lambda = 1 / (1 - i omega dt)."""
    omega_dt = 2 * math.pi * frequency * dt
    angle = math.atan(omega_dt)
    return angle / (2 * math.pi * dt), (1.0 + omega_dt ** 2) ** (-math.pi / angle)


def newmark_mode(frequency: float, dt: float):
    """(frequency Hz, decay per period) of Newmark's average acceleration on an undamped mode of
    ``frequency``: per step lambda = (1 + i omega dt / 2) / (1 - i omega dt / 2), |lambda| = 1."""
    return math.atan(math.pi * frequency * dt) / (math.pi * dt), 1.0


#: ``integrator`` -> its exact (frequency, decay per period) on an undamped mode
EXACT_MODES = {"backward_euler": backward_euler_mode, "newmark": newmark_mode}


def dynamic_run(model_name: str, dtype_name: str, device, m: int, steps_per_period: int, period: float,
                mode_shape: torch.Tensor, mode_frequency: float, periods: float, cg_tol: float,
                cg_max_iter: int = 1000, newton_iters: int = 1, require_convergence: bool = True,
                integrator: str = "backward_euler", solver: str = "none") -> dict:
    """Free vibration from the first mode's velocity: a record (value: frequency in Hz).
    ``solver``: the CG's preconditioner, "+warm" for warm starts (``SOLVERS``)."""
    dtype = getattr(torch, dtype_name)
    mesh, fixed, tip = cantilever(m, torch.float64, "cpu")
    dt = period / steps_per_period
    velocity = (2 * math.pi * mode_frequency * BEAM.tip_amplitude) * mode_shape
    rec = record(scene="cantilever", problem="dynamic", model=model_name, kind="tet", elements=mesh.num_elements,
                 nodes=mesh.num_vertices, objects=1, backend=tm.backend_info().get(torch.device(device).type),
                 device=torch.device(device).type, dtype=dtype_name, m=m, cells=list(BEAM.cells(m)),
                 steps_per_period=steps_per_period, dt=dt, cg_tol=cg_tol, cg_max_iter=cg_max_iter,
                 newton_iters=newton_iters, require_convergence=require_convergence, integrator=integrator,
                 solver=solver, quantity="frequency (Hz)")
    preconditioner, _, warm = solver.partition("+")
    sim = tm.Simulator([tm.Body(mesh, material(model_name), fixed=fixed, velocity=velocity)], dt=dt,
                       gravity=(0.0, 0.0, 0.0), cg_tol=cg_tol, cg_max_iter=cg_max_iter,
                       require_convergence=require_convergence, newton_iters=newton_iters, device=device,
                       dtype=dtype, integrator=integrator, preconditioner=preconditioner, warm_start=warm == "warm")
    tip = tip.to(sim.device)
    steps = max(int(math.ceil(periods * steps_per_period)), 6)
    samples = [torch.zeros((), dtype=dtype, device=sim.device)]
    iterations = torch.zeros((), dtype=torch.long, device=sim.device)

    def run():
        nonlocal iterations
        samples[1:] = []
        iterations = torch.zeros((), dtype=torch.long, device=sim.device)
        sim.x, sim.v = start_x, start_v  # each repeat starts from the same state
        for _ in range(steps):  # no host synchronisation inside the loop
            report = sim.step(1)
            iterations = iterations + report.cg_iterations.sum()
            samples.append(sim.displacements(0)[tip, 2].mean())

    start_x, start_v = sim.x.clone(), sim.v.clone()
    try:
        # set-up off the clock: a first step builds what the steps keep (the multigrid's
        # hierarchy, captured graphs); run() starts again from the initial state
        sim.step(1)
        _, seconds = timed(run, device)
    except tm.SolverError as exc:
        rec["error"] = common.error_text(exc)
        return rec
    signal = torch.stack(samples).double().cpu().numpy()
    frequency, decay, residual = fit_damped_mode(signal, dt)
    exact_frequency, exact_decay = EXACT_MODES[integrator](mode_frequency, dt)
    rec.update(steps=steps, time_s=seconds, time_per_period_s=seconds * steps_per_period / steps,
               cg_iterations=int(iterations), mode_frequency_hz=mode_frequency, fit_residual=residual,
               **{f"frequency_{integrator}_hz": exact_frequency, f"decay_{integrator}": exact_decay})
    if frequency is None:
        rec["error"] = f"the tip's motion is not one damped oscillation (fit residual {residual:.1e})"
        return rec
    # rel_error_time: what time stepping costs on this mesh; <integrator>_check: the fit against
    # the integrator's exact answer for this mesh's mode (~0 unless the CG tolerance shows).
    rec.update(value=frequency, decay_per_period=decay, rel_error_time=frequency / mode_frequency - 1.0,
               **{f"{integrator}_check": frequency / exact_frequency - 1.0})
    return rec


# ---------------------------------------------------------------------------------------------
# analysis: Pareto fronts and the settings to pick
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Criterion:
    """One way of judging runs: which problem, which record field is the error, in words."""

    name: str
    problem: str
    field: str
    title: str
    time_unit: str


CRITERIA = (
    Criterion("static", "static", "rel_error", "Static tip deflection", "s per solve"),
    Criterion("frequency", "dynamic", "rel_error", "First bending frequency (|mesh error| + |time-stepping error|)",
              "s per simulated period"),
    Criterion("motion", "dynamic", "rel_error_motion",
              "One period of motion: max(frequency error, amplitude lost per period)", "s per simulated period"),
    Criterion("solver", "dynamic", "rel_error_solver",
              "Solver error: frequency against the same mesh and dt solved to convergence", "s per simulated period"),
)


#: ``--solvers``: the preconditioner, with "+warm" for warm starts
SOLVERS = ("none", "none+warm", "multigrid", "multigrid+warm")


def solver_errors(records: Sequence[dict], model: str, dtype: str) -> None:
    """Each dynamic run's solver error ``rel_error_solver``: |its frequency / the frequency of the
    same mesh and dt solved to convergence (the "dt" family's run) - 1|: what the CG tolerance or
    budget (and the solver) costs, apart from the mesh and the time step. Set on the runs of the
    cg_tol and cg_cap families of ``model`` and ``dtype`` (in place)."""
    converged = {(r["m"], r["steps_per_period"]): r["value"] for r in records
                 if r.get("problem") == "dynamic" and r.get("family") == "dt" and r.get("value") is not None
                 and (r["model"], r["dtype"]) == (model, dtype)}
    for r in records:
        if (r.get("problem") == "dynamic" and (r["model"], r["dtype"]) == (model, dtype) and r.get("value") is not None
                and str(r.get("family", "")).startswith(("cg_tol", "cg_cap"))):
            reference = converged.get((r["m"], r["steps_per_period"]))
            if reference is not None:
                r["rel_error_solver"] = abs(r["value"] / reference - 1.0)


def cost(rec: dict) -> Optional[float]:
    """The time a record is judged by: the solve (static), one simulated period (dynamic)."""
    return rec.get("time_per_period_s") if rec.get("problem") == "dynamic" else rec.get("time_s")


def measured(records: Sequence[dict], criterion: Criterion) -> List[dict]:
    return [r for r in records if r.get("problem") == criterion.problem and r.get(criterion.field) is not None
            and cost(r) is not None and r.get("family") != "reference"]


def pareto_front(records: Sequence[dict], field: str = "rel_error", margin: float = 1e-3) -> List[dict]:
    """Records no faster record matches in ``field`` (within a relative ``margin``: a run that
    is slower for an error smaller in the fourth digit is not a choice), by increasing time ``[k]``."""
    front, best = [], math.inf
    for r in sorted(records, key=lambda r: (cost(r), r[field])):
        if r[field] < best * (1.0 - margin):
            front.append(r)
            best = r[field]
    return front


def settings_text(r: dict) -> str:
    cells = f"{r['elements']:,} tets" + (f", cells {r['aspect']:g}x long" if r.get("aspect", 1.0) != 1.0 else "")
    parts = [f"{r['model']} {r['dtype']} on {r['device']}", f"m = {r['m']} ({cells})"]
    if r["problem"] == "static":
        parts.append(f"tol {r['tol']:.0e}")
    else:
        parts.append(f"dt = T/{r['steps_per_period']}")
        parts.append(f"CG tol {r['cg_tol']:.0e}" if r.get("require_convergence", True)
                     else f"a fixed {r['cg_max_iter']} CG iterations")
        if r.get("newton_iters", 1) > 1:
            parts.append(f"{r['newton_iters']} Newton iterations")
        if r.get("integrator", "backward_euler") != "backward_euler":
            parts.append(r["integrator"])
        if r.get("solver", "none") != "none":
            parts.append(f"CG with {r['solver']}")
    return ", ".join(parts)


def picks(records: Sequence[dict], uncertainty: Optional[Dict[str, float]] = None) -> Dict[str, List[dict]]:
    """Per criterion and target: the fastest run within the target, or else the most accurate run.

    ``uncertainty``: per problem, the relative uncertainty of the converged reference; a target
    below it cannot be judged (``resolvable`` False), whatever the runs say.
    """
    out = {}
    for criterion in CRITERIA:
        runs = measured(records, criterion)
        floor = (uncertainty or {}).get(criterion.problem, 0.0)
        rows = []
        for target in TARGETS:
            within = [r for r in runs if r[criterion.field] <= target]
            best = min(within, key=cost) if within else min(runs, key=lambda r: r[criterion.field], default=None)
            if best is not None:
                rows.append({"target": target, "reached": bool(within), "resolvable": target > floor,
                             "reference_uncertainty": floor, "settings": settings_text(best),
                             "error": best[criterion.field], "time_s": cost(best)})
        out[criterion.name] = rows
    return out


def picks_paragraph(chosen: Dict[str, List[dict]]) -> List[str]:
    lines = ["## Which settings to pick", "",
             "Computed by the script from the runs below: for each target, the fastest run whose error against "
             "the converged 3-D value is within it, on this machine (another device moves the times, not the errors)."]
    for criterion in CRITERIA:
        rows = chosen.get(criterion.name) or []
        if rows:
            lines += ["", f"{criterion.title}:"]
        for row in rows:
            if not row["resolvable"]:
                lines.append(f"- {row['target']:.2%}: cannot be judged here: the converged reference itself is only "
                             f"known to {row['reference_uncertainty']:.1e} (finer reference meshes needed).")
            elif row["reached"]:
                lines.append(f"- {row['target']:.2%}: {row['settings']} (error {row['error']:.1e}, "
                             f"{row['time_s']:.3g} {criterion.time_unit}).")
            else:
                lines.append(f"- {row['target']:.2%}: not reached by these runs; the most accurate was "
                             f"{row['settings']} (error {row['error']:.1e}, {row['time_s']:.3g} "
                             f"{criterion.time_unit})" + (f"; predicted to reach it: {row['prediction']} "
                                                          "(extrapolated from the references, not run)."
                                                          if row.get("prediction") else "."))
    return lines


# ---------------------------------------------------------------------------------------------
# the plot
# ---------------------------------------------------------------------------------------------


def draw(records: Sequence[dict], meta: dict):
    def figure(plt):
        fig, axes = plt.subplots(1, len(CRITERIA), figsize=(7 * len(CRITERIA), 9.5))
        colors = {"hooke": "tab:blue", "stvk": "tab:orange", "corotational": "tab:green"}
        styles = {"float64": "-", "float32": ":"}
        markers = "osD^v<>pP*Xh"
        for ax, criterion in zip(axes, CRITERIA):
            runs = measured(records, criterion)
            families = sorted({r["family"] for r in runs})

            def error(r):
                return max(r[criterion.field], 1e-12)  # an exact zero would vanish from a log axis

            for key in sorted({(r["model"], r["dtype"], r["family"]) for r in runs}):
                model, dtype, family = key
                series = sorted((r for r in runs if (r["model"], r["dtype"], r["family"]) == key), key=cost)
                ax.plot([cost(r) for r in series], [error(r) for r in series], linestyle=styles.get(dtype, "-"),
                        color=colors.get(model, "grey"), marker=markers[families.index(family) % len(markers)],
                        markersize=4, linewidth=1, label=f"{model} {dtype} {family}")
            front = pareto_front(runs, criterion.field)
            if front:
                ax.plot([cost(r) for r in front], [error(r) for r in front], color="black", drawstyle="steps-post",
                        linewidth=2, alpha=0.4)
                ax.scatter([cost(r) for r in front], [error(r) for r in front], s=110, facecolors="none",
                           edgecolors="black", linewidths=1.5, zorder=5, label="Pareto front")
            for target in TARGETS:
                ax.axhline(target, color="grey", linewidth=0.6, linestyle="--")
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.xaxis.set_minor_formatter(plt.NullFormatter())  # minor labels overlap on short ranges
            ax.set_xlabel(criterion.time_unit)
            ax.set_ylabel("relative error")
            ax.set_title(criterion.title, fontsize=10)
            ax.grid(True, which="both", alpha=0.2)
            ax.legend(fontsize=5, ncol=3, loc="upper center", bbox_to_anchor=(0.5, -0.12))  # below: data stay visible
        fig.suptitle(common.plot_title(meta, "Cantilever: error against run time (against the converged 3-D value)"))
        return fig

    return figure


# ---------------------------------------------------------------------------------------------
# the sweep
# ---------------------------------------------------------------------------------------------


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", default="benchmarks/results/accuracy")
    p.add_argument("--quick", action="store_true", help="tiny meshes: seconds on a CPU")
    p.add_argument("--models", default="hooke,stvk,corotational")
    p.add_argument("--dtypes", default="float64,float32")
    p.add_argument("--problems", default="static,dynamic")
    p.add_argument("--integrators", default="backward_euler,newmark",
                   help="the dynamic 'dt' family's integrators (StepOptions.integrator)")
    p.add_argument("--solvers", default="none",
                   help="the dynamic cg_tol and cg_cap families' solvers: none, multigrid, and either with '+warm' "
                        "(warm starts); each other than none adds families '<family> <solver>'")
    p.add_argument("--static-m", default=None, help="refinements of the static mesh family (comma list)")
    p.add_argument("--dynamic-m", default=None, help="refinements of the dynamic mesh families (comma list)")
    p.add_argument("--family-m", type=int, default=None,
                   help="refinement of the dynamic dt, cg_tol, cg_cap and newton families' mesh (2; a GPU: 6)")
    p.add_argument("--periods", type=float, default=None, help="simulated periods per dynamic run (1)")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--budget-s", type=float, default=None, help="wall-clock limit: later runs are skipped")
    p.add_argument("--replot", action="store_true", help="only rebuild md/png from the json under --out")
    return p.parse_args(argv)


def ints(text: Optional[str], default: Sequence[int]) -> List[int]:
    return list(default) if text is None else [int(v) for v in text.split(",") if v]


def main(argv=None):
    args = parse_args(argv)
    if args.replot:
        return replot(args.out)
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    size = dict(PRESETS["quick" if args.quick else "default"])
    size["static_m"] = ints(args.static_m, size["static_m"])
    size["dynamic_m"] = ints(args.dynamic_m, size["dynamic_m"])
    if args.family_m:
        size["dyn_m"] = args.family_m
    if args.periods:
        size["periods"] = args.periods
    models = [m for m in args.models.split(",") if m]
    dtypes = [d for d in args.dtypes.split(",") if d]
    integrators = [i for i in args.integrators.split(",") if i]
    solvers = [v for v in args.solvers.split(",") if v]
    for solver in solvers:
        if solver not in SOLVERS:
            raise SystemExit(f"accuracy.py: unknown solver {solver!r} in --solvers; known: {', '.join(SOLVERS)}")
    problems = [p for p in args.problems.split(",") if p]
    budget = Budget(args.budget_s)
    started = time.perf_counter()
    meta = metadata(device, beam=BEAM.__dict__, preset="quick" if args.quick else "default", sizes=size)
    results = Results(args.out, "accuracy", TITLE, meta, COLUMNS)

    section = BEAM.section()
    q = section.mass_per_length * BEAM.gravity
    references = {
        "static_euler_bernoulli_m": analytic.euler_bernoulli_cantilever(BEAM.length, BEAM.length,
                                                                          section.bending_stiffness, q),
        "static_timoshenko_m": analytic.timoshenko_cantilever(BEAM.length, BEAM.length, section.bending_stiffness,
                                                              section.shear_stiffness, q),
        "frequency_euler_bernoulli_hz": analytic.euler_bernoulli_first_frequency(
            BEAM.length, section.bending_stiffness, section.mass_per_length),
        "frequency_timoshenko_hz": analytic.timoshenko_first_frequency(
            BEAM.length, section.bending_stiffness, section.shear_stiffness, section.mass_per_length,
            section.rotary_inertia),
    }
    meta["references"] = references

    def add(rec: dict, family: str, reference: Optional[float], timoshenko: float):
        rec["family"] = family
        rec["threads"] = torch.get_num_threads()
        if rec.get("value") is not None and reference is not None:
            rec["rel_error_signed"] = rec["value"] / reference - 1.0
            rec["rel_error"] = abs(rec["rel_error_signed"])
            rec["reference"] = "converged 3-D (Richardson)"
            if rec["problem"] == "dynamic":
                # The mesh makes the frequency too high, implicit Euler too low: they cancel at
                # some dt for this mode only. The error a setting is judged by is their sum in
                # magnitude, which no such coincidence makes small.
                rec["rel_error_mesh"] = rec["mode_frequency_hz"] / reference - 1.0
                rec["rel_error"] = abs(rec["rel_error_mesh"]) + abs(rec["rel_error_time"])
                rec["amplitude_loss_per_period"] = 1.0 - rec["decay_per_period"]
                # Implicit Euler's damping is part of what a user sees after a period; a capped CG
                # barely moves and so barely damps, with the frequency far off: judge both at once.
                rec["rel_error_motion"] = max(rec["rel_error"], abs(rec["amplitude_loss_per_period"]))
        if rec.get("value") is not None:
            rec["rel_error_timoshenko"] = rec["value"] / timoshenko - 1.0
        results.add(rec, echo=False)
        print(f"[{time.perf_counter() - started:6.1f}s] {rec['problem']:7s} {family:12s} {rec['model']:12s} "
              f"{rec['dtype']} m={rec['m']} value={rec.get('value')} err={rec.get('rel_error')} "
              f"t={rec.get('time_s')} {rec.get('error') or ''}", flush=True)

    def skip(problem, family, model, dtype, m, why):
        results.add(record(problem=problem, family=family, model=model, dtype=dtype, m=m, skipped=why), echo=False)

    # Warm-up (untimed): the first solve and step of a process pay for loading and caches.
    for model, dtype in sorted({(m, d) for m in models for d in dtypes} | {("hooke", "float64")}):
        if True:
            mesh, fixed, _ = cantilever(1, getattr(torch, dtype), device)
            try:
                tm.solve_static(tm.TensorMass(mesh, material(model)), fixed=fixed, tol=1e-3, max_newton=2)
            except tm.SolverError:
                pass
            tm.Simulator([tm.Body(mesh, material(model), fixed=fixed)], dt=1e-3).step(2)

    # --- static -------------------------------------------------------------------------------
    if "static" in problems:
        tip_timoshenko = references["static_timoshenko_m"]
        ref_runs = []
        for m in sorted(set(size["static_ref_m"]) | set(size["static_m"])):
            ref_runs.append(static_run("hooke", "float64", device, m, STATIC_TOL[("float64", "hooke")]))
        estimate, uncertainty = converged({r["m"]: r["value"] for r in ref_runs})
        references["static_values_m"] = {str(r["m"]): r["value"] for r in ref_runs}
        references.update(static_converged_m=estimate.value, static_richardson_order=estimate.order,
                          static_richardson_error_estimate=estimate.error_estimate,
                          static_reference_uncertainty=uncertainty,
                          static_richardson_m=[r["m"] for r in ref_runs[-3:]])
        print(f"static reference: converged {estimate.value:.8g} m (order {estimate.order:.2f}), Timoshenko "
              f"{tip_timoshenko:.8g} m", flush=True)
        tip_ref = estimate.value
        for r in ref_runs:
            if "hooke" in models and "float64" in dtypes:
                add(r, "mesh", tip_ref, tip_timoshenko)
            else:
                add(r, "reference", tip_ref, tip_timoshenko)
        for model in models:
            for dtype in dtypes:
                tol = STATIC_TOL[(dtype, model)]
                failed = None  # a failed solve is not retried on larger meshes: it would fail slower
                tight = {}  # m -> the tight-tolerance value of this model and dtype
                if (model, dtype) == ("hooke", "float64"):
                    tight = {r["m"]: r["value"] for r in ref_runs}
                for m in size["static_m"]:
                    if (model, dtype) == ("hooke", "float64"):
                        continue  # run as the reference above
                    if budget.remaining() <= 0 or failed:
                        skip("static", "mesh", model, dtype, m, failed or "budget spent")
                        continue
                    rec = static_run(model, dtype, device, m, tol)
                    add(rec, "mesh", tip_ref, tip_timoshenko)
                    tight[m] = rec.get("value")
                    if rec.get("error"):
                        failed = f"m = {m} failed ({rec['error'][:60]}...)"
                for t in size["static_tols"]:
                    if t < tol or budget.remaining() <= 0 or failed:
                        continue
                    rec = static_run(model, dtype, device, size["static_tol_m"], t)
                    if rec.get("value") is not None and tight.get(size["static_tol_m"]):
                        rec["rel_error_solver"] = rec["value"] / tight[size["static_tol_m"]] - 1.0
                    add(rec, "tol", tip_ref, tip_timoshenko)
                for aspect in size["aspects"]:
                    if budget.remaining() <= 0 or failed:
                        continue
                    add(static_run(model, dtype, device, size["aspect_m"], tol, aspect), "aspect", tip_ref,
                        tip_timoshenko)
            release(device)

    # --- dynamic ------------------------------------------------------------------------------
    if "dynamic" in problems:
        freq_timoshenko = references["frequency_timoshenko_hz"]
        modes = {}
        modal_m = sorted(set(size["modal_ref_m"]) | set(size["dynamic_m"]) | {size["dyn_m"]})
        for m in modal_m:
            frequency, shape, seconds = modal_frequency(m, device)
            modes[m] = (frequency, shape)
            print(f"mode 1 of m={m}: {frequency:.8g} Hz ({seconds:.1f} s)", flush=True)
        estimate, uncertainty = converged({m: modes[m][0] for m in modal_m})
        freq_ref = estimate.value
        references.update(frequency_converged_hz=freq_ref, frequency_richardson_order=estimate.order,
                          frequency_richardson_error_estimate=estimate.error_estimate,
                          frequency_reference_uncertainty=uncertainty,
                          frequency_richardson_m=modal_m[-3:],
                          modal_frequency_hz={str(m): modes[m][0] for m in modal_m})
        print(f"dynamic reference: converged {freq_ref:.8g} Hz (order {estimate.order:.2f}), Timoshenko "
              f"{freq_timoshenko:.8g} Hz", flush=True)
        period = 1.0 / freq_ref
        for model in models:
            for dtype in dtypes:
                cg_tol = DYNAMIC_CG_TOL[dtype]
                runs = []  # (family, m, N, cg_tol, cap, newton, require_convergence, integrator, solver)
                for n in size["dynamic_mesh_n"]:
                    runs += [(f"mesh N={n}", m, n, cg_tol, 1000, 1, True, "backward_euler", "none")
                             for m in size["dynamic_m"]]
                for integrator in integrators:
                    runs += [("dt" if integrator == "backward_euler" else f"dt {integrator}", size["dyn_m"], n, cg_tol,
                              1000, 1, True, integrator, "none") for n in size["dyn_n"]]
                for solver in solvers:
                    suffix = "" if solver == "none" else f" {solver}"
                    caps = size["cg_caps"] if solver == "none" else size["solver_caps"][solver.partition("+")[0]]
                    runs += [("cg_tol" + suffix, size["dyn_m"], size["dyn_mid_n"], t, 1000, 1, True, "backward_euler",
                              solver) for t in size["cg_tols"] if t > cg_tol]
                    runs += [("cg_cap" + suffix, size["dyn_m"], size["dyn_mid_n"], 0.0, c, 1, False, "backward_euler",
                              solver) for c in caps]
                runs += [("newton", size["dyn_m"], size["newton_n"], cg_tol, 1000, k, True, "backward_euler", "none")
                         for k in size["newtons"]]
                for family, m, n, tol, cap, newton, require, integrator, solver in runs:
                    if budget.remaining() <= 0:
                        skip("dynamic", family, model, dtype, m, "budget spent")
                        continue
                    rec = dynamic_run(model, dtype, device, m, n, period, modes[m][1], modes[m][0],
                                      size["periods"], tol, cap, newton, require, integrator, solver)
                    add(rec, family, freq_ref, freq_timoshenko)
                solver_errors(results.records, model, dtype)
                release(device)

    meta["references"] = references
    summarise(results)
    print(f"total {time.perf_counter() - started:.1f} s", flush=True)
    return results


def summarise(results: Results) -> None:
    """The md's sections (references, picks, predictions, fronts), the json's picks, the plot."""
    references = results.meta["references"]
    chosen = picks(results.records, {"static": references.get("static_reference_uncertainty") or 0.0,
                                     "dynamic": references.get("frequency_reference_uncertainty") or 0.0})
    for name, rows in chosen.items():
        for row in rows:
            if not row["reached"] and row["resolvable"]:
                row["prediction"] = predict(name, row["target"], references)
    results.meta["picks"] = chosen
    notes = reference_notes(references) + [""] + picks_paragraph(chosen) + [""] + front_notes(results.records)
    notes += ["", "## Runs", "", "error: |value / converged - 1|; vs Timoshenko: signed value / Timoshenko - 1; "
              "time-stepping error: the frequency against the same mesh's modal frequency; time s: the whole run "
              "(dynamic: `periods` periods; the plot and the picks use s per simulated period)."]
    results.notes = notes
    results.plot(draw(results.records, results.meta))
    results.finish()


def replot(out) -> Results:
    """Rebuild accuracy.md / .png (and the json's picks) from the accuracy.json under ``out``."""
    data = json.loads((Path(out) / "accuracy.json").read_text())
    results = Results(out, "accuracy", TITLE, data["meta"], COLUMNS)
    results.records = data["records"]
    refs = results.meta["references"]
    if "static_converged_m" in refs and "static_values_m" not in refs:  # written by an earlier version
        refs["static_values_m"] = {str(r["m"]): r["value"] for r in results.records
                                   if r.get("problem") == "static" and (r["model"], r["dtype"], r["family"])
                                   == ("hooke", "float64", "mesh") and r.get("value") is not None}
    summarise(results)
    return results


def predict(criterion: str, target: float, refs: dict) -> Optional[str]:
    """Settings that would reach ``target``, from the measured references only (no run): the mesh
    error of refinement m extrapolated as e_finest (m_finest / m)^order, the time-stepping error
    and damping of implicit Euler from its exact response to the mode (checked against every
    dynamic run: ``backward_euler_check``). The mesh gets half of the error budget."""
    if criterion == "static" and "static_converged_m" in refs:
        m_f = max(int(k) for k in refs["static_values_m"])
        e_f = abs(refs["static_values_m"][str(m_f)] / refs["static_converged_m"] - 1.0)
        m = math.ceil(m_f * (e_f / target) ** (1.0 / refs["static_richardson_order"]))
        return f"m = {m} ({360 * m ** 3:,} tets)"
    if criterion in ("frequency", "motion") and "frequency_converged_hz" in refs:
        modal = {int(k): v for k, v in refs["modal_frequency_hz"].items()}
        conv, order = refs["frequency_converged_hz"], refs["frequency_richardson_order"]
        m_f = max(modal)
        e_f = abs(modal[m_f] / conv - 1.0)
        m = next(m for m in range(1, 10_000) if (modal[m] / conv - 1.0 if m in modal
                                                  else e_f * (m_f / m) ** order) <= 0.5 * target)
        mesh_error = abs(modal[m] / conv - 1.0) if m in modal else e_f * (m_f / m) ** order
        f_m = conv * (1.0 + mesh_error)

        def ok(n):
            frequency, decay = backward_euler_mode(f_m, 1.0 / (conv * n))
            error = mesh_error + abs(frequency / f_m - 1.0)
            return max(error, 1.0 - decay) <= target if criterion == "motion" else error <= target

        n = 4
        while not ok(n):
            n = math.ceil(n * 1.05)
        return f"m = {m} ({360 * m ** 3:,} tets) with dt = T/{n}"
    return None


def converged(values_by_m: Dict[int, float]):
    """(Richardson estimate over the three finest refinements, relative uncertainty or None).

    The uncertainty is how far the estimate moves when the three refinements before the finest
    are used instead (needs four): an extrapolation is only as good as the asymptotic range.
    """
    ms = sorted(values_by_m)
    estimate = analytic.richardson([values_by_m[m] for m in ms[-3:]], [1.0 / m for m in ms[-3:]])
    if len(ms) < 4:
        return estimate, None
    try:
        previous = analytic.richardson([values_by_m[m] for m in ms[-4:-1]], [1.0 / m for m in ms[-4:-1]])
    except ValueError:  # not yet asymptotic one refinement earlier
        return estimate, abs(estimate.error_estimate / estimate.value)
    return estimate, abs(previous.value / estimate.value - 1.0)


def reference_notes(refs: dict) -> List[str]:
    lines = ["## The beam and its references", "",
             f"Cantilever L = {BEAM.length} m, {BEAM.width} m wide (y) x {BEAM.height} m high (z), "
             f"E = {BEAM.young:g} Pa, nu = {BEAM.poisson}, rho = {BEAM.density:g} kg/m^3, clamped at x = 0; "
             "refinement m: 10m x 3m x 2m cubic cells x 6 tets. Static: gravity -z, the mean u_z of the tip face. "
             "Dynamic: free vibration from the first mode's velocity, no gravity, tip amplitude 1 mm.", ""]
    if "static_converged_m" in refs:
        lines.append(f"- Static tip deflection: Euler-Bernoulli {refs['static_euler_bernoulli_m']:.6e} m, Timoshenko "
                     f"{refs['static_timoshenko_m']:.6e} m (Cowper kappa), converged 3-D "
                     f"{refs['static_converged_m']:.6e} m "
                     f"(Richardson over m = {refs['static_richardson_m']}, observed order "
                     f"{refs['static_richardson_order']:.2f}, error left in the finest mesh "
                     f"{refs['static_richardson_error_estimate'] / refs['static_converged_m']:.1e}, uncertainty "
                     f"{uncertainty_text(refs.get('static_reference_uncertainty'))}); the converged 3-D "
                     f"value is {refs['static_converged_m'] / refs['static_timoshenko_m'] - 1:+.2%} from Timoshenko's.")
    if "frequency_converged_hz" in refs:
        lines.append(f"- First bending frequency: Euler-Bernoulli {refs['frequency_euler_bernoulli_hz']:.6f} Hz, "
                     f"Timoshenko with rotary inertia {refs['frequency_timoshenko_hz']:.6f} Hz, converged 3-D "
                     f"{refs['frequency_converged_hz']:.6f} Hz (Richardson of the modal frequencies over m = "
                     f"{refs['frequency_richardson_m']}, observed order {refs['frequency_richardson_order']:.2f}, "
                     f"uncertainty {uncertainty_text(refs.get('frequency_reference_uncertainty'))}); "
                     "the converged 3-D value is "
                     f"{refs['frequency_converged_hz'] / refs['frequency_timoshenko_hz'] - 1:+.2%} from Timoshenko's. "
                     "Modal frequency per m: "
                     + ", ".join(f"{k}: {v:.5f} Hz" for k, v in refs["modal_frequency_hz"].items()) + ".")
    return lines


def uncertainty_text(value: Optional[float]) -> str:
    if value is None:
        return "unknown (three refinements)"
    return f"{value:.1e} (the estimate's move from one refinement fewer)"


def front_notes(records: Sequence[dict]) -> List[str]:
    lines = ["## Pareto fronts", "", "Runs no other run beats on both time and error, fastest first."]
    for criterion in CRITERIA:
        front = pareto_front(measured(records, criterion), criterion.field)
        if front:
            lines += ["", f"{criterion.title}:"]
            lines += [f"- {r[criterion.field]:.1e} in {cost(r):.3g} {criterion.time_unit}: {settings_text(r)}"
                      for r in front]
    return lines


if __name__ == "__main__":
    main()
