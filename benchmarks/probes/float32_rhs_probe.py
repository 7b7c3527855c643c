"""How accurate a float32 step's right-hand side is: the paper beam's proportions stepped in float32
(hooke, clamped, under gravity, dt = 0.01, CG to 1e-6), and at every step its right-hand side
b = h (f + h K v) computed in float32 and in float64 from the same float32 state and the same rest
positions (the float32 mesh's, upcast). Near equilibrium the elastic force cancels gravity, b is
the small difference of large terms, and its float32 rounding is large against it: the floor
below which converging a float32 step's solve buys nothing (docs/preconditioners.md).

    python benchmarks/probes/float32_rhs_probe.py [--elements 4800] [--young 1e5] [--steps 30]

A probe (no results file): it prints ||b32 - b64|| / ||b64|| (free nodes) every third step.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402
import torch  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.solver import implicit_euler as ie  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--elements", type=int, default=4800)
    parser.add_argument("--young", type=float, default=1e5)
    parser.add_argument("--steps", type=int, default=30)
    args = parser.parse_args(argv)
    mesh32 = tm.beam_mesh(*common.tet_dims(args.elements), size=common.PAPER_SIZE, dtype=torch.float32)
    mesh64 = tm.TetMesh(mesh32.vertices.double(), mesh32.elements)
    sims = []
    for mesh in (mesh32, mesh64):
        body = tm.Body(mesh, tm.Material(young=args.young, poisson=0.3, density=1000.0, model="hooke"),
                       fixed=mesh.vertices[:, 0] <= 1e-6)
        sims.append(tm.Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), cg_tol=1e-6, cg_max_iter=20000,
                                 require_convergence=False))
    single, double = sims
    mass_coef, stiffness_coef = ie._coefficients(double.options)
    free = double.system.free
    errors = []
    for _ in range(args.steps):
        x, v = single.x, single.v
        rhs = []
        for sim, dtype in ((single, torch.float32), (double, torch.float64)):
            matvec = sim.system.system_matvec(mass_coef, stiffness_coef, False, sim.options.variants)
            b, _, _ = ie._step_system(sim.system, x.to(dtype), v.to(dtype), sim.options, None, matvec)
            rhs.append(b.double() * free)
        errors.append(float((rhs[0] - rhs[1]).norm() / rhs[1].norm()))
        single.step()
    print(f"E = {args.young:g}, {single.model.num_elements} tets: ||b32 - b64|| / ||b64|| every third step:",
          " ".join(f"{e:.1e}" for e in errors[::3]))


if __name__ == "__main__":
    main()
