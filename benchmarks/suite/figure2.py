"""Figure 2 of the paper, reproduced: GPU / CPU speedup of whole implicit Euler steps against the
element count, tetrahedra and triangles, hooke, stvk and corotational.

    python benchmarks/suite/figure2.py --device cuda --out $OUT          # the full figure
    python benchmarks/suite/figure2.py --quick --out /tmp/f2             # tiny sizes, seconds, any CPU

Scene (``common.cantilever_sim``): the paper's beam (1 x 0.4 x 0.25 m, hexes x 6 tets; the
307,200-tet size is its 80 x 32 x 20) or a rectangle of triangles (membrane, in-plane gravity),
clamped at x = 0, dt = 0.01, a fixed budget of --cg-iterations CG iterations (tol 0).

Measured per size, in this process:
  ours      the extension on --device (``TENSORMASS_BACKEND=extension``)
  torch     our pure-torch path on --device
  csr, bsr  the assembled system matrix (torch sparse CSR / BSR 3x3) with CG in torch ops
  cupy      the same CSR with ``cupyx.scipy.sparse.linalg.cg`` (CUDA, when CuPy imports)
  cpu-extension, cpu-torch
            the C++ extension on all CPU threads (``torch.get_num_threads()``, --cpu-threads)
            and the pure-torch path on the CPU (only when --device is not the CPU)
``x_ours`` of a row = its ms per step / ours at the same size: how many times faster ours is;
on the cpu-extension row it is the paper's GPU/CPU speedup. ms/CG it. = ms per step / CG
iterations for the matrix-free runs (an upper bound: the step's force and right-hand side are
included), the timed solve / iterations for the assembled ones; x floor = that / the floor of
one matrix-free CG iteration (``common.cg_iteration_bytes`` / copy bandwidth).

A measurement is skipped (and says so) when the previous size of the same series predicts one
step longer than --max-seconds, or when the script's --budget-s would be exceeded. Writes
figure2.md, figure2.json, figure2.png under --out.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, copy_bandwidth, is_cuda, metadata, record, release
from measure import Estimator, run_assembled, run_simulator, sim_size

COLUMNS = [("kind", "kind", None), ("model", "model", None), ("elements", "elements", ","),
           ("device", "device", None), ("backend", "backend", None), ("cg_iterations", "CG it", None),
           ("steps", "steps", None), ("steps_per_s", "steps/s", ".2f"), ("ms_per_step", "ms/step", ".2f"),
           ("ms_per_cg_iteration", "ms/CG it", ".3f"), ("floor_ratio", "x floor", ".1f"),
           ("assembly_ms", "assembly ms", ".1f"), ("x_ours", "ours x faster", ".1f")]

DEFAULT_TET = "4800,38400,307200,1036800,2457600"
DEFAULT_TRI = "4800,38400,307200,1036800,2457600"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--quick", action="store_true", help="tiny sizes and steps: a smoke run of seconds on a CPU")
    p.add_argument("--kinds", default="tet,tri")
    p.add_argument("--models", default="hooke,stvk,corotational")
    p.add_argument("--tet-elements", default=None, help=f"approximate tetrahedron counts ({DEFAULT_TET})")
    p.add_argument("--tri-elements", default=None, help=f"approximate triangle counts ({DEFAULT_TRI})")
    p.add_argument("--cg-iterations", type=int, default=None, help="CG budget of a step (25)")
    p.add_argument("--steps", type=int, default=None, help="timed steps on --device after warm-up (5)")
    p.add_argument("--cpu-steps", type=int, default=None, help="timed steps of the CPU comparisons (2)")
    p.add_argument("--backends", default="extension,torch,csr,bsr,cupy", help="run on --device")
    p.add_argument("--cpu-backends", default="extension,torch", help="CPU comparisons ('' for none)")
    p.add_argument("--cpu-threads", type=int, default=None, help="torch threads of the CPU runs (default: torch's)")
    p.add_argument("--max-seconds", type=float, default=None, help="time limit of one measurement's timed steps (5)")
    p.add_argument("--budget-s", type=float, default=None, help="wall-clock limit of the whole script")
    p.add_argument("--torch-max-elements", type=int, default=1_100_000, help="largest size of the torch paths")
    p.add_argument("--assembled-max-elements", type=int, default=1_100_000, help="largest assembled size")
    p.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    args = p.parse_args(argv)
    common.fill_defaults(args, dict(tet_elements=DEFAULT_TET, tri_elements=DEFAULT_TRI, cg_iterations=25, steps=5,
                                    cpu_steps=2, max_seconds=5.0),
                         quick=dict(tet_elements="48", tri_elements="32", cg_iterations=5, steps=2, cpu_steps=1,
                                    max_seconds=2.0))
    return args


def main(argv=None):
    args = parse_args(argv)
    if args.cpu_threads:
        torch.set_num_threads(args.cpu_threads)
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    budget = Budget(args.budget_s)
    cpu_backends = [b for b in args.cpu_backends.split(",") if b] if is_cuda(device) else []
    copy_bytes = (1 << 24) if args.quick else (1 << 30)
    bandwidth = {"device": copy_bandwidth(device, copy_bytes)}
    if cpu_backends:
        bandwidth["cpu"] = copy_bandwidth("cpu", copy_bytes)
    meta = metadata(device, dtype=args.dtype, cg_iterations=args.cg_iterations,
                    copy_bandwidth_GBps={k: v / 1e9 for k, v in bandwidth.items()}, quick=args.quick,
                    argv=vars(args))
    results = Results(args.out, "figure2", "Figure 2: GPU / CPU speedup of implicit Euler steps", meta, COLUMNS,
                      notes=["ours = the extension on the device; x_ours = ms/step of the row / ours at the same "
                             "size (on cpu-extension rows: the paper's GPU/CPU speedup)."])
    estimator = Estimator()
    runs = [(k, m) for k in args.kinds.split(",") for m in args.models.split(",")]
    for position, (kind, model) in enumerate(runs):
        share = budget.share(len(runs) - position)
        sizes = common.parse_ints(args.tet_elements if kind == "tet" else args.tri_elements)
        for target in sizes:
            measure_size(args, results, estimator, share, device, dtype, kind, model, target, cpu_backends,
                         bandwidth)
    add_speedups(results.records)
    results.plot(lambda plt: draw(plt, results.records, meta))
    results.finish()
    return results


def measure_size(args, results, estimator, budget, device, dtype, kind, model, target, cpu_backends, bandwidth):
    """Every backend at one size; records appended to ``results``."""
    base = dict(scene="paper_beam" if kind == "tet" else "tri_beam", kind=kind, model=model, dtype=args.dtype,
                objects=1, target_elements=target)
    gravity = (0.0, 0.0, -9.81) if kind == "tet" else (0.0, -9.81, 0.0)
    plan = [(device, b) for b in args.backends.split(",") if b] + [(torch.device("cpu"), b) for b in cpu_backends]
    device_sims = {}  # backend -> a simulator of this size on the device (the assembled runs start from it)
    floor_bytes = None
    for dev, backend in plan:
        on_cpu_side = dev != device
        key = (kind, model, dev.type, backend)
        rec = record(device=dev.type, backend=f"cpu-{backend}" if on_cpu_side else backend, **base)
        assembled_run = backend in ("csr", "bsr", "cupy")
        source = next((b for b in ("extension", "torch") if b in device_sims), None)
        why = skip_reason(args, estimator, budget, key, target, backend)
        if why is None and assembled_run and source is None:
            why = "no simulator of this size ran on the device (the matrix is assembled from its model)"
        if why is None and backend == "cupy" and not is_cuda(device):
            why = "CuPy runs on CUDA only"
        if why:
            rec["skipped"] = why
            results.add(rec)
            continue
        steps = args.cpu_steps if on_cpu_side else args.steps
        if assembled_run:
            sim = device_sims[source]
            with common.forced_backend(source):  # the forces and the assembly run the ops that sim ran
                out = run_assembled(sim, gravity, backend, device, steps, args.max_seconds)
            out.update(sim_size(sim), assembled_with=source)
        else:
            def make(dev=dev):
                return common.cantilever_sim(kind, model, target, dev, dtype, args.cg_iterations)[0]

            out = run_simulator(make, backend, dev, steps, args.max_seconds)
        sim = out.pop("_sim", None)
        wall = out.pop("_wall_s", 0.0)
        if sim is not None and floor_bytes is None:
            floor_bytes = common.sim_cg_bytes(sim)["total"]
        if sim is not None and not on_cpu_side:
            device_sims[backend] = sim
        rec.update(out)
        step_s = (out.get("ms_per_step") or 0.0) / 1e3 or None
        estimator.note(key, out.get("elements") or target, step_s, wall)
        common.add_floor(rec, floor_bytes, bandwidth["cpu" if on_cpu_side else "device"])
        results.add(rec)
    device_sims.clear()
    release(device)


def skip_reason(args, estimator, budget, key, target, backend):
    """Why a measurement is not run (size limit, time limit, budget), or None."""
    limit = args.assembled_max_elements if backend in ("csr", "bsr", "cupy") else (
        args.torch_max_elements if backend == "torch" else None)
    if limit is not None and target > limit:
        return f"size limit: {target:,} > {limit:,} elements"
    step_s = estimator.step_seconds(key, target)
    if step_s > args.max_seconds:
        return f"time limit: one step estimated at {step_s:.1f} s > {args.max_seconds:g} s"
    wall = estimator.wall_seconds(key, target)
    if not budget.allows(wall):
        return f"budget: estimated {wall:.0f} s > {max(budget.remaining(), 0):.0f} s left"
    return None


def add_speedups(records):
    """x_ours on every row: its ms/step over ours (the device's extension) at the same size."""
    # ours = the extension on the accelerator (the CPU extension rows are compared with it: their
    # x_ours is the paper's GPU/CPU speedup), or on the CPU when the whole run is on the CPU
    on_device = any(r["device"] != "cpu" for r in records)
    ours = {(r["kind"], r["model"], r["elements"]): r for r in records
            if r["backend"] == "extension" and r.get("ms_per_step") and (r["device"] != "cpu" or not on_device)}
    for r in records:
        base = ours.get((r["kind"], r["model"], r["elements"]))
        if base is not None and base is not r and r.get("ms_per_step"):
            r["x_ours"] = r["ms_per_step"] / base["ms_per_step"]


def draw(plt, records, meta):
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5))
    series = sorted({(r["kind"], r["model"]) for r in records})
    for kind, model in series:
        rows = [r for r in records if r["kind"] == kind and r["model"] == model]
        cpu = sorted((r["elements"], r["x_ours"]) for r in rows
                     if r["backend"] == "extension" and r["device"] == "cpu" and r.get("x_ours"))
        style = "-" if kind == "tet" else "--"
        if cpu:
            left.plot(*zip(*cpu), style, marker="o", label=f"{kind} {model}")
        mine = sorted((r["elements"], r["steps_per_s"]) for r in rows
                      if r["backend"] == "extension" and r.get("steps_per_s"))
        if mine:
            right.plot(*zip(*mine), style, marker="o", label=f"{kind} {model}")
    if not left.get_lines():
        left.text(0.5, 0.5, "no CPU comparison in this run", transform=left.transAxes, ha="center")
    left.set_xscale("log")
    left.set_xlabel("elements")
    left.set_ylabel("speedup: ours on the GPU / C++ extension on all CPU threads")
    left.set_title(common.plot_title(meta, "GPU / CPU speedup per implicit step"), fontsize=9)
    right.set_xscale("log")
    right.set_yscale("log")
    right.set_xlabel("elements")
    right.set_ylabel(f"steps/s ({meta.get('cg_iterations')} CG iterations)")
    right.set_title("ours: steps per second", fontsize=9)
    for ax in (left, right):
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    return fig


if __name__ == "__main__":
    main()
