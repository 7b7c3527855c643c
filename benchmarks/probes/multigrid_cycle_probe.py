"""Where a multigrid-preconditioned step's time goes: one V-cycle, its levels' products, the
step's own product and one preconditioned CG iteration, each captured in a CUDA graph and
replayed (ms per replay), and a profiler table of the kernels of one eager V-cycle; then whole
steps: ms per step, which of the step's phases replay a graph and which run eagerly, the host's
time by function (cProfile) and the profiler's table of a few steps.

    python benchmarks/probes/multigrid_cycle_probe.py --device cuda [--elements 307200] [--young 1e5]
        [--dtype float32] [--warm-start none]

A probe (no results file): it prints what it measured.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402
import torch  # noqa: E402

from tensormass_torch.ops.multigrid import bsr_gemv, chebyshev  # noqa: E402


def replay_ms(work, device, repeats: int = 50) -> float:
    """Milliseconds per replay of ``work`` captured in a CUDA graph (on the CPU: per eager call)."""
    import time

    work()
    if device.type != "cuda":
        start = time.perf_counter()
        for _ in range(repeats):
            work()
        return (time.perf_counter() - start) / repeats * 1e3
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        work()
    graph.replay()
    torch.cuda.synchronize()
    begin, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    begin.record()
    for _ in range(repeats):
        graph.replay()
    end.record()
    torch.cuda.synchronize()
    return begin.elapsed_time(end) / repeats


def step_profile(sim, device, steps: int = 20):
    """Whole steps of ``sim``: ms per step, the step graphs' phases (graph or eager), cProfile's
    functions by total time and the profiler's table of a few steps."""
    import cProfile
    import pstats
    import time

    common.sync(device)
    start = time.perf_counter()
    for _ in range(steps):
        sim.step()
    common.sync(device)
    print(f"\n{(time.perf_counter() - start) / steps * 1e3:.3f} ms a step over {steps} steps; iterations "
          f"{int(sim.last_report.cg[0].iterations.max())}")
    for graphs in sim.system._step_graphs.values():
        phases = {str(key): ("eager" if graph is False else "graph") for key, graph in graphs._graphs.items()}
        print("phases:", phases)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(steps):
        sim.step()
    common.sync(device)
    profiler.disable()
    pstats.Stats(profiler).sort_stats("tottime").print_stats(25)
    if device.type == "cuda":
        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
            for _ in range(3):
                sim.step()
            torch.cuda.synchronize()
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--elements", type=int, default=307_200)
    parser.add_argument("--young", type=float, default=1e5)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--warm-start", default="none", help="StepOptions.warm_start (none, extrapolate, project)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    sim = common.cantilever_sim("tet", "hooke", args.elements, device, dtype, young=args.young)[0]
    sim.options = dataclasses.replace(sim.options, cg_tol=1e-6, cg_max_iter=20000, require_convergence=False,
                                      check_every=2, preconditioner="multigrid", warm_start=args.warm_start)
    sim.step(3)
    solve = sim.system._multigrid_solve
    multigrid = solve.multigrid
    print(f"{sim.model.num_elements} tets, {sim.model.num_nodes} nodes; levels {multigrid.sizes}; "
          f"iterations {int(sim.last_report.cg[0].iterations.max())}")
    gen = torch.Generator().manual_seed(0)
    r = (torch.randn(sim.x.shape, generator=gen, dtype=dtype).to(device) * sim.system.free).contiguous()
    graphs = [g for g in sim.system._step_graphs.values() if g.preconditioned]
    matvec = graphs[0].matvec if graphs else sim.system.system_matvec(1.0, 1e-4)
    rows = [("V-cycle", lambda: solve(r)), ("step product (fine matvec)", lambda: matvec(r))]
    for depth, level in enumerate(multigrid.levels):
        x = torch.randn(level.size, generator=gen, dtype=dtype).to(device)
        b = torch.randn(level.size, generator=gen, dtype=dtype).to(device)
        coarse = torch.randn(level.prolong.shape[1], generator=gen, dtype=dtype).to(device)
        step, out = torch.zeros_like(x), torch.zeros_like(x)
        rows += [(f"level {depth} A x ({level.matrix.values.shape[0]} blocks {level.matrix.block})",
                  lambda level=level, x=x, b=b: bsr_gemv(level.matrix, x, b, alpha=-1.0, beta=1.0)),
                 (f"level {depth} chebyshev step", lambda level=level, x=x, b=b, step=step, out=out: chebyshev(
                     b, level.inverse_diagonal, step, out, 0.3, 0.5, x=x, matrix=level.matrix)),
                 (f"level {depth} restrict ({level.restrict.values.shape[0]} blocks {level.restrict.block})",
                  lambda level=level, x=x: bsr_gemv(level.restrict, x)),
                 (f"level {depth} prolong ({level.prolong.values.shape[0]} blocks {level.prolong.block})",
                  lambda level=level, x=x, coarse=coarse: bsr_gemv(level.prolong, coarse, x, out=x))]
    cb = torch.randn(multigrid.coarse_inverse.shape[0], generator=gen, dtype=dtype).to(device)
    rows.append(("coarsest dense solve", lambda: multigrid.coarse_inverse @ cb))
    if graphs:
        g = graphs[0]
        pre = sim.system._multigrid_solve
        rows.append(("one PCG iteration", lambda: g.cg.iterate(g.matvec, 1, 10 ** 9, pre)))
    for name, work in rows:
        print(f"{name:60s} {replay_ms(work, device):8.4f} ms")
    if device.type == "cuda":
        from torch.profiler import ProfilerActivity, profile

        solve(r)
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            for _ in range(5):
                solve(r)
            torch.cuda.synchronize()
        print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25))
    step_profile(sim, device)


if __name__ == "__main__":
    main()
