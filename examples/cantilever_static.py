"""Static cantilever under gravity: tip deflection against Euler-Bernoulli and Timoshenko.

    python examples/cantilever_static.py [--cells 1 2 4] [--model hooke|stvk|corotational] [--dtype float64]

Prints the tip deflection for each refinement and its error against beam theory: P1 tetrahedra
are too stiff in bending (locking), and the error falls as the mesh is refined.
"""
import argparse

import torch

import tensormass_torch as tm


def beam_theory(young, poisson, density, gravity, length, side):
    """Tip deflections (Euler-Bernoulli, Timoshenko) of a square cantilever under its weight."""
    inertia, area = side ** 4 / 12.0, side * side
    load = density * gravity * area
    shear_area = 10.0 * (1.0 + poisson) / (12.0 + 11.0 * poisson) * area
    shear_modulus = young / (2.0 * (1.0 + poisson))
    bending = load * length ** 4 / (8.0 * young * inertia)
    return bending, bending + load * length ** 2 / (2.0 * shear_modulus * shear_area)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs="+", default=[1, 2, 4], help="cells across the section")
    parser.add_argument("--model", default="hooke", choices=["hooke", "stvk", "corotational"])
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    young, poisson, density, gravity, length, side = 1e6, 0.3, 1000.0, 9.81, 1.0, 0.2
    euler_bernoulli, timoshenko = beam_theory(young, poisson, density, gravity, length, side)
    print(f"beam theory: Euler-Bernoulli {euler_bernoulli:.5f} m, Timoshenko {timoshenko:.5f} m")
    rows = []
    for n in args.cells:
        mesh = tm.beam_mesh(5 * n, n, n, size=(length, side, side), dtype=dtype)
        model = tm.TensorMass(mesh, tm.Material(young, poisson, density, model=args.model))
        u = tm.solve_static(model, fixed=mesh.vertices[:, 0] <= 1e-9, gravity=(0, 0, -gravity), tol=1e-8)
        tip = -u[mesh.vertices[:, 0] >= length - 1e-9, 2].mean().item()
        rows.append((n, mesh.num_elements, tip, (tip - timoshenko) / timoshenko))
        print(f"{n} cells across, {mesh.num_elements:6d} tets: tip {tip:.5f} m, error vs Timoshenko {rows[-1][3]:+.2%}")
    return rows


if __name__ == "__main__":
    main()
