"""Time of one CG iteration against the memory floor, from 10^3 to 10^7 elements.

    python benchmarks/suite/cg_floor.py --device cuda --out $OUT
    python benchmarks/suite/cg_floor.py --quick --out /tmp/floor            # tiny sizes, CPU, seconds

Scene: the paper's beam at each size (``common.cantilever_sim``, tetrahedra), float32.
Time of one CG iteration: the difference of whole implicit steps at two CG budgets (--low and
--high iterations, tol 0) divided by the difference of the budgets, so the step's forces,
right-hand side and per-solve set-up cancel (``measure.marginal_cg_ms``). The floor: the bytes
one iteration must move (``common.cg_iteration_bytes``: element indices, shape vectors and
material, PartialForce written and read, the node vectors of the matvec epilogue and of the CG
updates; the parts are in each record's ``bytes_parts``) divided by the copy bandwidth measured
here. Targets: within 1.5x of the floor at >= 5M elements, 3x at 307,200.

Alternatives in this process: our pure-torch path (same method) and the assembled matrix (torch
CSR; time of a solve of --high iterations / --high, ``matrix_bytes`` = what one product reads
from it). Writes cg_floor.md, cg_floor.json, cg_floor.png under --out.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, copy_bandwidth, error_text, forced_backend, metadata, record, release
from measure import Estimator, marginal_cg_ms, run_assembled, sim_size, warm_up

DEFAULT_SIZES = "1000,10000,100000,307200,1000000,3000000,5000000,10000000"
TARGETS = ((5_000_000, 1.5), (307_200, 3.0))

COLUMNS = [("model", "model", None), ("elements", "elements", ","), ("nodes", "nodes", ","),
           ("backend", "backend", None), ("ms_per_cg_iteration", "ms/CG it", ".4f"),
           ("bytes_per_cg_iteration", "bytes/CG it", ","), ("floor_ms_per_cg_iteration", "floor ms", ".4f"),
           ("floor_ratio", "x floor", ".2f"), ("target_x_floor", "target", None)]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--quick", action="store_true", help="tiny sizes: seconds on a CPU")
    p.add_argument("--elements", default=None, help=f"approximate tetrahedron counts ({DEFAULT_SIZES})")
    p.add_argument("--models", default="hooke,stvk")
    p.add_argument("--backends", default="extension,torch,csr")
    p.add_argument("--low", type=int, default=None, help="CG budget of the short steps (5)")
    p.add_argument("--high", type=int, default=None, help="CG budget of the long steps (25)")
    p.add_argument("--steps", type=int, default=None, help="timed steps at each budget (5)")
    p.add_argument("--torch-max-elements", type=int, default=1_100_000)
    p.add_argument("--assembled-max-elements", type=int, default=1_100_000)
    p.add_argument("--max-seconds", type=float, default=None, help="time limit of the steps at one budget (4)")
    p.add_argument("--budget-s", type=float, default=None)
    args = p.parse_args(argv)
    common.fill_defaults(args, dict(elements=DEFAULT_SIZES, low=5, high=25, steps=5, max_seconds=4.0),
                         quick=dict(elements="48,384", low=2, high=5, steps=2, max_seconds=2.0))
    return args


def target_for(elements):
    for size, ratio in TARGETS:
        if elements >= size:
            return ratio
    return None


def run_marginal(kind_model, target, backend, device, args):
    """Our solver (extension or torch path) at one size: marginal ms per CG iteration."""
    model = kind_model
    out = {"backend": backend}
    start = time.perf_counter()
    try:
        with forced_backend(backend):
            sim, _ = common.cantilever_sim("tet", model, target, device, torch.float32, args.high)
            out.update(sim_size(sim))
            warm_up(sim, device)
            ms = marginal_cg_ms(sim, device, args.low, args.high, args.steps, args.max_seconds)
            parts = common.sim_cg_bytes(sim)
    except Exception as exc:
        out.update(error=error_text(exc), _wall_s=time.perf_counter() - start)
        release(device)
        return out, None
    out.update(ms_per_cg_iteration=ms, cg_iterations=args.high, bytes_parts=parts, _wall_s=time.perf_counter() - start)
    return out, sim


def main(argv=None):
    args = parse_args(argv)
    device = torch.device(args.device)
    budget = Budget(args.budget_s)
    bandwidth = copy_bandwidth(device, (1 << 24) if args.quick else (1 << 30))
    meta = metadata(device, dtype="float32", cg_budgets=[args.low, args.high],
                    copy_bandwidth_GBps={"device": bandwidth / 1e9}, argv=vars(args))
    results = Results(args.out, "cg_floor", "Time per CG iteration against the memory floor", meta, COLUMNS,
                      notes=[f"ms/CG it = (t(step at {args.high} CG it) - t(step at {args.low})) / "
                             f"{args.high - args.low}"
                             " (matrix-free); a solve / iterations (csr). floor = bytes / copy bandwidth "
                             f"({bandwidth / 1e9:.0f} GB/s); see common.cg_iteration_bytes for what is counted."])
    estimator = Estimator()
    models = args.models.split(",")
    for position, model in enumerate(models):
        share = budget.share(len(models) - position)
        for target in common.parse_ints(args.elements):
            sims = {}
            floor_bytes = None
            for backend in [b for b in args.backends.split(",") if b]:
                key = (model, backend)
                rec = record(scene="paper_beam", model=model, kind="tet", objects=1, dtype="float32",
                             device=device.type, backend=backend, target_elements=target,
                             target_x_floor=target_for(target))
                limit = {"torch": args.torch_max_elements, "csr": args.assembled_max_elements}.get(backend)
                wall = estimator.wall_seconds(key, target)
                source = next((b for b in ("extension", "torch") if b in sims), None)
                why = None
                if limit is not None and target > limit:
                    why = f"size limit: {target:,} > {limit:,} elements"
                elif not share.allows(wall):
                    why = f"budget: estimated {wall:.0f} s > {max(share.remaining(), 0):.0f} s left"
                elif backend == "csr" and source is None:
                    why = "no simulator of this size ran (the matrix is assembled from its model)"
                if why:
                    rec["skipped"] = why
                    results.add(rec)
                    continue
                if backend == "csr":
                    sim = sims[source]
                    gravity = (0.0, 0.0, -9.81)
                    with forced_backend(source):
                        out = run_assembled(sim, gravity, "csr", device, 1, args.max_seconds)
                    out.update(sim_size(sim), assembled_with=source)
                    for name in ("steps", "steps_per_s", "ms_per_step"):
                        out.pop(name, None)  # one step ran (the warm-up of the solve): not a step rate
                    new_sim = None
                else:
                    out, new_sim = run_marginal(model, target, backend, device, args)
                wall = out.pop("_wall_s", 0.0)
                if new_sim is not None:
                    sims[backend] = new_sim
                    if floor_bytes is None:
                        floor_bytes = out["bytes_parts"]["total"]
                rec.update(out)
                if backend == "csr" and rec.get("matrix_bytes") and rec.get("ms_per_cg_iteration"):
                    # its own floor: the matrix read once per iteration, p read and A p written,
                    # and the same CG vector updates
                    parts = common.sim_cg_bytes(sims[source])
                    own = rec["matrix_bytes"] + 2 * parts["p"] + parts["updates"]
                    rec["own_floor_ratio"] = rec["ms_per_cg_iteration"] / (1e3 * own / bandwidth)
                common.add_floor(rec, floor_bytes, bandwidth)
                estimator.note(key, rec.get("elements") or target, None, wall)
                results.add(rec)
            sims.clear()
            release(device)
    results.plot(lambda plt: draw(plt, results.records, meta))
    results.finish()
    return results


def draw(plt, records, meta):
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5))
    for model in sorted({r["model"] for r in records}):
        for backend in sorted({r["backend"] for r in records}):
            rows = sorted((r["elements"], r["ms_per_cg_iteration"], r.get("floor_ratio")) for r in records
                          if r["model"] == model and r["backend"] == backend and r.get("ms_per_cg_iteration"))
            if not rows:
                continue
            n, ms, ratio = zip(*rows)
            left.plot(n, ms, marker="o", label=f"{model} {backend}")
            if all(x is not None for x in ratio):
                right.plot(n, ratio, marker="o", label=f"{model} {backend}")
        floor = sorted({(r["elements"], r["floor_ms_per_cg_iteration"]) for r in records
                        if r["model"] == model and r.get("floor_ms_per_cg_iteration")})
        if floor:
            left.plot(*zip(*floor), "k--", linewidth=1, label=f"{model} floor")
    for size, ratio in TARGETS:
        right.plot([size], [ratio], "r*", markersize=10)
    left.set_ylabel("ms per CG iteration")
    right.set_ylabel("x floor (bytes / copy bandwidth)")
    for ax in (left, right):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("tetrahedra")
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7)
    left.set_title(common.plot_title(meta, "time per CG iteration"), fontsize=9)
    right.set_title("ratio to the floor (red stars: targets)", fontsize=9)
    return fig


if __name__ == "__main__":
    main()
