"""Many bodies of different sizes and materials in one packed batch, falling onto a floor.

    python examples/batch_of_bodies.py [--bodies 50] [--steps 100] [--device cuda] [--out out/batch]

Each body is a small beam with its own Young's modulus (1e4 to 1e6 Pa) and model; CG keeps
per-object scalars, so a stiff body never slows or perturbs a soft one.
"""
import argparse
import time

import torch

import tensormass_torch as tm


def make_bodies(count, device, dtype, seed=0):
    gen = torch.Generator().manual_seed(seed)
    bodies = []
    for i in range(count):
        n = 2 + int(torch.randint(0, 3, (1,), generator=gen))
        origin = (1.5 * (i % 10), 1.5 * (i // 10), 0.5 + float(torch.rand(1, generator=gen)))
        mesh = tm.beam_mesh(2 * n, n, n, size=(1.0, 0.4, 0.4), origin=origin, dtype=dtype, device=device)
        young = float(10 ** (4 + 2 * torch.rand(1, generator=gen)))
        model = "stvk" if i % 2 else "hooke"
        bodies.append(tm.Body(mesh, tm.Material(young, 0.3, 500.0, model), name=f"body{i}"))
    return bodies


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=50)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=None, help="write .vtu frames and a .pvd series here")
    args = parser.parse_args(argv)
    bodies = make_bodies(args.bodies, args.device, torch.float32)
    sim = tm.Simulator(bodies, dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=1.0,
                       planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], cg_tol=1e-4)
    writer = None
    if args.out:
        from tensormass_torch.sim.output import FrameWriter
        writer = FrameWriter(args.out, "batch")
        writer.write(sim)
    start = time.perf_counter()
    for _ in range(args.steps):
        sim.step()
    elapsed = time.perf_counter() - start
    if writer:
        writer.write(sim)
    lowest = min(sim.positions(i)[:, 2].min().item() for i in range(sim.num_bodies))
    print(f"{sim.num_bodies} bodies, {sum(b.mesh.num_elements for b in bodies)} tets, {args.steps} steps in "
          f"{elapsed:.2f} s ({args.steps / elapsed:.1f} steps/s); lowest node z = {lowest:.4f} m")
    return sim


if __name__ == "__main__":
    main()
