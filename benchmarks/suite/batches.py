"""Batches: 1 to 10,000 objects of 1k-5k tetrahedra in one Simulator, steps per second and
objects x steps per second, against a Python loop over single-object simulators.

    python benchmarks/suite/batches.py --device cuda --out $OUT
    python benchmarks/suite/batches.py --quick --out /tmp/batches          # tiny objects, CPU, seconds

Objects: small beams clamped at x = 0 under gravity, cycling through --shapes (hex counts; 6
tets per hex: by default 1,200 / 2,160 / 3,024 / 4,032 / 4,800 tets) and five Young's moduli
(1e5 .. 3e5 Pa), so that every object has its own CG scalars. dt = 0.01, a fixed budget of
--cg-iterations CG iterations (tol 0), float32.

Measured in this process for each batch size B:
  extension         one packed Simulator of B bodies, the extension (ours)
  torch             the same on our pure-torch path
  csr               the assembled block-diagonal matrix with per-object CG scalars (torch CSR)
  loop-extension    a Python loop over single-body Simulators, one step each per round; timed over
                    the first min(B, --loop-objects) objects (``objects_timed``; its objects x
                    steps/s does not depend on B, its steps/s is that of one round)
objects x steps/s = objects in the run x steps/s; x_ours = ours' objects x steps/s / the row's.
Writes batches.md, batches.json, batches.png under --out.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, copy_bandwidth, error_text, metadata, record, release
from measure import Estimator, run_assembled, run_simulator, sim_size, warm_up

import tensormass_torch as tm

DEFAULT_SHAPES = "10x5x4,12x6x5,14x6x6,16x7x6,20x8x5"
YOUNG = (1e5, 1.5e5, 2e5, 2.5e5, 3e5)
GRAVITY = (0.0, 0.0, -9.81)

COLUMNS = [("objects", "objects", ","), ("objects_timed", "loop ran", None), ("elements", "elements", ","),
           ("device", "device", None),
           ("backend", "backend", None), ("cg_iterations", "CG it", None), ("steps", "steps", None),
           ("steps_per_s", "steps/s", ".2f"), ("objects_steps_per_s", "objects x steps/s", ",.0f"),
           ("ms_per_cg_iteration", "ms/CG it", ".3f"), ("floor_ratio", "x floor", ".1f"),
           ("assembly_ms", "assembly ms", ".1f"), ("x_ours", "ours x faster", ".1f")]


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--quick", action="store_true", help="tiny objects and batches: seconds on a CPU")
    p.add_argument("--objects", default=None, help="batch sizes (1,10,100,1000,10000)")
    p.add_argument("--shapes", default=None, help=f"hex counts NXxNYxNZ of the objects, cycled ({DEFAULT_SHAPES})")
    p.add_argument("--cg-iterations", type=int, default=None, help="CG budget of a step (20)")
    p.add_argument("--steps", type=int, default=None, help="timed steps (5)")
    p.add_argument("--backends", default="extension,torch,csr,loop-extension")
    p.add_argument("--loop-objects", type=int, default=None, help="objects the Python loop is timed over (100)")
    p.add_argument("--torch-max-elements", type=int, default=3_000_000)
    p.add_argument("--assembled-max-elements", type=int, default=1_100_000)
    p.add_argument("--max-seconds", type=float, default=None, help="time limit of one measurement's steps (5)")
    p.add_argument("--budget-s", type=float, default=None)
    args = p.parse_args(argv)
    common.fill_defaults(args, dict(objects="1,10,100,1000,10000", shapes=DEFAULT_SHAPES, loop_objects=100,
                                    cg_iterations=20, steps=5, max_seconds=5.0),
                         quick=dict(objects="1,4", shapes="2x2x2,3x2x2", loop_objects=2, cg_iterations=5, steps=2,
                                    max_seconds=2.0))
    return args


def shapes_of(text):
    return [tuple(int(v) for v in s.split("x")) for s in text.split(",") if s]


class ObjectFactory:
    """Meshes (one per shape, built once on the CPU) and materials shared by the bodies."""

    def __init__(self, shapes):
        self.meshes = [tm.beam_mesh(*s, size=(0.1 * s[0] / s[2], 0.1 * s[1] / s[2], 0.1), dtype=torch.float32)
                       for s in shapes]
        self.fixed = [m.vertices[:, 0] <= 1e-6 for m in self.meshes]
        self.materials = [tm.Material(young=e, poisson=0.3, density=1000.0, model="stvk", tangent="exact")
                          for e in YOUNG]

    def bodies(self, count):
        return [tm.Body(self.meshes[i % len(self.meshes)], self.materials[i % len(self.materials)],
                        fixed=self.fixed[i % len(self.meshes)]) for i in range(count)]

    def simulator(self, count, device, cg_iterations, first=0):
        bodies = self.bodies(first + count)[first:]
        return tm.Simulator(bodies, dt=0.01, gravity=GRAVITY, cg_tol=0.0, cg_max_iter=cg_iterations,
                            require_convergence=False, check_every=1000, device=device, dtype=torch.float32)


def run_loop(factory, count, device, args):
    """A Python loop over ``count`` single-body simulators (the extension), one step each per
    round: seconds per round, as run_simulator's fields."""
    out = {"backend": "loop-extension"}
    start = time.perf_counter()
    try:
        with common.forced_backend("extension"), torch.no_grad():
            sims = [factory.simulator(1, device, args.cg_iterations, first=i) for i in range(count)]
            for sim in sims:
                warm_up(sim, device)

            def round_(n):
                for _ in range(n):
                    for sim in sims:
                        sim.step(1)

            seconds, done = common.time_steps(round_, device, args.steps, args.max_seconds)
            iters = common.last_cg_iterations(sims[0])
    except Exception as exc:
        out.update(error=error_text(exc), _wall_s=time.perf_counter() - start)
        release(device)
        return out
    out.update(objects_timed=count, elements=sum(sim_size(s)["elements"] for s in sims),
               nodes=sum(sim_size(s)["nodes"] for s in sims), steps=done, steps_per_s=1.0 / seconds,
               ms_per_step=1e3 * seconds, cg_iterations=iters,
               ms_per_cg_iteration=1e3 * seconds / (iters * count) if iters else None,
               _wall_s=time.perf_counter() - start)
    return out


def main(argv=None):
    args = parse_args(argv)
    device = torch.device(args.device)
    budget = Budget(args.budget_s)
    factory = ObjectFactory(shapes_of(args.shapes))
    bandwidth = copy_bandwidth(device, (1 << 24) if args.quick else (1 << 30))
    meta = metadata(device, dtype="float32", shapes=args.shapes, cg_iterations=args.cg_iterations,
                    copy_bandwidth_GBps={"device": bandwidth / 1e9}, argv=vars(args))
    results = Results(args.out, "batches", "Batches of small objects: one packed Simulator against a Python loop",
                      meta, COLUMNS, notes=["objects x steps/s = objects x steps/s of the run; the loop is timed "
                                            f"over at most {args.loop_objects} objects (its objects column)."])
    estimator = Estimator()
    backends = [b for b in args.backends.split(",") if b]
    loop_cache = None  # the loop over --loop-objects objects: the same for every larger batch
    for count in common.parse_ints(args.objects):
        sims = {}
        floor_bytes = None
        elements_guess = count * sum(6 * a * b * c for a, b, c in shapes_of(args.shapes)) // len(shapes_of(args.shapes))
        for backend in backends:
            key = backend
            rec = record(scene="batch", model="stvk", kind="tet", objects=count, dtype="float32",
                         device=device.type, backend=backend, target_elements=elements_guess)
            limit = {"torch": args.torch_max_elements, "csr": args.assembled_max_elements}.get(backend)
            loop_count = min(count, args.loop_objects)
            size = loop_count if backend == "loop-extension" else count
            source = next((b for b in ("extension", "torch") if b in sims), None)
            why = None
            if limit is not None and elements_guess > limit:
                why = f"size limit: {elements_guess:,} > {limit:,} elements"
            elif estimator.step_seconds(key, size) > args.max_seconds:
                why = f"time limit: one step estimated at {estimator.step_seconds(key, size):.1f} s"
            elif not budget.allows(estimator.wall_seconds(key, size)):
                why = (f"budget: estimated {estimator.wall_seconds(key, size):.0f} s > "
                       f"{max(budget.remaining(), 0):.0f} s left")
            elif backend == "csr" and source is None:
                why = "no batched simulator ran (the matrix is assembled from its model)"
            if why:
                rec["skipped"] = why
                results.add(rec)
                continue
            if backend == "loop-extension" and loop_cache is not None and loop_count == args.loop_objects:
                out = dict(loop_cache, note=f"the loop over {loop_count} objects measured at the first batch "
                                            f">= {loop_count} (its throughput does not depend on the batch size)")
            elif backend == "loop-extension":
                out = run_loop(factory, loop_count, device, args)
                if loop_count == args.loop_objects and "error" not in out:
                    loop_cache = {k: v for k, v in out.items() if k != "_wall_s"}
            elif backend == "csr":
                with common.forced_backend(source):
                    out = run_assembled(sims[source], GRAVITY, "csr", device, args.steps, args.max_seconds)
                out.update(sim_size(sims[source]), assembled_with=source)
            else:
                out = run_simulator(lambda: factory.simulator(count, device, args.cg_iterations), backend, device,
                                    args.steps, args.max_seconds)
            sim = out.pop("_sim", None)
            wall = out.pop("_wall_s", 0.0)
            if sim is not None:
                sims[backend] = sim
                floor_bytes = floor_bytes or common.sim_cg_bytes(sim)["total"]
            rec.update(out)
            if rec.get("steps_per_s"):
                ran = rec.get("objects_timed") or rec["objects"]  # the loop's rounds step objects_timed bodies
                rec["objects_steps_per_s"] = ran * rec["steps_per_s"]
            if backend != "loop-extension":
                common.add_floor(rec, floor_bytes, bandwidth)
            estimator.note(key, size, (rec.get("ms_per_step") or 0.0) / 1e3 or None, wall)
            results.add(rec)
        sims.clear()
        release(device)
    ours = {r["objects"]: r["objects_steps_per_s"] for r in results.records
            if r["backend"] == "extension" and r.get("objects_steps_per_s")}
    for r in results.records:
        if r.get("objects_steps_per_s") and r["backend"] != "extension" and ours.get(r["objects"]):
            r["x_ours"] = ours[r["objects"]] / r["objects_steps_per_s"]
    results.plot(lambda plt: draw(plt, results.records, meta))
    results.finish()
    return results


def draw(plt, records, meta):
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 5))
    for backend in sorted({r["backend"] for r in records}):
        rows = sorted((r["objects"], r["steps_per_s"], r["objects_steps_per_s"]) for r in records
                      if r["backend"] == backend and r.get("steps_per_s"))
        if not rows:
            continue
        b, s, os_ = zip(*rows)
        left.plot(b, s, marker="o", label=backend)
        right.plot(b, os_, marker="o", label=backend)
    for ax, label in ((left, "steps/s"), (right, "objects x steps/s")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("objects in the batch")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    left.set_title(common.plot_title(meta, f"batches, {meta.get('cg_iterations')} CG iterations"), fontsize=9)
    return fig


if __name__ == "__main__":
    main()
