"""Where a mixed-precision step's time goes: the paper beam (307,200 tets, hooke, tolerance 1e-6,
warm_start="project"), float64 state, ``precision="mixed"`` against ``"full"``: ms a step over 20
steps after 40 (stepped one at a time) and their iterations, which of the step's phases ran as CUDA graphs, and torch.profiler's tables of 5
steps (CUDA kernels, then host time) to stdout.

    python benchmarks/probes/mixed_step_probe.py [--young 1e5 1e7] [--elements 307200] > mixed_profile.txt
    ... --inner-tol 1e-3 1e-4 --no-profile     # the corrections' tolerance (Refinement.inner_tol), each a run
"""
import argparse
import dataclasses
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402

from tensormass_torch.solver import refine  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--young", type=float, nargs="+", default=[1e5, 1e7])
    parser.add_argument("--elements", type=int, default=307_200)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--no-profile", action="store_true", help="times only")
    parser.add_argument("--inner-tol", type=float, nargs="+", default=[refine.INNER_TOL],
                        help="the float32 corrections' relative tolerance (one mixed run each)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    times = {}
    for young in args.young:
        for precision, inner in [("mixed", tol) for tol in args.inner_tol] + [("full", None)]:
            label = precision if inner is None or len(args.inner_tol) == 1 else f"mixed, inner {inner:g}"
            sim = common.cantilever_sim("tet", "hooke", args.elements, device, torch.float64, young=young)[0]
            sim.options = dataclasses.replace(sim.options, cg_tol=1e-6, cg_max_iter=20000, require_convergence=False,
                                              preconditioner="none", warm_start="project", precision=precision)
            if inner is not None:  # (before the first step: the rounds' graphs capture it)
                sim.system.refinement(sim.options).inner_tol = inner
            sim.step(40)
            common.sync(device)
            start, steps, iterations = time.perf_counter(), 20, []
            for _ in range(steps):  # (a step's report is on the host already: reading it costs nothing)
                sim.step()
                iterations.append(int(sim.last_report.cg[0].iterations.max()))
            common.sync(device)
            ms = times[(young, label)] = (time.perf_counter() - start) / steps * 1e3
            phases = ", ".join(f"{key}: {'eager' if graph is False else 'graph'}"
                               for graphs in sim.system._step_graphs.values() for key, graph in graphs._graphs.items())
            print(f"E {young:g} {label}: {ms:.3f} ms/step, {sum(iterations) / steps:.1f} iterations a step "
                  f"({min(iterations)}-{max(iterations)}); "
                  f"phases {phases or 'eager'}", flush=True)
            if not args.no_profile and device.type == "cuda":
                with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                    sim.step(5)
                    common.sync(device)
                for key in ("cuda_time_total", "cpu_time_total"):
                    print(prof.key_averages().table(sort_by=key, row_limit=18, max_name_column_width=70), flush=True)
            del sim
            common.release(device)
    return times


if __name__ == "__main__":
    main()
