"""A body from a surface mesh: pyvista's hex nut (``nut.ply``, a closed triangle surface that the
pyvista package ships) tetrahedralised by TetGen, scaled from millimetres to metres, dropped
onto a floor as soft rubber.

    python examples/surface_mesh.py [--surface FILE] [--scale 0.001] [--max-volume V] [--steps 80]
                                    [--method tetgen|ftetwild] [--out out/nut] [--gif] [--device cuda]

Needs ``tetgen`` (or ``pytetwild`` with ``--method ftetwild``) and, for the default surface,
pyvista. Returns (simulator, mesh).
"""
import argparse
import time

import torch

import tensormass_torch as tm


def default_surface() -> str:
    try:
        from pyvista import examples
    except ImportError:
        raise SystemExit("the default surface is pyvista's nut.ply: pip install pyvista, or pass --surface FILE")
    return examples.nutfile


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--surface", default=None, help="a closed triangle surface (.stl .obj .ply .off ...)")
    parser.add_argument("--scale", type=float, default=0.001, help="surface units to metres (nut.ply: mm)")
    parser.add_argument("--method", default="tetgen", choices=["tetgen", "ftetwild"])
    parser.add_argument("--max-volume", type=float, default=None,
                        help="largest tet volume, in the surface's units cubed (tetgen)")
    parser.add_argument("--steps", type=int, default=80)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default=None, help="write .vtu frames and a .pvd series here")
    parser.add_argument("--gif", action="store_true", help="also render nut.gif (needs pyvista and --out)")
    args = parser.parse_args(argv)

    options = {"max_volume": args.max_volume} if args.max_volume and args.method == "tetgen" else {}
    start = time.perf_counter()
    mesh = tm.tetrahedralize(args.surface or default_surface(), method=args.method, **options)
    # into metres, its lowest point 5 cm above the floor at z = 0
    vertices = mesh.vertices * args.scale
    vertices = vertices - vertices.mean(0) * torch.tensor([1.0, 1.0, 0.0])
    vertices[:, 2] += 0.05 - float(vertices[:, 2].min())
    mesh = tm.TetMesh(vertices, mesh.elements).to(device=args.device)
    print(f"{mesh.num_elements} tets, {mesh.num_vertices} nodes from the surface in "
          f"{time.perf_counter() - start:.2f} s ({args.method})")

    rubber = tm.Material(young=2e5, poisson=0.45, density=1100.0, model="corotational")
    sim = tm.Simulator([tm.Body(mesh, rubber, name="nut")], dt=0.005, rayleigh_mass=1.0,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], device=args.device)
    writer = renderer = None
    if args.out:
        from tensormass_torch.app.render import FrameRenderer
        from tensormass_torch.sim.output import FrameWriter

        writer = FrameWriter(args.out, "nut")
        writer.write(sim)
        if args.gif:
            renderer = FrameRenderer(args.out, "nut", png=False, gif=True)
            renderer.write(sim)
    start = time.perf_counter()
    for step in range(1, args.steps + 1):
        sim.step()
        if step % 5 == 0:
            for out in (writer, renderer):
                if out:
                    out.write(sim)
    if renderer:
        renderer.close()
    lowest = float(sim.positions(0)[:, 2].min())
    print(f"{args.steps} steps in {time.perf_counter() - start:.2f} s; lowest node z = {lowest * 1e3:.2f} mm")
    return sim, mesh


if __name__ == "__main__":
    main()
