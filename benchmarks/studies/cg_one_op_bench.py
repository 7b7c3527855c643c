"""The CG solve of an implicit step in one op (persistent kernel) against the same CG op by op
(matvec-alpha, cg_update, cg_direction per iteration, replayed from a CUDA graph), for several
chunk sizes of the plan (chunks = the blocks of the reductions), on the SOFA beam and the paper's
beam (hooke tensor form, float32, fixed iteration counts: tol = 0). Times are CUDA-event times of
the solve alone (start + iterations), medians of repeated runs; they include the host's launch of
the one op (~60 us: benchmarks inside a captured step do not pay it). Chunkings with more chunks
than the persistent kernel has resident blocks have no one-op path (solve.persistent_cg_fits).

    python benchmarks/studies/cg_one_op_bench.py [--out DIR]        # on the GPU machine
    python benchmarks/studies/cg_one_op_bench.py --slope            # time per iteration: pipelined vs two-reduction
    ncu --clock-control none -k regex:persistent_cg -c 1 --section WarpStateStats \
        --section SpeedOfLight python benchmarks/studies/cg_one_op_bench.py --once
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # common, measure
import common  # noqa: E402
from step_bench import paper_beam, sofa  # noqa: E402

from tensormass_torch.ops.variants import KernelVariants  # noqa: E402
from tensormass_torch.solver.cg import CGSolver  # noqa: E402

SCENES = {"sofa_beam": sofa, "paper_beam": paper_beam}


def event_time_us(work, repeats: int) -> float:
    """Median CUDA-event time of ``work()`` in microseconds."""
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        work()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end) * 1e3)
    return statistics.median(times)


def measure(scene_name: str, iterations: int, chunk_nodes, repeats: int):
    sim = SCENES[scene_name]("hooke", "cuda", torch.float32)
    system = sim.system
    x, rhs = sim.x, torch.randn_like(sim.x)
    matvec = system.system_matvec(1.0, sim.options.dt ** 2).load(x)
    cg = CGSolver(system.segments, rhs.shape, rhs.dtype, rhs.device, system.free, chunk_nodes=chunk_nodes)
    row = {"scene": scene_name, "nodes": int(x.shape[0]), "chunks": cg.plan.num_chunks,
           "chunk_nodes": int(cg.plan.chunk_start[1] - cg.plan.chunk_start[0]), "cg_iterations": iterations}
    if not cg.solves_in_one_op(matvec):  # more chunks than resident persistent blocks
        return {**row, "one_op_us": None, "op_by_op_us": None, "note": "no one-op path (plan beyond one wave)"}

    def one_op():
        cg.begin(matvec, rhs, 0.0, iterations, iterations)

    def op_by_op():
        cg.start(matvec, rhs, None, 0.0, iterations)
        cg.run_iterations(matvec, iterations, iterations, graph_key="bench")

    for work in (one_op, op_by_op, one_op, op_by_op):  # warm-up (and the graph's capture)
        work()
    torch.cuda.synchronize()
    return {**row, "one_op_us": event_time_us(one_op, repeats), "op_by_op_us": event_time_us(op_by_op, repeats)}


def slope(scene_name: str, repeats: int, counts=(0, 10, 20, 40)):
    """The whole solve's time per iteration: (t(40 iterations) - t(20)) / 20, launch cancelled
    out; for the pipelined CG (hooke_node_solve), then the two-reduction persistent CG
    (hooke_node_cg) with its neighbour cache on and off, then the pipelined again (drift): each
    the solver's configuration (``pipelined``, ``KernelVariants.neighbor_cache``) of its matvec."""
    sim = SCENES[scene_name]("hooke", "cuda", torch.float32)
    system = sim.system
    rhs = torch.randn_like(sim.x)
    cg = CGSolver(system.segments, rhs.shape, rhs.dtype, rhs.device, system.free)
    for pipelined, cache in ((True, True), (False, True), (False, False), (True, True)):
        variants = KernelVariants(neighbor_cache=cache)
        matvec = system.system_matvec(1.0, sim.options.dt ** 2, pipelined, variants).load(sim.x)
        times = {}
        for count in counts:
            work = lambda: cg.begin(matvec, rhs, 0.0, count, count)  # noqa: E731 (a whole solve of count)
            work()
            times[count] = event_time_us(work, repeats)
        per_iteration = (times[counts[-1]] - times[counts[-2]]) / (counts[-1] - counts[-2])
        name = "pipelined CG" if pipelined else f"two-reduction CG, neighbour cache {'on' if cache else 'off'}"
        print(f"{scene_name} ({name}): " + ", ".join(f"{c} it {t:.1f} us" for c, t in times.items())
              + f"; {per_iteration:.1f} us per iteration", flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", default=None)
    ap.add_argument("--repeats", type=int, default=30)
    ap.add_argument("--slope", action="store_true", help="time per iteration of the one-op solve only")
    ap.add_argument("--once", action="store_true",
                    help="one one-op solve of the SOFA beam, 10 iterations (for ncu -k regex:persistent_cg)")
    args = ap.parse_args()
    if args.once:
        sim = sofa("hooke", "cuda", torch.float32)
        rhs = torch.randn_like(sim.x)
        matvec = sim.system.system_matvec(1.0, sim.options.dt ** 2).load(sim.x)
        CGSolver(sim.system.segments, rhs.shape, rhs.dtype, rhs.device, sim.system.free).begin(matvec, rhs, 0.0, 10, 10)
        torch.cuda.synchronize()
        return
    if args.slope:
        for scene_name in SCENES:
            slope(scene_name, args.repeats)
        return
    rows = []
    for scene_name, iterations in (("sofa_beam", 10), ("paper_beam", 25)):
        for chunk_nodes in (64, 128, 256, 512, None):
            row = measure(scene_name, iterations, chunk_nodes, args.repeats)
            row["chunk_setting"] = "auto" if chunk_nodes is None else chunk_nodes
            rows.append(row)
            head = f"{scene_name:10s} chunk {str(row['chunk_setting']):>5s} ({row['chunks']:5d} chunks): "
            if row["one_op_us"] is None:
                print(head + row["note"], flush=True)
                continue
            print(head + f"one op {row['one_op_us']:8.1f} us, op by op {row['op_by_op_us']:8.1f} us, "
                  f"{iterations} it", flush=True)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "cg_one_op.json"), "w") as fh:
            json.dump({"meta": common.metadata("cuda"), "records": rows}, fh, indent=1)


if __name__ == "__main__":
    main()
