"""Defaults against stiff and extreme materials: does a simulator built with nothing but defaults
run every case to its end with converged steps?

Two studies, every simulator on its defaults (CG tolerance 1e-6 with the automatic cap, stvk on
the definite tangent, require_convergence on, so no step passes unconverged):

* ``table``: a 1 m x 0.1 m x 0.1 m beam (20 x 2 x 2 cells, 480 tets) clamped at x = 0 under
  gravity, 100 steps, for rubber (E 5 MPa; nu 0.45, 0.49, 0.499), soft tissue (nu 0.45; E 1e3,
  1e4, 1e5 Pa) and steel (E 200 GPa, nu 0.3, rho 7850) x hooke, stvk, corotational x dt 1e-4,
  1e-2, 5e-2 s. Per cell: steps done, CG iterations per step (mean, max), time per step.
* ``paper_beam``: the paper's beam (``tensormass run paper_beam``), stvk, 150 steps: per step the
  energy (kinetic + elastic + gravity's potential), inverted elements and CG iterations.

    python benchmarks/studies/robustness.py --out benchmarks/results/robustness            # CPU, float32
    python benchmarks/studies/robustness.py --only paper_beam --resolution 4 --device cuda --out DIR

``tests/solver/test_stiff_and_extreme_defaults.py`` runs the table in CI and asserts that every cell completes.
"""
from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import torch

import tensormass_torch as tm
from tensormass_torch.sim.builtin import paper_beam
from tensormass_torch.sim.diagnostics import inversion_report

#: The table's materials: name -> Material keyword arguments (besides the model).
MATERIALS = {
    "rubber nu 0.45": dict(young=5e6, poisson=0.45, density=1100.0),
    "rubber nu 0.49": dict(young=5e6, poisson=0.49, density=1100.0),
    "rubber nu 0.499": dict(young=5e6, poisson=0.499, density=1100.0),
    "tissue E 1e3": dict(young=1e3, poisson=0.45, density=1000.0),
    "tissue E 1e4": dict(young=1e4, poisson=0.45, density=1000.0),
    "tissue E 1e5": dict(young=1e5, poisson=0.45, density=1000.0),
    "steel E 2e11": dict(young=2e11, poisson=0.3, density=7850.0),
}
MODELS = ("hooke", "stvk", "corotational")
DTS = (1e-4, 1e-2, 5e-2)


def table_cell(material: str, model: str, dt: float, steps: int = 100, device="cpu", dtype=torch.float32) -> dict:
    """One cell of the table: the clamped beam on defaults for ``steps`` steps of ``dt``."""
    mesh = tm.beam_mesh(20, 2, 2, size=(1.0, 0.1, 0.1), dtype=dtype, device=device)
    body = tm.Body(mesh, tm.Material(model=model, **MATERIALS[material]), fixed=mesh.vertices[:, 0] <= 1e-6)
    sim = tm.Simulator([body], dt=dt)
    iterations, error, converged = [], "", True
    start = time.perf_counter()
    try:
        for _ in range(steps):
            report = sim.step()
            iterations.append(int(report.cg_iterations.max()))
            converged &= all(bool(r.converged.all()) for r in report.cg)
    except tm.SolverError as exc:
        error = str(exc)
    seconds = time.perf_counter() - start
    done = sim.steps_done
    return {"material": material, "model": model, "dt": dt, "steps": steps, "done": done, "converged": converged,
            "cg_mean": sum(iterations) / max(len(iterations), 1), "cg_max": max(iterations, default=0),
            "ms_per_step": 1e3 * seconds / max(done, 1), "tip_z": float(sim.positions(0)[:, 2].min()),
            "cg_max_iter": sim.options.cg_max_iter, "error": error}


def run_table(steps=100, device="cpu", dtype=torch.float32, materials=MATERIALS, models=MODELS, dts=DTS):
    return [table_cell(m, model, dt, steps, device, dtype) for m in materials for model in models for dt in dts]


def table_markdown(rows) -> str:
    lines = ["| material | model | dt 1e-4: CG it mean/max, ms/step | dt 1e-2 | dt 5e-2 |", "|---|---|---|---|---|"]
    cells = {(r["material"], r["model"], r["dt"]): r for r in rows}
    for material in dict.fromkeys(r["material"] for r in rows):
        for model in dict.fromkeys(r["model"] for r in rows):
            parts = []
            for dt in DTS:
                r = cells.get((material, model, dt))
                if r is None:
                    parts.append("")
                elif r["error"] or r["done"] < r["steps"]:
                    parts.append(f"FAILED at step {r['done'] + 1}")
                else:
                    parts.append(f"{r['cg_mean']:.0f} / {r['cg_max']}, {r['ms_per_step']:.2f} ms")
            lines.append(f"| {material} | {model} | " + " | ".join(parts) + " |")
    return "\n".join(lines)


def energy(sim) -> float:
    """Kinetic + elastic + gravity's potential energy of the scene (J)."""
    kinetic = float(sim.kinetic_energy().sum())
    elastic = float(sim.model.energy(sim.x))
    potential = -float((sim.system.external * (sim.x - sim.model.rest)).sum())
    return kinetic + elastic + potential


def run_paper_beam(resolution=2, steps=150, device="cpu", dtype=torch.float32, model="stvk") -> dict:
    scene = paper_beam(resolution=resolution, model=model, device=device, dtype=dtype, steps=steps)
    sim = scene.simulator
    rows, error = [], ""
    start = time.perf_counter()
    try:
        for step in range(1, steps + 1):
            report = sim.step()
            if step % 10 == 0 or step == steps:
                inversion = inversion_report(sim)
                rows.append({"step": step, "t": sim.time, "energy": energy(sim),
                             "inverted": int(inversion.inverted.sum()), "min_ratio": float(inversion.min_ratio.min()),
                             "cg": int(report.cg_iterations.max()), "finite": bool(torch.isfinite(sim.x).all()),
                             "tip_z": float(sim.positions(0)[:, 2].min())})
    except tm.SolverError as exc:
        error = str(exc)
    if device != "cpu":
        torch.cuda.synchronize()
    seconds = time.perf_counter() - start
    return {"resolution": resolution, "tets": sum(b.mesh.num_elements for b in sim.bodies), "model": model,
            "steps": steps, "done": sim.steps_done, "seconds": seconds, "error": error, "rows": rows,
            "device": str(sim.device), "dtype": str(sim.dtype).replace("torch.", "")}


def paper_beam_markdown(result) -> str:
    lines = [f"The paper's beam, {result['model']}, {result['tets']:,} tets on {result['device']} "
             f"({result['dtype']}): {result['done']} of {result['steps']} steps in {result['seconds']:.1f} s"
             + (f"; FAILED: {result['error']}" if result["error"] else ""), "",
             "| step | t (s) | energy (J) | inverted | min element ratio | CG it | tip z (m) |",
             "|---:|---:|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        lines.append(f"| {r['step']} | {r['t']:.2f} | {r['energy']:.4g} | {r['inverted']} | {r['min_ratio']:.3f} | "
                     f"{r['cg']} | {r['tip_z']:.4f} |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=["table", "paper_beam"], default=None)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--resolution", type=int, default=2, help="paper beam: 4,800 r^3 tets")
    parser.add_argument("--steps", type=int, default=None, help="steps (table 100, paper beam 150)")
    parser.add_argument("--out", default=None, help="folder for robustness.md and robustness.json")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    result = {"python": platform.python_version(), "torch": torch.__version__, "backend": tm.backend_info(),
              "device": args.device, "dtype": args.dtype}
    text = [f"# Defaults against stiff and extreme cases ({args.device}, {args.dtype})", ""]
    if args.only in (None, "table"):
        rows = run_table(steps=args.steps or 100, device=args.device, dtype=dtype)
        result["table"] = rows
        text += ["Clamped 1 x 0.1 x 0.1 m beam, 480 tets, gravity, 100 steps on defaults; each cell: CG "
                 "iterations per step (mean / max) and wall time per step.", "", table_markdown(rows), ""]
        print(table_markdown(rows), flush=True)
    if args.only in (None, "paper_beam"):
        beam = run_paper_beam(args.resolution, args.steps or 150, args.device, dtype)
        result["paper_beam"] = beam
        text += [paper_beam_markdown(beam), ""]
        print(paper_beam_markdown(beam), flush=True)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "robustness.md").write_text("\n".join(text))
        (out / "robustness.json").write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
