"""A rabbit-like body on a floor, sagging under gravity while a tool presses down on its back.

    python examples/rabbit.py [--size 0.3] [--cell 0.08] [--steps 60] [--model corotational] [--out out/rabbit] [--gif]

The body is made by ``tensormass_torch.mesh.implicit`` (smooth unions of ellipsoids, tetrahedralised
on a lattice: no mesh file, no download). It rests on a penalty floor at z = 0. The tool is a
ball-shaped region over the back: the nodes inside it are prescribed and move down at
``--tool-speed`` for ``--press-time`` seconds, then hold, as a probe pushing into soft tissue
would. Returns the simulator and the tool's nodes.
"""
import argparse
import time

import torch

import tensormass_torch as tm
from tensormass_torch.mesh import implicit as meshgen

# The tool, in units of the body length: a ball over the back whose lower part cuts into it.
TOOL_CENTER = (-0.05, 0.0, 0.56)
TOOL_RADIUS = 0.12


class ToolPress:
    """Positions ``[k, 3]`` of the tool's nodes at time t: straight down at ``speed`` until ``stop``."""

    def __init__(self, start, speed, stop):
        self.start = start
        self.velocity = torch.tensor([0.0, 0.0, -speed], dtype=start.dtype, device=start.device)
        self.stop = stop

    def __call__(self, t):
        return self.start + self.velocity * min(t, self.stop)


def build(size, cell, model, young, tool_speed, press_time, device, dtype):
    """The simulator and the tool's node mask ``[V]``; ``cell`` is relative to ``size``."""
    mesh = meshgen.rabbit_mesh(size=size, cell=cell * size).to(device=device, dtype=dtype)
    center = torch.tensor(TOOL_CENTER, dtype=dtype, device=device) * size
    tool = (mesh.vertices - center).norm(dim=1) <= TOOL_RADIUS * size
    if not bool(tool.any()):  # a very coarse lattice may leave no node in the ball
        tool = mesh.vertices[:, 2] >= mesh.vertices[:, 2].max() - 1e-9
    material = tm.Material(young=young, poisson=0.35, density=1000.0, model=model,
                           rotation="qr" if model == "corotational" else "polar")
    body = tm.Body(mesh, material, prescribed=tool, motion=ToolPress(mesh.vertices[tool], tool_speed, press_time),
                   name="rabbit")
    sim = tm.Simulator([body], dt=0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass=1.0, rayleigh_stiffness=0.002,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], cg_tol=1e-4)
    return sim, tool


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=float, default=0.3, help="body length (m)")
    parser.add_argument("--cell", type=float, default=0.08, help="lattice spacing of the mesh, relative to --size")
    parser.add_argument("--young", type=float, default=5e4, help="Young's modulus (Pa)")
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--every", type=int, default=5, help="write a frame every N steps")
    parser.add_argument("--model", default="corotational", choices=list(tm.MODELS),
                        help="corotational (default) stays stable where the tool crushes elements; stvk may not")
    parser.add_argument("--tool-speed", type=float, default=0.1, help="m/s, downward")
    parser.add_argument("--press-time", type=float, default=0.2, help="s, then the tool holds")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--out", default=None, help="write .vtu frames and a .pvd series here")
    parser.add_argument("--gif", action="store_true", help="also render rabbit.gif (needs pyvista and --out)")
    args = parser.parse_args(argv)
    sim, tool = build(args.size, args.cell, args.model, args.young, args.tool_speed, args.press_time, args.device,
                      getattr(torch, args.dtype))
    writers = []
    if args.out:
        from tensormass_torch.app.render import FrameRenderer
        from tensormass_torch.sim.output import FrameWriter

        writers.append(FrameWriter(args.out, "rabbit"))
        if args.gif:
            writers.append(FrameRenderer(args.out, "rabbit", png=False, gif=True, window_size=(640, 480)))
    for w in writers:
        w.write(sim)
    mesh = sim.bodies[0].mesh
    print(f"rabbit: {mesh.num_vertices} nodes, {mesh.num_elements} tets, {int(tool.sum())} under the tool, "
          f"{args.model}, {args.steps} steps")
    start = time.perf_counter()
    for step in range(1, args.steps + 1):
        sim.step()
        if step % args.every == 0 or step == args.steps:
            for w in writers:
                w.write(sim)
    elapsed = time.perf_counter() - start
    for w in writers:
        getattr(w, "close", lambda: None)()
    u = sim.displacements(0)
    ears = mesh.vertices[:, 2] >= mesh.vertices[:, 2].max() - 0.05 * args.size
    print(f"{args.steps} steps in {elapsed:.2f} s ({args.steps / elapsed:.1f} steps/s); tool pushed "
          f"{-float(u[tool, 2].mean()):.3f} m, lowest node z = {float(sim.positions(0)[:, 2].min()):+.4f} m, "
          f"ear tips moved {float(u[ears].norm(dim=1).mean()):.3f} m")
    return sim, tool


if __name__ == "__main__":
    main()
