"""Steps per second of whole implicit Euler steps on the benchmark scenes (DESIGN section 7).

    python benchmarks/step_bench.py --device cuda --out $OUT      # all scenes, both backends

Scenes: SOFA's GPU benchmark beam (101,250 tets, 10 CG iterations, contact plane) and the
paper's 307,200-tet beam (25 CG iterations), each with the extension and the pure-torch path
in the same process. CG runs a fixed budget (require_convergence=False, tol=0) so that every
variant does the same work. Writes step_bench.md / step_bench.json under --out.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import time
from pathlib import Path

import torch

import tensormass_torch as tm
from tensormass_torch.scenes import sofa_beam


def paper_beam(model, device, dtype):
    mesh = tm.beam_mesh(80, 32, 20, size=(1.0, 0.4, 0.25), dtype=dtype, device=device)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model)
    body = tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] <= 1e-6)
    return tm.Simulator([body], dt=0.01, gravity=(0, 0, -9.81), cg_tol=0.0, cg_max_iter=25,
                        require_convergence=False, check_every=1000)


def sofa(model, device, dtype):
    sim = sofa_beam(model=model, device=device, dtype=dtype).simulator
    sim.options.cg_tol = 0.0  # SOFA runs its 10 iterations; no early exit, no host check
    sim.options.check_every = 1000
    return sim


def sync(device):
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def measure(make, model, device, dtype, steps, warmup=2):
    sim = make(model, device, dtype)
    sim.step(warmup)
    sync(device)
    start = time.perf_counter()
    sim.step(steps)
    sync(device)
    seconds = (time.perf_counter() - start) / steps
    iters = int(sim.last_report.cg_iterations.max())
    return {"steps_per_s": 1.0 / seconds, "ms_per_step": 1e3 * seconds, "cg_iterations": iters,
            "ms_per_cg_iteration": 1e3 * seconds / max(iters, 1),
            "elements": sum(g.elements.shape[0] for g in sim.model.groups)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--backends", default="extension,torch")
    parser.add_argument("--scenes", default="sofa_beam,paper_beam")
    args = parser.parse_args(argv)
    scenes = {"sofa_beam": sofa, "paper_beam": paper_beam}
    device_name = torch.cuda.get_device_name() if torch.device(args.device).type == "cuda" else "cpu"
    # The GPU machine's copy of the tree has no .git: scripts pass the commit in TENSORMASS_COMMIT.
    commit = os.environ.get("TENSORMASS_COMMIT") or subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    records = []
    for scene in args.scenes.split(","):
        models = ["hooke", "corotational"] if scene == "sofa_beam" else ["hooke", "stvk"]
        for model in models:
            for backend in args.backends.split(","):
                os.environ["TENSORMASS_BACKEND"] = backend
                try:
                    rec = measure(scenes[scene], model, args.device, torch.float32, args.steps)
                except Exception as exc:  # a backend missing on this machine: say so, go on
                    rec = {"error": f"{type(exc).__name__}: {exc}"}
                rec.update(scene=scene, model=model, backend=backend, device=device_name, dtype="float32")
                records.append(rec)
                print(json.dumps(rec), flush=True)
    os.environ.pop("TENSORMASS_BACKEND", None)
    meta = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "commit": commit,
            "torch": torch.__version__, "device": device_name}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "step_bench.json").write_text(json.dumps({"meta": meta, "records": records}, indent=1))
    lines = [f"# Implicit Euler steps ({device_name}, {meta['date']}, commit {commit}, torch {torch.__version__})", "",
             "| scene | model | elements | backend | CG it | ms/step | steps/s | ms/CG it |", "|---|---|---|---|---|---|---|---|"]
    for r in records:
        if "error" in r:
            lines.append(f"| {r['scene']} | {r['model']} | | {r['backend']} | | {r['error'][:60]} | | |")
        else:
            lines.append(f"| {r['scene']} | {r['model']} | {r['elements']} | {r['backend']} | {r['cg_iterations']} | "
                         f"{r['ms_per_step']:.2f} | {r['steps_per_s']:.1f} | {r['ms_per_cg_iteration']:.3f} |")
    (out / "step_bench.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
