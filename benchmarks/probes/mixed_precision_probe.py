"""What a mixed-precision converged step would take on the paper beam: the state, the right-hand
side, the projected warm start and the residuals in float64, the CG in float32 (iterative
refinement), against float64 CG from the same kind of guess.

    python benchmarks/probes/mixed_precision_probe.py [--young 1e5 1e7] [--elements 38400]
                                                      [--steps 40] [--settle 10] [--inner-tol 1e-3] [--vectors 32]
                                                      [--out benchmarks/results/preconditioners]

Why: a float32 step cannot converge to 1e-6 of its float64 counterpart (its right-hand side, the
small difference of large forces near equilibrium, is new rounding at every step, 1e-4 of itself
on the paper beam at E = 1e5: ``float32_rhs_probe.py``), and a float64 step costs float64
iterations. Refinement keeps what needs float64 in float64 and does the iterations in float32:

    x = x0 (the projection of b on the last solutions, ``solver.guess.SolutionSpace``, float64)
    repeat:  r = b - A x (float64);  stop if |r| <= tol |b|
             d = float32 CG on A d = r, from 0, to max(inner_tol, tol |b| / (2 |r|)) of |r|
             x = x + d

The scene is the paper beam's (``common.cantilever_sim``: hooke, clamped, gravity, dt = 0.01),
stepped through its assembled matrix (``assembled.AssembledStepper``'s equations) along the exact
trajectory (each step solved to 1e-13 in float64); each way keeps its own projection space, fed
with its own 1e-6 solutions, as the simulator's ``warm_start="project"`` does. Per step: the
guess's relative residual, float64 CG iterations to ``tol`` = 1e-6, and the refinement's float32
iterations and float64 products (one a residual); the means over the steps after ``--settle``.
Iterations on the CPU; what they cost on a GPU is the float32 and float64 iteration times of the
same beam (``solve_to_tolerance.md``). Writes ``mixed_precision.json`` to ``--out``.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402
from assembled import AssembledStepper, sparse_matvec  # noqa: E402

from tensormass_torch.solver.guess import PROJECTION_VECTORS, SolutionSpace  # noqa: E402

TOL = 1e-6


def cg(product, rhs: torch.Tensor, x: torch.Tensor, tol: float, reference: float, max_iter: int = 100_000):
    """Plain CG on A x = ``rhs`` from ``x`` (in ``rhs``'s dtype), until |r| <= ``tol`` *
    ``reference``: (x, iterations)."""
    r = rhs - product(x)
    p, rr, k = r.clone(), (r * r).sum(), 0
    while k < max_iter and float(rr.sqrt()) > tol * reference:
        ap = product(p)
        alpha = rr / (p * ap).sum()
        x, r = x + alpha * p, r - alpha * ap
        new = (r * r).sum()
        p, rr, k = r + (new / rr) * p, new, k + 1
    return x, k


def refine(product64, product32, rhs: torch.Tensor, x: torch.Tensor, inner_tol: float, most: int = 50):
    """Iterative refinement from ``x`` to ``TOL``: (x, float32 iterations per correction,
    float64 products, the end's relative residual)."""
    norm = float(torch.linalg.vector_norm(rhs))
    inner = []
    while True:
        r = rhs - product64(x)
        left = float(torch.linalg.vector_norm(r))
        if left <= TOL * norm or len(inner) >= most:
            return x, inner, len(inner) + 1, left / norm
        wanted = max(inner_tol, 0.5 * TOL * norm / left)
        r32 = r.to(torch.float32)
        d, k = cg(product32, r32, torch.zeros_like(r32), wanted, left)
        x, _ = x + d.to(torch.float64), inner.append(k)


def measure(young: float, elements: int, steps: int, settle: int, inner_tol: float,
            vectors: int = PROJECTION_VECTORS) -> dict:
    sim, gravity = common.cantilever_sim("tet", "hooke", elements, "cpu", torch.float64, young=young)
    stepper = AssembledStepper(sim, gravity)
    stepper.assemble(stepper.x)
    matrix64 = stepper._matrix  # hooke: assembled once
    product64 = sparse_matvec(matrix64)
    product32 = sparse_matvec(torch.sparse_csr_tensor(matrix64.crow_indices(), matrix64.col_indices(),
                                                      matrix64.values().to(torch.float32), matrix64.shape))

    spaces = {way: SolutionSpace(stepper.x, sim.segments, vectors) for way in ("float64", "mixed")}
    h, rows = stepper.h, []
    for step in range(steps):
        rhs = stepper.rhs()
        norm = float(torch.linalg.vector_norm(rhs))
        guess64, guess_mixed = spaces["float64"].guess(rhs), spaces["mixed"].guess(rhs)
        solution64, iterations64 = cg(product64, rhs, guess64, TOL, norm)
        solution_mixed, inner, products, end = refine(product64, product32, rhs, guess_mixed, inner_tol)
        spaces["float64"].add(solution64, product64)
        spaces["mixed"].add(solution_mixed, product64)
        exact, _ = cg(product64, rhs, solution64, 1e-13, norm)  # the trajectory: the exact step
        stepper.v = stepper.v + exact
        stepper.x = stepper.x + h * stepper.v
        rows.append(dict(step=step, guess_residual_float64=float(torch.linalg.vector_norm(rhs - product64(guess64))) / norm,
                         guess_residual_mixed=float(torch.linalg.vector_norm(rhs - product64(guess_mixed))) / norm,
                         float64_iterations=iterations64, float32_iterations=inner, float64_products=products,
                         mixed_residual=end))
        print(f"E {young:g} step {step}: guesses {rows[-1]['guess_residual_float64']:.1e} / "
              f"{rows[-1]['guess_residual_mixed']:.1e}; float64 CG {iterations64}; mixed {inner} float32, "
              f"{products} float64 products, end {end:.1e}", flush=True)
    kept = rows[settle:]
    mean = lambda key: sum(key(r) for r in kept) / max(len(kept), 1)  # noqa: E731
    return dict(young=young, elements=sim.model.num_elements, steps=steps, settle=settle, inner_tol=inner_tol,
                vectors=vectors,
                float64_iterations=mean(lambda r: r["float64_iterations"]),
                float32_iterations=mean(lambda r: sum(r["float32_iterations"])),
                float64_products=mean(lambda r: r["float64_products"]),
                worst_mixed_residual=max(r["mixed_residual"] for r in rows), steps_detail=rows)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--young", type=float, nargs="+", default=[1e5, 1e7])
    parser.add_argument("--elements", type=int, default=38400)
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--settle", type=int, default=10, help="steps left out of the means (the spaces fill)")
    parser.add_argument("--inner-tol", type=float, default=1e-3, help="the float32 corrections' relative tolerance")
    parser.add_argument("--vectors", type=int, default=PROJECTION_VECTORS, help="the projection's basis vectors")
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "results" / "preconditioners"))
    args = parser.parse_args(argv)
    if args.settle >= args.steps:
        raise SystemExit(f"--settle ({args.settle}) must be less than --steps ({args.steps})")
    records = [measure(young, args.elements, args.steps, args.settle, args.inner_tol, args.vectors)
               for young in args.young]
    for r in records:
        print(f"E = {r['young']:g}, {r['elements']} tets, steps {r['settle']}-{r['steps'] - 1}: float64 CG "
              f"{r['float64_iterations']:.1f} iterations a step; mixed {r['float32_iterations']:.1f} float32 "
              f"iterations and {r['float64_products']:.2f} float64 products; worst end {r['worst_mixed_residual']:.1e}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "mixed_precision.json").write_text(json.dumps(dict(meta=common.metadata("cpu"), records=records), indent=1))
    return records


if __name__ == "__main__":
    main()
