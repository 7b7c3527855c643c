"""The effect of stvk's definite tangent (``Material(tangent="definite")``): steps survived, CG
iterations and speed against the exact tangent, on scenes that compress stvk.

    python benchmarks/studies/definite_tangent.py --device cuda --out $OUT [--quick]

Scenes: ``compressed`` (a 1 m beam whose free end is pushed 70 % of the way in over 0.2 s,
dt 0.02, CG to 1e-6) and ``paper_beam`` (the 307,200-tet beam sagging under its weight, 25 CG
iterations per step as in step_bench; its exact tangent turns indefinite after ~30 steps).
Each record: scene, tangent, steps run, failed (the SolverError, if any), CG iterations per step,
steps/s, lowest node height. Writes definite_tangent.md / .json.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch

import tensormass_torch as tm


def compressed(tangent, device, dtype, quick):
    n = 1 if quick else 2
    mesh = tm.beam_mesh(8 * n, 2 * n, 2 * n, size=(1.0, 0.2, 0.2), dtype=dtype, device=device)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk", tangent=tangent)
    end = mesh.vertices[:, 0] > 1 - 1e-4
    start = mesh.vertices[end].clone()
    push = torch.tensor([1.0, 0.0, 0.0], dtype=dtype, device=device)
    body = tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] < 1e-6, prescribed=end,
                   motion=lambda t: start - min(t, 0.2) / 0.2 * 0.7 * push)
    sim = tm.Simulator([body], dt=0.02, gravity=(0, 0, 0), cg_tol=1e-6, cg_max_iter=2000)
    return sim, (10 if quick else 40)


def paper_beam(tangent, device, dtype, quick):
    nx, ny, nz = (16, 6, 4) if quick else (80, 32, 20)
    mesh = tm.beam_mesh(nx, ny, nz, size=(1.0, 0.4, 0.25), dtype=dtype, device=device)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk", tangent=tangent)
    sim = tm.Simulator([tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] <= 1e-6)], dt=0.01, gravity=(0, 0, -9.81),
                       cg_tol=0.0, cg_max_iter=25, require_convergence=False, check_every=1000)
    return sim, (10 if quick else 80)


def run(make, tangent, device, dtype, quick):
    sim, steps = make(tangent, device, dtype, quick)
    done, iterations, failed = 0, 0, None
    common.sync(device)
    start = time.perf_counter()
    for _ in range(steps):
        try:
            report = sim.step()
        except tm.SolverError as exc:
            failed = str(exc).split(";")[0]
            break
        done += 1
        iterations += int(report.cg_iterations.max())
    common.sync(device)
    seconds = time.perf_counter() - start
    return {"scene": make.__name__, "tangent": tangent, "steps": done, "of": steps, "failed": failed,
            "cg_iterations_per_step": iterations / max(done, 1), "steps_per_s": done / seconds if done else None,
            "lowest_z": float(sim.x[:, 2].min()), "elements": sum(g.elements.shape[0] for g in sim.model.groups)}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results/definite_tangent")
    p.add_argument("--quick", action="store_true")
    args = p.parse_args(argv)
    dtype = torch.float32
    meta = common.metadata(args.device, dtype="float32")
    records = []
    for make in (compressed, paper_beam):
        for tangent in ("exact", "definite"):
            rec = run(make, tangent, args.device, dtype, args.quick)
            records.append(rec)
            print(json.dumps(rec), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "definite_tangent.json").write_text(json.dumps({"meta": meta, "records": records}, indent=1))
    lines = [f"# stvk: exact against definite tangent ({meta.get('device_name', args.device)}, "
             f"commit {meta.get('commit')}, {meta.get('date')})", "",
             "| scene | elements | tangent | steps run | CG it/step | steps/s | lowest z | failure |",
             "|---|---:|---|---:|---:|---:|---:|---|"]
    for r in records:
        sps = "" if r["steps_per_s"] is None else f"{r['steps_per_s']:.1f}"
        lines.append(f"| {r['scene']} | {r['elements']:,} | {r['tangent']} | {r['steps']} / {r['of']} | "
                     f"{r['cg_iterations_per_step']:.1f} | {sps} | {r['lowest_z']:.3f} | {r['failed'] or ''} |")
    (out / "definite_tangent.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
