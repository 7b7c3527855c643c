"""Warm starts on SOFA's beam lying on its floor: ms a step (one step at a time) and CG
iterations from zero, from the extrapolation and from the projection, which of the captured
step's phases replay a graph, and the host's time by function (cProfile) for the projected steps.

    python benchmarks/probes/warm_start_probe.py --device cuda [--dtype float32] [--settle 40]
                                                 [--classic] [--no-profile]

``--classic``: the warm starts also with ``pipelined=False`` (the classic persistent CG after the
start, as before the pipelined CG went on from a guess), in the same process. A probe (no results
file): it prints what it measured and returns it (``{name: (ms a step, iterations a step)}``).
"""
from __future__ import annotations

import argparse
import cProfile
import dataclasses
import pstats
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402
import torch  # noqa: E402

from tensormass_torch.sim.builtin import sofa_beam  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--settle", type=int, default=40, help="steps before the timed ones")
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--classic", action="store_true", help="the warm starts with pipelined=False too")
    parser.add_argument("--no-profile", action="store_true", help="no cProfile of the projected steps")
    args = parser.parse_args(argv)
    device, dtype = torch.device(args.device), getattr(torch, args.dtype)
    runs = [("none", True), ("extrapolate", True), ("project", True)]
    if args.classic:
        runs += [("extrapolate", False), ("project", False)]
    measured = {}
    for warm, pipelined in runs:
        sim = sofa_beam(model="hooke", device=device, dtype=dtype, scale=1 if device.type == "cuda" else 5).simulator
        sim.options = dataclasses.replace(sim.options, cg_tol=1e-6, cg_max_iter=20000, require_convergence=False,
                                          check_every=8, preconditioner="none", warm_start=warm, pipelined=pipelined)
        for _ in range(args.settle):
            sim.step()
        common.sync(device)
        start = time.perf_counter()
        iterations = []
        for _ in range(args.steps):
            sim.step()
            iterations.append(int(sim.last_report.cg[0].iterations.max()))
        common.sync(device)
        name = warm if pipelined else f"{warm}, classic CG"
        measured[name] = ((time.perf_counter() - start) / args.steps * 1e3, iterations)
        print(f"{name}: {measured[name][0]:.2f} ms a step (one at a time); iterations {iterations[:6]}")
        for graphs in sim.system._step_graphs.values():
            print("  phases", {str(k): ("eager" if g is False else "graph") for k, g in graphs._graphs.items()})
        if warm == "project" and pipelined and not args.no_profile:
            profiler = cProfile.Profile()
            profiler.enable()
            for _ in range(10):
                sim.step()
            common.sync(device)
            profiler.disable()
            pstats.Stats(profiler).sort_stats("tottime").print_stats(14)
    return measured


if __name__ == "__main__":
    main()
