"""Where a mixed-precision step's time goes, and what it costs against the float32 25-iteration
step: the paper beam (307,200 tets, hooke, tolerance 1e-6, warm_start="project"), a float64 state
with ``precision="mixed"`` and ``"full"``, beside the float32 fixed-budget step (25 iterations,
tol 0, what the speed benchmarks time), each a fresh simulator, ms a step over 20 steps after 40
(``sim.step(20)``, as the benchmarks time them: the 25-iteration steps and the mixed ones
chained; the float64 projected steps are not) and the
iterations of 20 steps after them (one at a time), the runs alternated ``--repeats`` times in one
process (the medians and the ratio to the 25-iteration step at the end); which of the step's
phases ran as CUDA graphs; and torch.profiler's tables of 5 steps (CUDA kernels, then host time)
of the first repeat to stdout.

    python benchmarks/probes/mixed_step_probe.py [--young 1e5 1e7] [--elements 307200] > mixed_profile.txt
    ... --inner-tol 1e-3 1e-4 --no-profile     # the corrections' tolerance (Refinement.inner_tol), each a run
    ... --repeats 3 --no-profile                 # the ratio, alternated three times
"""
import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402

from tensormass_torch.solver import refine  # noqa: E402

BASELINE = "float32, 25 iterations"


def run(young: float, elements: int, device, label: str, inner, profiled: bool) -> float:
    """ms a step of one configuration (a fresh simulator), printed with its iterations."""
    if label == BASELINE:  # (cantilever_sim's own settings: tol 0, 25 iterations, no check)
        sim = common.cantilever_sim("tet", "hooke", elements, device, torch.float32, young=young)[0]
    else:
        precision = "full" if inner is None else "mixed"
        sim = common.cantilever_sim("tet", "hooke", elements, device, torch.float64, young=young)[0]
        sim.options = dataclasses.replace(sim.options, cg_tol=1e-6, cg_max_iter=20000, require_convergence=False,
                                          preconditioner="none", warm_start="project", precision=precision)
        if inner is not None:  # (before the first step: the rounds' graphs capture it)
            sim.system.refinement(sim.options).inner_tol = inner
    sim.step(40)
    common.sync(device)
    start, steps, iterations = time.perf_counter(), 20, []
    sim.step(steps)  # (as the benchmarks time steps: chains of 8 a graph where they chain, one read a chain)
    common.sync(device)
    ms = (time.perf_counter() - start) / steps * 1e3
    for _ in range(steps):  # their iterations, one step at a time (untimed)
        sim.step()
        iterations.append(int(sim.last_report.cg[0].iterations.max()))
    phases = ", ".join(f"{key}: {'eager' if graph is False else 'graph'}"
                       for graphs in sim.system._step_graphs.values() for key, graph in graphs._graphs.items())
    print(f"E {young:g} {label}: {ms:.3f} ms/step, {sum(iterations) / steps:.1f} iterations a step "
          f"({min(iterations)}-{max(iterations)}); phases {phases or 'eager'}", flush=True)
    if profiled and device.type == "cuda":
        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            sim.step(5)
            common.sync(device)
        for key in ("cuda_time_total", "cpu_time_total"):
            print(prof.key_averages().table(sort_by=key, row_limit=18, max_name_column_width=70), flush=True)
    del sim
    common.release(device)
    return ms


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--young", type=float, nargs="+", default=[1e5, 1e7])
    parser.add_argument("--elements", type=int, default=307_200)
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--no-profile", action="store_true", help="times only")
    parser.add_argument("--inner-tol", type=float, nargs="+", default=[refine.INNER_TOL],
                        help="the float32 corrections' relative tolerance (one mixed run each)")
    parser.add_argument("--repeats", type=int, default=1, help="the runs alternated this many times")
    args = parser.parse_args(argv)
    if args.repeats < 1:
        parser.error(f"--repeats must be >= 1, got {args.repeats}")
    device = torch.device(args.device)
    configurations = [(BASELINE, None)] + [
        ("mixed" if len(args.inner_tol) == 1 else f"mixed, inner {tol:g}", tol) for tol in args.inner_tol]
    configurations.append(("float64, full", None))
    times = {}
    for repeat in range(args.repeats):
        for young in args.young:
            for label, inner in configurations:
                ms = run(young, args.elements, device, label, inner, not args.no_profile and repeat == 0)
                times.setdefault((young, label), []).append(ms)
    medians = {key: statistics.median(values) for key, values in times.items()}
    for (young, label), median in medians.items():
        ratio = median / medians[(young, BASELINE)]
        print(f"E {young:g} {label}: median {median:.3f} ms a step of {len(times[(young, label)])}, "
              f"{ratio:.2f}x the float32 25-iteration step", flush=True)
    return medians


if __name__ == "__main__":
    main()
