"""A scalpel cuts a clamped slab through as it moves; the far piece falls onto the floor.

    python examples/scalpel.py [--model corotational|hooke|stvk] [--resolution 2] [--on-device] [--png FILE]

An upright blade edge sweeps across the slab near its clamp (``tm.Scalpel``: keyframes of the
edge over time; ``sim.add_scalpel``: before each step the body is cut along the strip the edge
sweeps, the crossed faces part and their nodes split). Prints the nodes the cuts added, the
number of pieces and the far end's height; with --png renders the slab before, during and after
the cut side by side (needs pyvista). The built-in scene ``tensormass run cut`` is the same.
``--on-device`` cuts with kernels on the simulator's device (``Simulator(cut_on_device=True)``:
a hooke body; on a GPU the cut of each step is replayed from a captured graph, with no host
synchronisation) and says where the cuts ran.
"""
import argparse

import tensormass_torch as tm
from tensormass_torch.mesh.topology import element_pieces


def pieces(mesh) -> int:
    """Connected pieces of a mesh (elements joined through shared nodes)."""
    return int(element_pieces(mesh.elements, mesh.num_vertices).max()) + 1


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="corotational", choices=["corotational", "hooke", "stvk"])
    parser.add_argument("--resolution", type=int, default=2, help="cells: 10 r x 3 r x 2 r")
    parser.add_argument("--png", default=None, help="render before / during / after into this PNG")
    parser.add_argument("--on-device", action="store_true", help="cut on the device (a hooke body)")
    args = parser.parse_args(argv)
    r = args.resolution
    mesh = tm.beam_mesh(10 * r, 3 * r, 2 * r, size=(1.0, 0.3, 0.2), origin=(0.0, -0.15, -0.1))
    body = tm.Body(mesh, tm.Material(young=5e6, poisson=0.3, density=500.0, model=args.model),
                   fixed=mesh.vertices[:, 0] == 0, name="slab")
    sim = tm.Simulator([body], dt=0.01, planes=[tm.Plane((0.0, 0.0, 1.0), -0.5, 1e5)], rayleigh_mass=0.5,
                       cg_tol=1e-5, cut_on_device=args.on_device)
    # the edge stands upright beside the slab at x = 0.33 and crosses it along +y in 0.4 s
    start = [[0.33, -0.3, -0.3], [0.33, -0.3, 0.3]]
    end = [[0.33, 0.3, -0.3], [0.33, 0.3, 0.3]]
    sim.add_scalpel(tm.Scalpel("slab", times=[0.1, 0.5], edges=[start, end]))
    shots = {}
    print(f"{'t':>5} {'nodes':>6} {'pieces':>7} {'far end z':>10}")
    for step in range(121):
        if step % 20 == 0:
            now = sim.mesh("slab")
            far = sim.positions(0)[now.vertices[:, 0] > 0.9, 2].mean().item()
            print(f"{sim.time:5.2f} {now.num_vertices:6d} {pieces(now):7d} {far:10.4f}")
        if step in (0, 50, 120):
            shots[step] = (sim.mesh("slab"), sim.positions(0).clone())
        if step < 120:
            sim.step()
    if args.on_device:
        where = "on the device" if sim.device_cuts_active else "on the host (the device cut does not serve " \
            "this scene: tm.sim.device_cut.DeviceCuts.unavailable says why)"
        print(f"cuts made {where}")
    if args.png:
        from tensormass_torch.app.render import render_png

        path = render_png(args.png, [[shots[k]] for k in (0, 50, 120)], window_size=(1200, 420), zoom=0.85,
                          labels=["t = 0 s", "t = 0.5 s: cut through", "t = 1.2 s"])
        print(f"wrote {path}")


if __name__ == "__main__":
    main()
