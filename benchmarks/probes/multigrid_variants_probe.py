"""Which multigrid cycle is cheapest per converged step: the finest level's smoothing degree
(1, 2 or 3 Chebyshev steps before and after the coarse correction, the coarser levels at 2),
and, on a beam lying on a floor, the floor's penalties carried into the coarse levels (the
default: each change of the penalised nodes reloads them) or left to the finest level's
smoothing alone.

    python benchmarks/probes/multigrid_variants_probe.py --device cuda

A probe (no results file): per scene and variant, CG iterations and ms per step (steady state,
the solve to a relative residual of 1e-6 as in solve_to_tolerance), printed.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "studies"))
import common  # noqa: E402
import torch  # noqa: E402
from solve_to_tolerance import SOLVERS, make_scene  # noqa: E402

from tensormass_torch.solver import multigrid  # noqa: E402


def with_fine_degree(sim, degree: int):
    """The finest level's Chebyshev steps of ``degree`` on the interval the built ones use, and
    the step graphs made again (their kernels hold the coefficients)."""
    hierarchy = sim.system._rest_preconditioner[1][2]
    if not hierarchy.levels:  # (a mesh small enough for the coarse solve alone)
        return
    level = hierarchy.levels[0]
    low = 2.0 / level.steps[0][1] - multigrid.CHEBYSHEV_TOP
    level.steps = multigrid.chebyshev_steps(low, multigrid.CHEBYSHEV_TOP, degree)
    for graphs in sim.system._step_graphs.values():
        graphs._graphs.clear()


def run(scene, young, variant, device, steps, elements):
    sim = make_scene(scene, elements, young, device, torch.float32)
    sim.options = dataclasses.replace(sim.options, **SOLVERS["multigrid"])
    original_load = multigrid.Multigrid.load
    if variant == "penalties on the finest level only":
        multigrid.Multigrid.load = lambda self, node_stiffness, free=None: original_load(self, None, free)
    try:
        sim.step(1)
        if variant.startswith("fine degree"):
            with_fine_degree(sim, int(variant.split()[-1]))
        sim.step(5)
        common.sync(device)
        start = time.perf_counter()
        iterations = []
        for _ in range(steps):
            sim.step(1)
            iterations.append(int(sim.last_report.cg[0].iterations.max()))
        common.sync(device)
        per_step = (time.perf_counter() - start) / steps
    finally:
        multigrid.Multigrid.load = original_load
    print(f"{scene:10s} E={young:.0e} {variant:36s} mean it {sum(iterations) / len(iterations):5.1f}  "
          f"{per_step * 1e3:7.2f} ms/step", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--elements", type=int, default=307_200, help="paper beam tets (the SOFA beam's: 101,250)")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    for young in (1e5, 1e7):
        for variant in ("fine degree 1", "fine degree 2", "fine degree 3"):
            run("paper_beam", young, variant, device, args.steps, args.elements)
    for variant in ("default", "penalties on the finest level only", "fine degree 1"):
        run("sofa_beam", 1e3, variant, device, args.steps, args.elements)


if __name__ == "__main__":
    main()
