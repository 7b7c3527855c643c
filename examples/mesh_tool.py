"""A tool of any closed surface carrying a soft block by friction: a belt (the closed surface of a
slab, or any closed surface file) moves sideways under a block dropped onto it, and friction
brings the block up to the belt's speed.

    python examples/mesh_tool.py [--surface belt.stl] [--resolution 24] [--friction 0.5]
                                 [--speed 0.2] [--steps 100] [--device cuda]

The belt is ``tm.MeshTool``: the surface's signed distance sampled once on a grid (built on
``--device``), then a penalty like any tool's, with regularised Coulomb friction against the tool's
motion (``friction``). Each step reports the force the block puts on the belt (its friction pulls
the belt back while the block slips; then 0.2 N, what the belt gives against the scene's
Rayleigh mass damping r_M m v). Prints that force and the block's speed every 10 steps;
returns ``(simulator, rows)``.
"""
import argparse

import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces


def slab_surface():
    """The closed surface of a 2 x 1 x 0.5 m slab whose top face is at z = 0 in the tool's frame:
    ``(vertices [V, 3], triangles [F, 3])`` (thicker than two of the grid's cells: thinner parts
    are lost to the trilinear interpolation)."""
    slab = tm.beam_mesh(4, 2, 1, size=(2.0, 1.0, 0.5), origin=(-1.0, -0.5, -0.5), dtype=torch.float64)
    return slab.vertices, boundary_faces(slab.elements)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surface", default=None, help="a closed surface file (default: a slab)")
    parser.add_argument("--resolution", type=int, default=24)
    parser.add_argument("--friction", type=float, default=0.5)
    parser.add_argument("--speed", type=float, default=0.2, help="the belt's speed (m/s)")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args(argv)

    block = tm.beam_mesh(4, 4, 4, size=(0.1, 0.1, 0.1), origin=(-0.05, -0.05, 0.002))
    rubber = tm.Material(young=1e6, poisson=0.3, density=1000)
    dt = 0.005
    belt = tm.MeshTool(args.surface or slab_surface(), resolution=args.resolution, stiffness=1e5,
                       friction=args.friction, times=[0.0, 10.0], positions=[[0.0, 0.0, 0.0], [10 * args.speed, 0, 0]],
                       device=args.device, name="belt")
    sim = tm.Simulator([tm.Body(block, rubber)], dt=dt, tools=[belt], rayleigh_mass=1.0, cg_tol=1e-6,
                       device=args.device)
    mass = sim.system.mass[:, 0]
    rows = []
    for step in range(1, args.steps + 1):
        report = sim.step().contact
        if step % 10 == 0 or step == args.steps:
            speed = float((mass * sim.v[:, 0]).sum() / mass.sum())
            force = report.tool_force[0].tolist()
            rows.append((step * dt, force, speed))
            print(f"t = {step * dt:4.2f} s  force on the belt [{force[0]:7.3f} {force[1]:7.3f} {force[2]:7.3f}] N  "
                  f"block's speed {speed:.4f} m/s (belt {args.speed:g})")
    return sim, rows


if __name__ == "__main__":
    main()
