"""SOFA's GPU benchmark beam (``tensormass run sofa_beam``): implicit Euler steps per second.

    python benchmarks/suite/sofa_beam.py --device cuda --out $OUT
    python benchmarks/suite/sofa_beam.py --quick --out /tmp/sofa          # a 1/15-resolution beam, CPU

Scene: ``tensormass_torch.sim.builtin.sofa_beam`` (76 x 16 x 16 nodes, 101,250 tets, E = 1000,
nu = 0.3, total mass 50, gravity -9 along y, dt = 0.04, r_M = r_K = 0.1, a contact plane, nodes
with x <= 0.1 fixed) with SOFA's fixed budget of 10 CG iterations (tol 0, so every variant runs
all 10). Models: hooke and corotational (SOFA's model, QR rotation frame).

Measured in this process: ours (the extension on --device), our pure-torch path on --device,
the assembled matrix with CG (torch CSR / BSR 3x3, CuPy's cg on CUDA; the contact plane is
left out of those: no node reaches it in the measured steps), and the C++ extension on all CPU
threads (when --device is not the CPU). ms/CG it. = ms per step / 10 for the matrix-free runs,
the timed solve / 10 for the assembled ones; x floor against ``common.cg_iteration_bytes``.
Published (SOFA's own table): 385 steps/s on an RTX 2070, 9 steps/s on an i7-10750H. Target:
>= 10,000 steps/s. Writes sofa_beam.md, sofa_beam.json, sofa_beam.png under --out.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, copy_bandwidth, is_cuda, metadata, record, release
from measure import run_assembled, run_simulator, sim_size

from tensormass_torch.sim.builtin import sofa_beam

SOFA_PUBLISHED = {"RTX 2070 (SOFA, CUDA)": 385.0, "i7-10750H (SOFA, CPU)": 9.0}
TARGET_STEPS_PER_S = 10_000.0
GRAVITY = (0.0, -9.0, 0.0)

COLUMNS = [("model", "model", None), ("elements", "elements", ","), ("device", "device", None),
           ("backend", "backend", None), ("cg_iterations", "CG it", None), ("steps", "steps", None),
           ("steps_per_s", "steps/s", ".1f"), ("ms_per_step", "ms/step", ".3f"),
           ("ms_per_cg_iteration", "ms/CG it", ".4f"), ("floor_ratio", "x floor", ".1f"),
           ("assembly_ms", "assembly ms", ".1f"), ("x_ours", "ours x faster", ".1f"),
           ("x_sofa_gpu", "x SOFA GPU (385)", ".2f")]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--quick", action="store_true", help="the beam at 1/15 resolution, few steps: seconds on a CPU")
    p.add_argument("--models", default="hooke,corotational")
    p.add_argument("--scale", type=int, default=None, help="divide the beam's resolution (sofa_beam(scale=)): 1")
    p.add_argument("--steps", type=int, default=None,
                   help="timed steps on --device (1000, or --max-seconds: a sustained run, as SOFA's table; "
                        "with 50 the first single steps and the host checks between chains weighed ~25%% of a "
                        "0.2 ms step)")
    p.add_argument("--cpu-steps", type=int, default=None, help="timed steps of the CPU comparison (3)")
    p.add_argument("--backends", default="extension,torch,csr,bsr,cupy")
    p.add_argument("--cpu-backends", default="extension")
    p.add_argument("--max-seconds", type=float, default=None, help="time limit of one measurement's steps (5)")
    p.add_argument("--budget-s", type=float, default=None)
    args = p.parse_args(argv)
    common.fill_defaults(args, dict(scale=1, steps=1000, cpu_steps=3, max_seconds=5.0),
                         quick=dict(scale=15, steps=2, cpu_steps=1, max_seconds=2.0))
    return args


def make_sim(model, device, scale):
    sim = sofa_beam(model=model, device=device, dtype=torch.float32, scale=scale).simulator
    sim.options.cg_tol = 0.0          # SOFA runs its 10 iterations: no early exit
    sim.options.check_every = 1000    # and no host check inside them
    return sim


def main(argv=None):
    args = parse_args(argv)
    device = torch.device(args.device)
    budget = Budget(args.budget_s)
    cpu_backends = [b for b in args.cpu_backends.split(",") if b] if is_cuda(device) else []
    copy_bytes = (1 << 24) if args.quick else (1 << 30)
    bandwidth = {"device": copy_bandwidth(device, copy_bytes)}
    if cpu_backends:
        bandwidth["cpu"] = copy_bandwidth("cpu", copy_bytes)
    meta = metadata(device, dtype="float32", scale=args.scale, sofa_published_steps_per_s=SOFA_PUBLISHED,
                    target_steps_per_s=TARGET_STEPS_PER_S,
                    copy_bandwidth_GBps={k: v / 1e9 for k, v in bandwidth.items()}, argv=vars(args))
    results = Results(args.out, "sofa_beam", "SOFA's GPU benchmark beam: implicit Euler steps per second", meta,
                      COLUMNS, notes=[f"SOFA's own table: {', '.join(f'{k} {v:g}' for k, v in SOFA_PUBLISHED.items())}"
                                      f" steps/s; target >= {TARGET_STEPS_PER_S:,.0f} steps/s."])
    for model in args.models.split(","):
        sims = {}
        floor_bytes = None
        plan = [(device, b) for b in args.backends.split(",") if b] + [(torch.device("cpu"), b) for b in cpu_backends]
        for dev, backend in plan:
            on_cpu_side = dev != device
            rec = record(scene="sofa_beam", model=model, kind="tet", objects=1, dtype="float32", device=dev.type,
                         backend=f"cpu-{backend}" if on_cpu_side else backend)
            assembled_run = backend in ("csr", "bsr", "cupy")
            source = next((b for b in ("extension", "torch") if b in sims), None)
            if budget.remaining() <= 0:
                rec["skipped"] = "budget spent"
            elif assembled_run and source is None:
                rec["skipped"] = "no simulator ran on the device (the matrix is assembled from its model)"
            elif backend == "cupy" and not is_cuda(device):
                rec["skipped"] = "CuPy runs on CUDA only"
            if rec["skipped"]:
                results.add(rec)
                continue
            steps = args.cpu_steps if on_cpu_side else args.steps
            if assembled_run:
                with common.forced_backend(source):
                    out = run_assembled(sims[source], GRAVITY, backend, device, steps, args.max_seconds)
                out.update(sim_size(sims[source]), assembled_with=source,
                           note="contact plane left out (untouched in these steps)")
            else:
                out = run_simulator(lambda dev=dev: make_sim(model, dev, args.scale), backend, dev, steps,
                                    args.max_seconds)
            sim = out.pop("_sim", None)
            out.pop("_wall_s", None)
            if sim is not None:
                floor_bytes = floor_bytes or common.sim_cg_bytes(sim)["total"]
                if not on_cpu_side:
                    sims[backend] = sim
            rec.update(out)
            if rec.get("steps_per_s"):
                rec["x_sofa_gpu"] = rec["steps_per_s"] / SOFA_PUBLISHED["RTX 2070 (SOFA, CUDA)"]
                rec["target_ratio"] = rec["steps_per_s"] / TARGET_STEPS_PER_S
            common.add_floor(rec, floor_bytes, bandwidth["cpu" if on_cpu_side else "device"])
            results.add(rec)
        sims.clear()
        release(device)
    # ours = the extension on the accelerator (not its CPU row, which is compared with it)
    on_device = any(r["device"] != "cpu" for r in results.records)
    ours = {r["model"]: r for r in results.records
            if r["backend"] == "extension" and r.get("ms_per_step") and (r["device"] != "cpu" or not on_device)}
    for r in results.records:
        base = ours.get(r["model"])
        if base is not None and base is not r and r.get("ms_per_step"):
            r["x_ours"] = r["ms_per_step"] / base["ms_per_step"]
    results.plot(lambda plt: draw(plt, results.records, meta))
    results.finish()
    return results


def draw(plt, records, meta):
    rows = [r for r in records if r.get("steps_per_s")]
    fig, ax = plt.subplots(figsize=(10, 0.45 * max(len(rows), 4) + 1.5))
    labels = [f"{r['model']} / {r['backend']} ({r['device']})" for r in rows]
    ax.barh(range(len(rows)), [r["steps_per_s"] for r in rows], color="tab:blue")
    for name, value in SOFA_PUBLISHED.items():
        ax.axvline(value, linestyle="--", color="gray")
        ax.text(value, len(rows) - 0.5, f" {name}", rotation=90, va="top", fontsize=7)
    ax.axvline(TARGET_STEPS_PER_S, linestyle=":", color="red")
    ax.set_yticks(range(len(rows)))
    ax.set_yticklabels(labels, fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("steps per second (10 CG iterations)")
    ax.set_title(common.plot_title(meta, "SOFA's benchmark beam"), fontsize=9)
    ax.grid(True, axis="x", which="both", alpha=0.3)
    return fig


if __name__ == "__main__":
    main()
