"""Stability on stiff and extreme cases (issue 6): a sweep of scenes, each run to its end or to
its first failed step, with a table of outcomes; and what a minimal scene allocates against a
full-featured one.

    python benchmarks/studies/stability.py --out benchmarks/results/stability            # < 10 min, 2-core CPU
    python benchmarks/studies/stability.py --quick --out /tmp/stability                  # about a minute
    python benchmarks/studies/stability.py --device cuda --dtype float32 --out $OUT/stability

Cases (``CASES``; every one with hooke, stvk and corotational unless said):
  young        E = 1e2 .. 1e10 Pa (nu 0.3, dt 0.01 s)
  poisson      nu = 0 .. 0.499 (E 1e6 Pa)
  dt           dt = 1e-5 .. 0.1 s (E 1e6 Pa)
  mass_ratio   density 1 and 1e6 kg/m^3 on the two halves of one beam (ratio 1e6)
      (these four: a beam 1 x 0.2 x 0.2 m clamped at x = 0, no gravity, started with the
      velocity v_z = v0 (x / L)^2, v0 = 0.02 sqrt(E / rho) (a tip swing of ~0.1 L))
  rotation     a free beam spinning about z through 180 deg in 1 s (a rigid motion)
  compression  the far end of the clamped beam pushed to x = L (1 - c) along a smooth ramp,
               c = 0.5, 0.9 and 1.2 (through the clamp: inversion is forced); also stvk with
               ``tangent="definite"`` (row "stvk-definite": the positive semi-definite tangent)
  free_fall    a cube dropped from 0.5 m onto a penalty plane (k = 1e4 N/m per node)
  long_run     10,000 steps of a small cantilever under gravity (memory at start and end)
A case that fails is run again with ``substeps_on_failure=4`` (a record "+substeps"): the
effect of adaptive sub-stepping.

Measured (every step): total energy (kinetic + elastic + gravity + plane penalty), the volume
ratio of each body (sum of signed tet volumes / rest), the smallest element volume ratio and
the inverted elements (``tensormass_torch.sim.diagnostics``), CG iterations. Reported:
  energy_drift   (E_end - E_0) / E_ref, E_ref = the largest kinetic + elastic energy of the run
                 (implicit Euler dissipates: negative drift is its numerical damping)
  energy_gain    max_t (E_t - E_0) / E_ref: energy created (> 0 only when unstable)
  volume_error   max_t |volume ratio - 1|
Outcome: "failed" when a step raised SolverError (CG breakdown, not converged within the cap,
NaN/inf) or the state went non-finite; "degraded" when the run finished but energy_gain > 1%,
volume_error > 5% (cases where the volume should be kept), or an element inverted; "stable"
otherwise. Energy is not judged where prescribed motion does work (compression).

Footprint (``footprint.md``/``.json``): bytes per element of the model's buffers, of the
solver's per-step buffers and of the state (``tensormass_torch.sim.diagnostics.allocations``) and
time per step at a fixed CG budget, for a minimal scene (one hooke tet body, no damping, no
planes) and a full-featured one (stvk + corotational + membrane + planes + damping + prescribed).

Writes stability.md, stability.json, stability.png (outcome map, when matplotlib imports),
footprint.md, footprint.json under --out.
"""
from __future__ import annotations

import argparse
import gc
import math
import os
import sys
import time
from pathlib import Path
from typing import Dict, List, Optional

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # common, measure
import common  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.sim.diagnostics import InversionCheck, allocation_summary  # noqa: E402

MODELS = ("hooke", "stvk", "corotational")
#: Row order of the outcome map: the models, then stvk with its positive semi-definite tangent.
VARIANTS = MODELS + ("stvk-definite",)


def material(variant: str, **params) -> "tm.Material":
    """``"stvk-definite"``: stvk with ``tangent="definite"``; otherwise the model of that name
    with its exact tangent (the paper's stvk: the row the definite one is compared with)."""
    if variant == "stvk-definite":
        return tm.Material(model="stvk", tangent="definite", **params)
    return tm.Material(model=variant, tangent="exact", **params)
LENGTH, SIDE = 1.0, 0.2
RHO = 1000.0

COLUMNS = [
    ("case", "case", None), ("parameter", "parameter", None), ("value", "value", "g"), ("model", "model", None),
    ("outcome", "outcome", None), ("steps_done", "steps", "d"), ("energy_drift", "energy drift", "+.3g"),
    ("energy_gain", "energy gain", ".2g"), ("volume_error", "volume error", ".3g"),
    ("min_volume_ratio", "min element ratio", "+.3g"), ("inverted_max", "inverted", "d"),
    ("cg_mean", "CG its/step", ".1f"), ("cg_max", "CG max", "d"), ("substep_steps", "sub-stepped", "d"),
    ("wall_s", "wall s", ".2f"),
]

FOOTPRINT_COLUMNS = [
    ("scene", "scene", None), ("elements", "elements", "d"), ("nodes", "nodes", "d"),
    ("model_bytes_per_element", "model B/elem", ".1f"), ("solver_bytes_per_element", "solver B/elem", ".1f"),
    ("state_bytes_per_element", "state B/elem", ".1f"), ("total_bytes_per_element", "total B/elem", ".1f"),
    ("groups", "groups", None), ("ms_per_step", "ms/step", ".3f"), ("us_per_element_step", "us/(element step)", ".2f"),
    ("cg_iterations", "CG its/step", "d"),
]


# ---------------------------------------------------------------------------------------------
# scenes
# ---------------------------------------------------------------------------------------------


def beam(device, dtype, cells=(6, 2, 2)):
    return tm.beam_mesh(*cells, size=(LENGTH, SIDE, SIDE), origin=(0.0, -SIDE / 2, -SIDE / 2), dtype=dtype,
                        device=device)


def swinging_beam(model, device, dtype, young=1e6, poisson=0.3, dt=0.01, density=RHO, cells=(6, 2, 2), **sim_kw):
    """The clamped beam, no gravity, started with v_z = v0 (x / L)^2, v0 = 0.02 sqrt(E / rho_mean)."""
    mesh = beam(device, dtype, cells)
    rho_mean = float(torch.as_tensor(density, dtype=torch.float64).mean())
    v0 = 0.02 * math.sqrt(young / rho_mean)
    x = mesh.vertices
    velocity = torch.zeros_like(x)
    velocity[:, 2] = v0 * (x[:, 0] / LENGTH) ** 2
    body = tm.Body(mesh, material(model, young=young, poisson=poisson, density=density), fixed=x[:, 0] <= 1e-9,
                   velocity=velocity, name="beam")
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), device=device, dtype=dtype, **sim_kw)


def spinning_beam(model, device, dtype, steps=100, dt=0.01, **sim_kw):
    mesh = tm.beam_mesh(10, 1, 1, size=(LENGTH, 0.1, 0.1), origin=(-LENGTH / 2, -0.05, -0.05), dtype=dtype,
                        device=device)
    omega = math.pi / (steps * dt)
    x = mesh.vertices
    velocity = torch.stack((-omega * x[:, 1], omega * x[:, 0], torch.zeros_like(x[:, 2])), dim=1)
    body = tm.Body(mesh, material(model, young=5e6, poisson=0.3, density=RHO), velocity=velocity)
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), device=device, dtype=dtype, **sim_kw)


def smooth_ramp(s: float) -> float:
    s = min(max(s, 0.0), 1.0)
    return s - math.sin(2.0 * math.pi * s) / (2.0 * math.pi)


def compressed_beam(model, device, dtype, squeeze=0.5, steps=100, dt=0.01, **sim_kw):
    """The clamped beam's far face pushed to x = L (1 - squeeze) over 80% of the run, then held."""
    mesh = beam(device, dtype)
    x = mesh.vertices
    far = x[:, 0] >= LENGTH - 1e-9
    start = x[far].clone()
    ramp = 0.8 * steps * dt

    def motion(t):
        goal = start.clone()
        goal[:, 0] = LENGTH * (1.0 - squeeze * smooth_ramp(t / ramp))
        return goal

    body = tm.Body(mesh, material(model, young=1e6, poisson=0.3, density=RHO), fixed=x[:, 0] <= 1e-9,
                   prescribed=far, motion=motion, name="beam")
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, 0.0), rayleigh_mass=1.0, device=device, dtype=dtype,
                        **sim_kw)


def falling_cube(model, device, dtype, dt=0.01, **sim_kw):
    mesh = tm.beam_mesh(2, 2, 2, size=(0.2, 0.2, 0.2), origin=(-0.1, -0.1, 0.5), dtype=dtype, device=device)
    body = tm.Body(mesh, material(model, young=1e6, poisson=0.3, density=RHO), name="cube")
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, -9.81), planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)],
                        device=device, dtype=dtype, **sim_kw)


def long_cantilever(model, device, dtype, dt=0.01, **sim_kw):
    """A 24-tet cantilever sagging under gravity (tip deflection ~0.4 L) and swinging, undamped."""
    mesh = beam(device, dtype, cells=(4, 1, 1))
    body = tm.Body(mesh, material(model, young=1e6, poisson=0.3, density=RHO),
                   fixed=mesh.vertices[:, 0] <= 1e-9, name="beam")
    return tm.Simulator([body], dt=dt, gravity=(0.0, 0.0, -9.81), device=device, dtype=dtype, **sim_kw)


# ---------------------------------------------------------------------------------------------
# one run, measured
# ---------------------------------------------------------------------------------------------


def total_energy(sim, rest) -> float:
    """Kinetic + elastic + gravity (against the rest positions) + plane penalty energy (J)."""
    energy = sim.kinetic_energy().sum() + sim.model.energy(sim.x)
    energy = energy - (sim.system.external * (sim.x - rest)).sum()
    if sim.planes is not None:
        pen = sim.planes.penetration(sim.x)
        energy = energy + 0.5 * (sim.planes.stiffness * pen * pen).sum()
    return float(energy)


def motion_energy(sim) -> float:
    return float(sim.kinetic_energy().sum() + sim.model.energy(sim.x))


def rss_mib() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def run_case(sim, steps: int, judge_energy: bool = True, judge_volume: bool = True, memory: bool = False,
             deadline: Optional[float] = None) -> Dict[str, object]:
    """Run ``steps`` steps (or until ``deadline``, time.monotonic()), measuring every step."""
    check = InversionCheck.for_simulator(sim)
    rest = sim.model.rest
    e0 = total_energy(sim, rest)
    energies, e_ref = [e0], motion_energy(sim)
    volume_error, min_ratio, inverted_max, penetration = 0.0, 1.0, 0, 0.0
    cg_total, cg_max, substep_steps = 0, 0, 0
    out: Dict[str, object] = {"error": None}
    if memory:
        gc.collect()
        out["rss_start_mib"] = rss_mib()
        if sim.device.type == "cuda":
            out["cuda_allocated_start_mib"] = torch.cuda.memory_allocated(sim.device) / 2**20
    common.sync(sim.device)
    start = time.perf_counter()
    done = 0
    try:
        for _ in range(steps):
            report = sim.step()
            done += 1
            its = int(report.cg_iterations.max())
            cg_total += its
            cg_max = max(cg_max, its)
            substep_steps += int(report.substeps > 1)
            inv = check(sim.x)
            volume_error = max(volume_error, float((inv.volume_ratio - 1.0).abs().max()))
            min_ratio = min(min_ratio, float(inv.min_ratio.min()))
            inverted_max = max(inverted_max, int(inv.inverted.sum()))
            energies.append(total_energy(sim, rest))
            e_ref = max(e_ref, motion_energy(sim))
            if sim.planes is not None:
                penetration = max(penetration, float(sim.planes.penetration(sim.x).max()))
            if not math.isfinite(energies[-1]):
                out["error"] = "non-finite energy"
                break
            if deadline is not None and time.monotonic() > deadline:
                out["note"] = f"stopped by the time budget after {done} of {steps} steps"
                break
    except tm.SolverError as exc:
        out["error"] = common.error_text(exc)
    common.sync(sim.device)
    wall = time.perf_counter() - start
    if memory:
        gc.collect()
        out["rss_end_mib"] = rss_mib()
        if sim.device.type == "cuda":
            out["cuda_allocated_end_mib"] = torch.cuda.memory_allocated(sim.device) / 2**20
    e_ref = max(e_ref, 1e-300)
    drift = (energies[-1] - e0) / e_ref if len(energies) > 1 else None
    gain = max(max(e - e0 for e in energies) / e_ref, 0.0)
    out.update(steps_done=done, steps=steps, wall_s=wall, energy_drift=drift if judge_energy else None,
               energy_gain=gain if judge_energy else None, volume_error=volume_error, min_volume_ratio=min_ratio,
               inverted_max=inverted_max, cg_mean=cg_total / done if done else None, cg_max=cg_max,
               substep_steps=substep_steps, energy_start=e0, energy_ref=e_ref,
               max_penetration_m=penetration if sim.planes is not None else None)
    if out["error"]:
        out["outcome"] = "failed"
    else:
        reasons = []
        if judge_energy and gain > 0.01:
            reasons.append(f"energy gain {gain:.2g}")
        if judge_volume and volume_error > 0.05:
            reasons.append(f"volume error {volume_error:.2g}")
        if inverted_max > 0:
            reasons.append(f"{inverted_max} inverted")
        out["outcome"] = "degraded" if reasons else "stable"
        if sim.planes is not None:
            reasons.append(f"max penetration {penetration:.3g} m")
        if memory:
            reasons.append(f"RSS {out['rss_start_mib']:.1f} -> {out['rss_end_mib']:.1f} MiB")
            if "cuda_allocated_start_mib" in out:
                reasons.append(f"CUDA allocated {out['cuda_allocated_start_mib']:.2f} -> "
                               f"{out['cuda_allocated_end_mib']:.2f} MiB")
        if out.get("note"):
            reasons.append(out["note"])
        if reasons:
            out["note"] = "; ".join(reasons)
    return out


# ---------------------------------------------------------------------------------------------
# the sweep
# ---------------------------------------------------------------------------------------------


def cases(quick: bool) -> List[dict]:
    """Every run: case, parameter, value, model, builder(model, device, dtype, **sim_kw), steps,
    judge_energy, judge_volume."""
    steps = 12 if quick else 50
    models = MODELS
    young = (1e2, 1e6, 1e10) if quick else (1e2, 1e4, 1e6, 1e8, 1e10)
    poisson = (0.0, 0.45, 0.499) if quick else (0.0, 0.3, 0.45, 0.49, 0.499)
    dts = (1e-5, 1e-2, 1e-1) if quick else (1e-5, 1e-4, 1e-3, 1e-2, 1e-1)
    out = []
    for m in models:
        for e in young:
            out.append(dict(case="young", parameter="E Pa", value=e, model=m, steps=steps,
                            build=lambda m, d, t, e=e, **kw: swinging_beam(m, d, t, young=e, **kw)))
    for m in models:
        for nu in poisson:
            out.append(dict(case="poisson", parameter="nu", value=nu, model=m, steps=steps,
                            build=lambda m, d, t, nu=nu, **kw: swinging_beam(m, d, t, poisson=nu, **kw)))
    for m in models:
        for h in dts:
            out.append(dict(case="dt", parameter="dt s", value=h, model=m, steps=steps,
                            build=lambda m, d, t, h=h, **kw: swinging_beam(m, d, t, dt=h, **kw)))

    def two_densities(m, d, t, **kw):
        mesh = beam(d, t)
        centres = mesh.vertices[mesh.elements].mean(1)[:, 0]
        density = torch.where(centres > LENGTH / 2, torch.tensor(1e6, dtype=t), torch.tensor(1.0, dtype=t))
        return swinging_beam(m, d, t, density=density.to(t), **kw)

    for m in models:
        out.append(dict(case="mass_ratio", parameter="rho ratio", value=1e6, model=m, steps=steps, build=two_densities))
    spin_steps = 25 if quick else 100
    for m in models:
        out.append(dict(case="rotation", parameter="deg turned", value=180, model=m, steps=spin_steps,
                        build=lambda m, d, t, **kw: spinning_beam(m, d, t, steps=spin_steps, **kw)))
    squeeze_steps = 25 if quick else 100
    for m in models + ("stvk-definite",):  # the definite tangent: what it changes where stvk breaks down
        for c in ((0.5, 1.2) if quick else (0.5, 0.9, 1.2)):
            out.append(dict(case="compression", parameter="squeeze", value=c, model=m, steps=squeeze_steps,
                            judge_energy=False, judge_volume=False,
                            build=lambda m, d, t, c=c, **kw: compressed_beam(m, d, t, squeeze=c, steps=squeeze_steps,
                                                                             **kw)))
    fall_steps = 40 if quick else 100
    for m in models:
        out.append(dict(case="free_fall", parameter="drop m", value=0.5, model=m, steps=fall_steps,
                        build=falling_cube))
    long_steps = 1000 if quick else 10000
    for m in ("corotational",) if quick else models:
        out.append(dict(case="long_run", parameter="steps", value=long_steps, model=m, steps=long_steps,
                        build=long_cantilever, memory=True))
    return out


def run_sweep(args, results: common.Results, budget: common.Budget):
    dtype = getattr(torch, args.dtype)
    todo = cases(args.quick)
    for i, c in enumerate(todo):
        base = dict(case=c["case"], parameter=c["parameter"], value=c["value"], model=c["model"], dtype=args.dtype,
                    device=str(args.device))
        if budget.remaining() <= 0:
            results.add(common.record(**base, skipped="time budget spent"))
            continue
        # the long runs get what they need; the others share what is left fairly
        share = budget.share(len(todo) - i)
        variants = [("", {})]
        for label, extra in variants:  # a failure appends the sub-stepping retry to this list
            sim_kw = dict(cg_tol=args.cg_tol, cg_max_iter=args.cg_max_iter, **extra)
            try:
                sim = c["build"](c["model"], args.device, dtype, **sim_kw)
            except tm.TensorMassError as exc:
                results.add(common.record(**base, outcome="failed", error=common.error_text(exc)))
                continue
            deadline = None if c.get("memory") else time.monotonic() + max(share.remaining(), 1.0)
            measured = run_case(sim, c["steps"], c.get("judge_energy", True), c.get("judge_volume", True),
                                memory=c.get("memory", False), deadline=deadline)
            mat = sim.bodies[0].material
            rec = common.record(**base, elements=sum(b.mesh.num_elements for b in sim.bodies),
                                nodes=sim.model.num_nodes,
                                young=float(torch.as_tensor(mat.young, dtype=torch.float64).mean()),
                                poisson=float(torch.as_tensor(mat.poisson, dtype=torch.float64).mean()),
                                density=float(torch.as_tensor(mat.density, dtype=torch.float64).mean()),
                                dt=sim.options.dt,
                                substeps_on_failure=sim.substeps_on_failure, **measured)
            rec["case"] = c["case"] + label
            results.add(rec)
            if measured["outcome"] == "failed" and not label:
                variants.append(("+substeps", {"substeps_on_failure": 4}))
            common.release(args.device)


# ---------------------------------------------------------------------------------------------
# footprint: a minimal scene against a full-featured one
# ---------------------------------------------------------------------------------------------


def minimal_scene(device, dtype, cells):
    mesh = beam(device, dtype, cells)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=RHO, model="hooke"),
                   fixed=mesh.vertices[:, 0] <= 1e-9)
    return tm.Simulator([body], dt=0.01, device=device, dtype=dtype, cg_tol=0.0, cg_max_iter=20,
                        require_convergence=False, check_every=1000)


def full_scene(device, dtype, cells):
    """The same beam twice (stvk with its far end prescribed, corotational) plus a corotational
    membrane of about as many triangles, Rayleigh damping and a floor."""
    mesh = beam(device, dtype, cells)
    x = mesh.vertices
    far = x[:, 0] >= LENGTH - 1e-9
    start = x[far].clone()
    sheet = tm.beam_tri_mesh(cells[0] * 2, cells[1] * 2, size=(LENGTH, SIDE), dim=3, dtype=dtype, device=device)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, 0.0, 0.5], dtype=dtype, device=device), sheet.elements)
    bodies = [
        tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=RHO, model="stvk"), fixed=x[:, 0] <= 1e-9,
                prescribed=far, motion=lambda t: start + 0.01 * t),
        tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=RHO, model="corotational"), fixed=x[:, 0] <= 1e-9),
        tm.Body(sheet, tm.Material(young=1e5, poisson=0.3, density=RHO, model="corotational", thickness=0.01),
                fixed=sheet.vertices[:, 0] <= 1e-9),
    ]
    return tm.Simulator(bodies, dt=0.01, device=device, dtype=dtype, rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                        planes=[tm.Plane((0.0, 0.0, 1.0), -0.3, 1e4)], cg_tol=0.0, cg_max_iter=20,
                        require_convergence=False, check_every=1000)


def run_footprint(args, results: common.Results):
    dtype = getattr(torch, args.dtype)
    cells = (8, 2, 2) if args.quick else (20, 4, 4)
    for name, build in (("minimal", minimal_scene), ("full", full_scene)):
        sim = build(args.device, dtype, cells)
        sim.step(2)  # the solver's buffers exist after a first step
        parts = allocation_summary(sim)
        elements = sum(b.mesh.num_elements for b in sim.bodies)
        seconds, n = common.time_steps(sim.step, args.device, steps=args.footprint_steps, max_seconds=10.0)
        groups = ", ".join(f"{g.kind}/{g.model}/{g.form}" for g in sim.model.groups)
        results.add(common.record(scene=name, elements=elements, nodes=sim.model.num_nodes, dtype=args.dtype,
                                  device=str(args.device), steps=n, ms_per_step=1e3 * seconds,
                                  us_per_element_step=1e6 * seconds / elements,
                                  cg_iterations=common.last_cg_iterations(sim), groups=groups,
                                  model_bytes_per_element=parts["model"] / elements,
                                  solver_bytes_per_element=parts["solver"] / elements,
                                  state_bytes_per_element=parts["state"] / elements,
                                  total_bytes_per_element=sum(parts.values()) / elements, bytes=parts))


# ---------------------------------------------------------------------------------------------


def draw(records, meta):
    def fig_fn(plt):
        shown = [r for r in records if r.get("outcome") and not r["case"].endswith("+substeps")]
        names = list(dict.fromkeys(r["case"] for r in shown))
        fig, axes = plt.subplots(1, len(names), figsize=(2.6 * len(names), 3.2), squeeze=False)
        colors = {"stable": "tab:green", "degraded": "tab:orange", "failed": "tab:red"}
        for ax, name in zip(axes[0], names):
            rows = [r for r in shown if r["case"] == name]
            values = list(dict.fromkeys(r["value"] for r in rows))
            for r in rows:
                ax.scatter(values.index(r["value"]), VARIANTS.index(r["model"]), s=160, c=colors[r["outcome"]],
                           edgecolors="k")
            ax.set_xticks(range(len(values)))
            ax.set_xticklabels([format(v, "g") for v in values], rotation=45, fontsize=7)
            ax.set_yticks(range(len(VARIANTS)))
            ax.set_yticklabels(VARIANTS if ax is axes[0][0] else [], fontsize=8)
            ax.set_ylim(-0.6, len(VARIANTS) - 0.4)
            ax.set_title(f"{name}\n({rows[0]['parameter']})", fontsize=9)
        for label, c in colors.items():
            axes[0][-1].scatter([], [], c=c, label=label, edgecolors="k")
        axes[0][-1].legend(fontsize=7, loc="center left", bbox_to_anchor=(1.0, 0.5))
        fig.suptitle(common.plot_title(meta, "Stability: outcome per case and model"), fontsize=9)
        fig.tight_layout()
        return fig
    return fig_fn


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cpu")
    p.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    p.add_argument("--out", default="benchmarks/results/stability")
    p.add_argument("--quick", action="store_true", help="fewer values and steps (about a minute on a CPU)")
    p.add_argument("--budget-s", type=float, default=None, help="wall-clock limit of the sweep (default: none)")
    p.add_argument("--cg-tol", type=float, default=1e-8)
    p.add_argument("--cg-max-iter", type=int, default=2000, help="CG cap per solve: above it a step fails")
    p.add_argument("--footprint-steps", type=int, default=200)
    p.add_argument("--no-footprint", action="store_true")
    args = p.parse_args(argv)

    meta = common.metadata(args.device, dtype=args.dtype, quick=args.quick, cg_tol=args.cg_tol,
                           cg_max_iter=args.cg_max_iter)
    notes = [
        "Each run goes to its last step or its first failed step; measured after every step: total energy "
        "(kinetic + elastic + gravity + plane penalty), each body's volume ratio (sum of signed tet volumes / "
        "rest), the smallest element volume ratio and the inverted elements (tensormass_torch.sim.diagnostics), "
        f"CG iterations (tolerance {args.cg_tol:g}, cap {args.cg_max_iter}: above it a step fails).",
        "",
        "- energy drift: (E_end - E_0) / E_ref, E_ref the largest kinetic + elastic energy of the run "
        "(implicit Euler dissipates: a negative drift is its numerical damping, -1 = everything damped out)",
        "- energy gain: max over the run of (E_t - E_0) / E_ref: energy created (> 0 only when something is "
        "unstable)",
        "- volume error: max over the run of |V / V0 - 1|; min element ratio: the smallest element volume / "
        "rest (< 0: inverted); inverted: the most elements inverted at once",
        "- CG its/step: mean over the steps (CG max: the largest); sub-stepped: steps that needed sub-steps",
        "- outcome: failed = a step raised SolverError (CG breakdown, not converged within the cap, NaN/inf); "
        "degraded = the run finished but energy gain > 1%, volume error > 5% (where volume should be kept) "
        "or an element inverted; stable otherwise. Energy and volume are not judged where prescribed motion "
        "works on the body (compression)",
        "- a failed case is run again with substeps_on_failure=4 (case '+substeps'): the effect of adaptive "
        "sub-stepping",
        "",
        "Scenes (benchmarks/studies/stability.py docstring): young/poisson/dt/mass_ratio: a 144-tet beam "
        "1 x 0.2 x 0.2 m "
        "clamped at x = 0, no gravity, started swinging (tip speed 0.02 sqrt(E / rho)); rotation: a free "
        "40-tet beam spinning 180 deg in 1 s; compression: the clamped beam's far face pushed to "
        "x = L (1 - squeeze) over 0.8 s (mass damping 1/s); free_fall: a 48-tet cube dropped 0.5 m onto a plane "
        "(k = 1e4 N/m per node); long_run: a 24-tet cantilever under gravity, undamped, dt 0.01 s.",
    ]
    results = common.Results(args.out, "stability", "Stability on stiff and extreme cases", meta, COLUMNS, notes)
    budget = common.Budget(args.budget_s)
    run_sweep(args, results, budget)
    results.plot(draw(results.records, meta))
    results.finish()
    if not args.no_footprint:
        footprint = common.Results(args.out, "footprint", "Leave out what a scene does not need: bytes and time",
                                   meta, FOOTPRINT_COLUMNS, [
                                       "minimal: one hooke tet body (clamped), no damping, no planes, no prescribed "
                                       "nodes. full: the same beam as stvk (far end prescribed) and as corotational, "
                                       "a corotational membrane, Rayleigh damping, a floor plane. Bytes per element "
                                       "(all bodies' elements) of every tensor the simulator holds after a step "
                                       "(tensormass_torch.sim.diagnostics.allocations): model = rest, masses and the "
                                       "element groups (buffers, gather plans, the extension's cached int32 indices "
                                       "and Lame parameters); solver = system and CG buffers; state = x, v, masks. "
                                       "Time per step at a fixed budget of 20 CG iterations."])
        run_footprint(args, footprint)
        footprint.finish()


if __name__ == "__main__":
    main()
