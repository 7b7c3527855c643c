"""Carving: a clamped beam loses elements while it swings under gravity.

    python examples/carve.py [--steps 80] [--model corotational|hooke|stvk] [--out DIR]

A notch is cut into the top of the beam near its clamp, a slab of elements every few steps
(``Simulator.remove_elements``: the Tensor-Mass way, in place, between steps); the weakened beam
sags further. Prints the tip's height and the mass removed as the notch deepens; with --out
writes .vtu frames showing the removed elements gone.
"""
import argparse

import torch

import tensormass_torch as tm


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--model", default="corotational", choices=["corotational", "hooke", "stvk"])
    parser.add_argument("--out", default=None, help="folder for .vtu frames (every 10 steps)")
    args = parser.parse_args(argv)
    mesh = tm.beam_mesh(12, 3, 3, size=(1.2, 0.3, 0.3), dtype=torch.float64)
    body = tm.Body(mesh, tm.Material(young=3e6, poisson=0.3, density=500.0, model=args.model),
                   fixed=mesh.vertices[:, 0] == 0, name="beam")
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-8)
    centroids = mesh.vertices[mesh.elements].mean(1)
    near_clamp = (centroids[:, 0] > 0.2) & (centroids[:, 0] < 0.3)
    tip = mesh.vertices[:, 0] >= 1.2 - 1e-9
    # the notch deepens from the top face in slabs of 0.05: one slab every 10 steps
    depths = [0.3 - 0.05 * k for k in range(1, 5)]
    print(f"{'step':>5} {'tip z':>9} {'elements':>9} {'removed mass':>13}")
    for step in range(args.steps + 1):
        if step % 10 == 0:
            k = step // 10 - 1
            if 0 <= k < len(depths):
                slab = near_clamp & (centroids[:, 2] > depths[k]) & sim.alive_elements(0)
                sim.remove_elements("beam", torch.nonzero(slab).flatten())
            z = sim.positions(0)[tip, 2].mean().item()
            alive = int(sim.alive_elements(0).sum())
            print(f"{step:5d} {z:9.4f} {alive:9d} {float(sim.removed_mass[0]):13.4f}")
            if args.out:
                kept = tm.TetMesh(sim.positions(0), mesh.elements[sim.alive_elements(0)], check=False)
                tm.save_mesh(f"{args.out}/carve_{step:04d}.vtu", kept)
        if step < args.steps:
            sim.step()


if __name__ == "__main__":
    main()
