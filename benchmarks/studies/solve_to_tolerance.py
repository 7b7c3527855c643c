"""Time to a converged step: preconditioned CG against today's fixed-budget steps, and how the
multigrid's iteration count grows with the mesh.

    python benchmarks/studies/solve_to_tolerance.py --device cuda --out $OUT
    ... --quick                                  # tiny sizes, seconds on a CPU

Part 1 (solve_to_tolerance.md): on the paper's 307,200-tet beam (hooke, E = 1e5 and 1e7, dt =
0.01, clamped, gravity) and SOFA's 101,250-tet beam (hooke, its plane), implicit Euler steps
solved to a relative residual of 1e-6 with each preconditioner (none, jacobi, multigrid, and
cholesky: the rest matrix's sparse Cholesky factor, the direct-solver baseline; "+warm": each
step's CG started from the extrapolation of the steps before, ``warm_start=True``; "+project":
from the projection on the last steps' solutions, ``warm_start="project"``; "mixed": a float64
state whose solves are iterative refinement with float32 corrections, ``precision="mixed"``,
whatever ``--dtype`` says), and
the same scene's fixed-budget steps of 25 and 10 CG iterations (tol 0: what the speed
benchmarks time). Per row: CG iterations of the last timed step and their mean over the 5
steps after, the last step's relative residual (the CG's own:
the true residual for none and multigrid, Jacobi's scaled one), ms per step (steady state, after
``--settle`` steps, 5 by default, that build the multigrid hierarchy and capture the CUDA graphs;
a projected warm start's basis fills over its first ~30 steps, so its steady state needs
``--settle 40``) and the ratio to the
25-iteration step of the same scene, and the multigrid's and the factorisation's set-up seconds
(the first step less a steady one).

Part 2 (multigrid_scaling.md): the paper beam's proportions from the SOFA beam's size to about
5M tets (``--sizes``), E = 1e5, tolerance 1e-6: the multigrid's iterations per step, levels,
set-up seconds and ms per step, beside the unpreconditioned CG's iterations on the same step.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, metadata, record, release, time_steps

from tensormass_torch.sim.builtin import sofa_beam

SOLVERS = {  # name -> StepOptions changes
    "25 iterations": dict(cg_tol=0.0, cg_max_iter=25, require_convergence=False, check_every=1000,
                          preconditioner="none"),
    "10 iterations": dict(cg_tol=0.0, cg_max_iter=10, require_convergence=False, check_every=1000,
                          preconditioner="none"),
    "none": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8, preconditioner="none"),
    "jacobi": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8,
                   preconditioner="jacobi"),
    "none+warm": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8,
                      preconditioner="none", warm_start=True),
    "multigrid": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=2,
                      preconditioner="multigrid"),
    "multigrid+warm": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=2,
                           preconditioner="multigrid", warm_start=True),
    "none+project": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8,
                         preconditioner="none", warm_start="project"),
    "multigrid+project": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=2,
                              preconditioner="multigrid", warm_start="project"),
    "cholesky": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=2,
                     preconditioner="cholesky"),
    # a float64 state (whatever --dtype says) whose solves are float32 corrections (solver.refine)
    "mixed": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8, preconditioner="none",
                  precision="mixed"),
    "mixed+project": dict(cg_tol=1e-6, cg_max_iter=20000, require_convergence=False, check_every=8,
                          preconditioner="none", warm_start="project", precision="mixed"),
}

COLUMNS = [("scene", "scene", None), ("young", "E", ".0e"), ("elements", "elements", None),
           ("solver", "solver", None), ("cg_iterations", "CG it", None), ("cg_iterations_mean", "mean CG it", ".1f"),
           ("relative_residual", "rel. residual", ".1e"), ("ms_per_step", "ms/step", ".2f"),
           ("x_25", "x 25-it step", ".2f"), ("setup_s", "set-up s", ".2f"), ("levels", "levels", None),
           ("error", "error", None)]
SCALING_COLUMNS = [("elements", "elements", None), ("nodes", "nodes", None), ("levels", "levels (unknowns)", None),
                   ("operator_complexity", "op. complexity", ".2f"), ("cg_iterations", "MG CG it", None),
                   ("plain_iterations", "plain CG it", None), ("setup_s", "set-up s", ".1f"),
                   ("ms_per_step", "MG ms/step", ".2f"), ("error", "error", None)]


def make_scene(scene: str, elements: int, young: float, device, dtype):
    if scene == "sofa_beam":
        sim = sofa_beam(model="hooke", device=device, dtype=dtype,
                        scale=1 if elements >= 100_000 else 5).simulator
    else:
        sim = common.cantilever_sim("tet", "hooke", elements, device, dtype, young=young)[0]
    return sim


def last_report(sim):
    report = sim.last_report.cg[0]
    return int(report.iterations.max()), float(report.relative_residual.max())


def measure(scene: str, elements: int, young: float, solver: str, device, dtype, steps: int, max_seconds: float,
            settle: int = 5):
    if SOLVERS[solver].get("precision") == "mixed":  # (its residuals, state and right-hand side: float64)
        dtype = torch.float64
    sim = make_scene(scene, elements, young, device, dtype)
    sim.options = dataclasses.replace(sim.options, **SOLVERS[solver])
    common.sync(device)
    start = time.perf_counter()
    sim.step(1)
    common.sync(device)
    first = time.perf_counter() - start
    sim.step(settle - 1)  # (the graphs of the iteration counts the next steps take are captured here)
    per_step, _ = time_steps(sim.step, device, steps, max_seconds)
    iterations, residual = last_report(sim)
    counts = []
    for _ in range(5):  # (warm starts vary from step to step)
        sim.step(1)
        counts.append(last_report(sim)[0])
    built = sim.system._rest_preconditioner
    hierarchy = None if built is None or not hasattr(built[1][2], "sizes") else built[1][2]
    setup = None if built is None else first - per_step
    return dict(scene=scene, young=young, elements=sim.model.num_elements, nodes=sim.model.num_nodes, solver=solver,
                cg_iterations=iterations, cg_iterations_mean=sum(counts) / len(counts), relative_residual=residual,
                ms_per_step=per_step * 1e3,
                setup_s=setup,
                levels=None if hierarchy is None else len(hierarchy.sizes),
                operator_complexity=None if hierarchy is None else hierarchy.operator_complexity,
                level_sizes=None if hierarchy is None else hierarchy.sizes), sim


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--elements", type=int, default=None, help="paper beam tets (default 307,200)")
    parser.add_argument("--sizes", default=None, help="tets of the scaling part (default 101k .. 4.9M)")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--parts", default="solvers,scaling")
    parser.add_argument("--solvers", default=",".join(SOLVERS), help="rows of part 1, of: " + ", ".join(SOLVERS))
    parser.add_argument("--scenes", default="paper_beam:1e5,paper_beam:1e7,sofa_beam",
                        help="part 1's scenes: paper_beam:E and sofa_beam")
    parser.add_argument("--max-seconds", type=float, default=5.0)
    parser.add_argument("--budget-s", type=float, default=None)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--settle", type=int, default=5,
                        help="steps before the timed ones (a projected warm start fills its basis over ~30)")
    parser.add_argument("--name", default="solve_to_tolerance", help="part 1's results file name")
    args = parser.parse_args(argv)
    common.fill_defaults(args, dict(elements=307_200, sizes="101250,307200,1228800,2457600,4915200", steps=20),
                         dict(elements=4_800, sizes="4800,38400", steps=3))
    device = torch.device(args.device)
    dtype = getattr(torch, args.dtype)
    budget = Budget(args.budget_s)
    parts = args.parts.split(",")
    meta = metadata(device, dtype=str(dtype))
    if "solvers" in parts:
        results = Results(args.out, args.name, "Time to a converged step (relative residual 1e-6) "
                          "against fixed CG budgets", meta, COLUMNS,
                          notes=[f"hooke, implicit Euler, {args.dtype}; steady-state ms per step after "
                                 f"{args.settle} steps."])
        scenes = []
        for item in args.scenes.split(","):
            name, _, young = item.partition(":")
            if name == "sofa_beam":
                scenes.append(("sofa_beam", 101_250 if not args.quick else 1_000, 1e3))
            elif name == "paper_beam":
                scenes.append(("paper_beam", args.elements, float(young or 1e5)))
            else:
                parser.error(f"unknown scene {name!r} in --scenes")
        solvers = [name.strip() for name in args.solvers.split(",") if name.strip()]
        unknown = sorted(set(solvers) - set(SOLVERS))
        if unknown:
            parser.error(f"unknown solvers {unknown} in --solvers; known: {', '.join(SOLVERS)}")
        for scene, elements, young in scenes:
            base = None
            for solver in solvers:
                if not budget.allows(10.0):
                    results.add(record(scene=scene, young=young, solver=solver, skipped="budget"))
                    continue
                try:
                    rec, sim = measure(scene, elements, young, solver, device, dtype, args.steps, args.max_seconds,
                                       max(args.settle, 1))
                    del sim
                except Exception as exc:  # a failed row says why; the others still run
                    rec = dict(scene=scene, young=young, solver=solver, error=common.error_text(exc))
                if solver == "25 iterations":
                    base = rec.get("ms_per_step")
                if base and rec.get("ms_per_step"):
                    rec["x_25"] = rec["ms_per_step"] / base
                results.add(record(**rec))
                release(device)
        results.finish()
    if "scaling" in parts:
        results = Results(args.out, "multigrid_scaling", "Multigrid iterations against mesh size (paper beam "
                          "proportions, hooke, E = 1e5, relative residual 1e-6)", meta, SCALING_COLUMNS)
        for elements in common.parse_ints(args.sizes):
            if not budget.allows(20.0):
                results.add(record(elements=elements, skipped="budget"))
                continue
            try:
                rec, sim = measure("paper_beam", elements, 1e5, "multigrid", device, dtype, max(args.steps // 4, 2),
                                   args.max_seconds)
                plain = dataclasses.replace(sim.options, **SOLVERS["none"])
                sim.options = plain
                sim.step(1)
                rec["plain_iterations"] = last_report(sim)[0]
                rec["levels"] = " / ".join(str(n) for n in rec.pop("level_sizes"))
                del sim
            except Exception as exc:
                rec = dict(elements=elements, error=common.error_text(exc))
            results.add(record(**rec))
            release(device)
        results.finish()


if __name__ == "__main__":
    main()
