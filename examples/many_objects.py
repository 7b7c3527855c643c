"""A few hundred objects of different shapes and materials in one Simulator, falling onto a floor.

    python examples/many_objects.py [--objects 300] [--steps 50] [--device cuda] [--out out/many] [--gif]
                                    [--no-contact]

Shapes: boxes, balls, capsules and rabbit-like bodies (``tensormass_torch.mesh.implicit``), each shape
meshed once and copied; every object has its own Young's modulus (1e4 to 1e6 Pa, log-uniform),
Poisson ratio, density and model (hooke, stvk, corotational). They are packed into one batch: one
kernel launch per op for all of them, and a CG with per-object scalars and convergence. They meet
each other through ``tm.Contact`` (``--no-contact``: they fall through each other; bodies that
touch are then solved together). Returns the simulator.
"""
import argparse
import time

import torch

import tensormass_torch as tm
from tensormass_torch.mesh import implicit as meshgen

SPACING = 0.5  # m between object centres on the grid


def shape_library(dtype):
    """One small mesh per shape, centred at the origin, about 0.3 m across: ``{name: TetMesh}``."""
    return {
        "box": tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.2), origin=(-0.15, -0.1, -0.1), dtype=dtype),
        "ball": meshgen.sphere_mesh(0.13, cell=0.065).to(dtype=dtype),
        "capsule": meshgen.capsule_mesh(0.08, 0.2, cell=0.055).to(dtype=dtype),
        "rabbit": meshgen.rabbit_mesh(size=0.3, cell=0.075, origin=(0.0, 0.0, -0.15)).to(dtype=dtype),
    }


def make_bodies(count, device, dtype, seed=0):
    """``count`` bodies on a grid (raised 0.3 to 1.3 m), shapes and models in turn, random materials."""
    gen = torch.Generator().manual_seed(seed)
    library = shape_library(dtype)
    names = list(library)
    side = max(1, int(count ** 0.5 + 0.999))
    models = tm.MODELS
    bodies = []
    for i in range(count):
        shape = names[i % len(names)]
        template = library[shape]
        lift = 0.3 + float(torch.rand(1, generator=gen))
        offset = torch.tensor([SPACING * (i % side), SPACING * (i // side), lift], dtype=dtype)
        mesh = tm.TetMesh(template.vertices + offset, template.elements, check=False).to(device=device)
        model = models[(i // len(names)) % len(models)]
        material = tm.Material(young=float(10 ** (4 + 2 * torch.rand(1, generator=gen))),
                               poisson=float(0.2 + 0.25 * torch.rand(1, generator=gen)),
                               density=float(300 + 1200 * torch.rand(1, generator=gen)), model=model,
                               rotation="qr" if model == "corotational" else "polar")
        velocity = (torch.rand(3, generator=gen, dtype=dtype) - 0.5) * torch.tensor([1.0, 1.0, 0.5], dtype=dtype)
        bodies.append(tm.Body(mesh, material, velocity=velocity.tolist(), name=f"{shape}{i}"))
    return bodies


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--objects", type=int, default=300)
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--every", type=int, default=5, help="write a frame every N steps")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--out", default=None, help="write .vtu frames and a .pvd series here")
    parser.add_argument("--gif", action="store_true", help="also render many.gif (needs pyvista and --out)")
    parser.add_argument("--no-contact", action="store_true", help="bodies pass through each other")
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    bodies = make_bodies(args.objects, args.device, dtype)
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass=0.5,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], cg_tol=1e-4,
                       device=args.device, dtype=dtype,
                       contact=None if args.no_contact else tm.Contact(stiffness=1e4))
    writers = []
    if args.out:
        from tensormass_torch.app.render import FrameRenderer
        from tensormass_torch.sim.output import FrameWriter

        writers.append(FrameWriter(args.out, "many"))
        if args.gif:
            writers.append(FrameRenderer(args.out, "many", png=False, gif=True, window_size=(960, 720)))
    for w in writers:
        w.write(sim)
    elements = sum(b.mesh.num_elements for b in bodies)
    print(f"{sim.num_bodies} objects, {elements} tets, {sim.x.shape[0]} nodes on {sim.device}")
    start = time.perf_counter()
    for step in range(1, args.steps + 1):
        sim.step()
        if step % args.every == 0 or step == args.steps:
            for w in writers:
                w.write(sim)
    elapsed = time.perf_counter() - start
    for w in writers:
        getattr(w, "close", lambda: None)()
    lowest = float(sim.x[:, 2].min())
    print(f"{args.steps} steps in {elapsed:.2f} s ({args.steps / elapsed:.1f} steps/s); lowest node z = "
          f"{lowest:+.4f} m; CG iterations of the last step: max {int(sim.last_report.cg_iterations.max())}")
    return sim


if __name__ == "__main__":
    main()
