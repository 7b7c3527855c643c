"""Scale on one device: peak memory a tetrahedron over construction and the first steps, the
memory a scene keeps while it steps, and set-up seconds, against element count.

    python benchmarks/studies/setup_memory.py --device cuda --out DIR
    python benchmarks/studies/setup_memory.py --quick --device cpu --out DIR       # seconds

Scene: the paper beam's proportions (clamped at x = 0, gravity), float32, 25 CG iterations a
step (SOFA's fixed budget), through the public API (``tm.Simulator``). Each (model, size) runs
in a process of its own, so each peak is its own:

- construction peak: the most memory allocated while ``tm.Simulator(...)`` runs;
- peak: the most over construction and the first ``--steps`` steps (what the first step builds
  lazily included: node graphs, captured graphs);
- held: what stays allocated after those steps (the steady state);
- set-up s: construction plus the first step (synchronised), what a user waits for before the
  simulator steps at speed; ms/step: the steps after it.

On CUDA the memory is ``torch.cuda.max_memory_allocated`` / ``memory_allocated`` (the caching
allocator's view: what the scene's tensors need). On the CPU it is the process's resident set
(peak from ``getrusage``, glibc told to return large blocks to the system at once:
``MALLOC_MMAP_THRESHOLD_``), less the resident set before construction: close to the tensors'
bytes, not the same. Sizes that do not fit end as a row with the error.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import torch
from common import Results, metadata

COLUMNS = [("model", "model", None), ("elements", "elements", None),
           ("construction_peak_b", "construction peak B/tet", ".0f"), ("peak_b", "peak B/tet", ".0f"),
           ("held_b", "held B/tet", ".0f"), ("peak_over_held", "peak / held", ".2f"),
           ("setup_s", "set-up s", ".3g"), ("ms_per_step", "ms/step", ".3g"), ("peak_gb", "peak GB", ".3g")]


def _resident() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def _peak_resident() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024


def measure(model: str, elements: int, device: torch.device, steps: int) -> dict:
    """One (model, size) in this process: the row's numbers (bytes a tet, seconds)."""
    import tensormass_torch as tm

    cuda = device.type == "cuda"
    mesh = tm.beam_mesh(*common.tet_dims(elements), size=common.PAPER_SIZE, dtype=torch.float32)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model),
                   fixed=mesh.vertices[:, 0] <= 1e-6)
    count = mesh.num_elements

    def sync():
        if cuda:
            torch.cuda.synchronize(device)

    if cuda:
        torch.zeros(1, device=device)  # the context before the clock and the counters
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
    else:
        base = _resident()
    start = time.perf_counter()
    sim = tm.Simulator([body], dt=0.01, cg_tol=0.0, cg_max_iter=25, require_convergence=False,
                       device=device, dtype=torch.float32)
    sync()
    construction_peak = torch.cuda.max_memory_allocated(device) if cuda else _peak_resident()
    sim.step(1)
    sync()
    setup = time.perf_counter() - start
    tick = time.perf_counter()
    sim.step(steps - 1)
    sync()
    per_step = (time.perf_counter() - tick) / max(steps - 1, 1)
    peak = torch.cuda.max_memory_allocated(device) if cuda else _peak_resident()
    held = torch.cuda.memory_allocated(device) if cuda else _resident()
    return dict(model=model, elements=count, construction_peak_b=(construction_peak - base) / count,
                peak_b=(peak - base) / count, held_b=(held - base) / count,
                peak_over_held=(peak - base) / max(held - base, 1), setup_s=setup, ms_per_step=per_step * 1e3,
                peak_gb=(peak - base) / 1e9)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results/scale")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--models", default=None, help="comma list of hooke, stvk, corotational")
    parser.add_argument("--elements", default=None, help="tets (comma list)")
    parser.add_argument("--steps", type=int, default=None, help="steps after construction (the first timed apart)")
    parser.add_argument("--timeout", type=float, default=900.0, help="seconds a (model, size) may take")
    parser.add_argument("--one", default=None, help=argparse.SUPPRESS)  # "model,elements": one row, as JSON
    args = parser.parse_args(argv)
    common.fill_defaults(args, dict(models="hooke,stvk,corotational", elements="1000000,5000000,20000000",
                                    steps=12), dict(models="hooke,stvk", elements="3000", steps=3))
    device = torch.device(args.device)
    if args.one:
        model, elements = args.one.split(",")
        print(json.dumps(measure(model, int(elements), device, args.steps)))
        return
    results = Results(args.out, "setup_memory", "Peak memory and set-up time against element count",
                      metadata(device), COLUMNS,
                      notes=[f"paper-beam proportions, float32, 25 CG iterations a step, {args.steps} steps; "
                             f"{'CUDA allocator' if device.type == 'cuda' else 'CPU resident set'} bytes a tet."])
    env = {**os.environ, "MALLOC_MMAP_THRESHOLD_": "65536"}
    for model in [m for m in args.models.split(",") if m]:
        for elements in [int(v) for v in args.elements.split(",") if v]:
            command = [sys.executable, __file__, "--one", f"{model},{elements}", "--device", args.device,
                       "--steps", str(args.steps)]
            try:
                done = subprocess.run(command, capture_output=True, text=True, timeout=args.timeout, env=env)
                lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
                if done.returncode == 0 and lines:
                    results.add(json.loads(lines[-1]))
                else:
                    error = (done.stderr.strip().splitlines() or ["no output"])[-1]
                    results.add(dict(model=model, elements=elements, error=error[:200]))
            except subprocess.TimeoutExpired:
                results.add(dict(model=model, elements=elements, error=f"over {args.timeout:g} s"))


if __name__ == "__main__":
    main()
