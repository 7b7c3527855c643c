"""Contact between bodies at scale: piles of soft blocks in columns dropped onto a floor,
steps/s with body contact against without it in the same run, the detection's time against the
number of surface triangles, and the deepest interpenetration over the run.

    python benchmarks/studies/contact_piles.py [--columns 2 4 6] [--cells 10 10 5] [--steps 120]
                                               [--friction 0] [--swept] [--check-every 0] [--device cuda]
                                               [--dtype float32]
                                               [--out benchmarks/results/contact] [--quick]

Each pile is columns x columns stacks of ``columns`` blocks (0.2 x 0.2 x 0.1 m, E = 1e5 Pa,
nu = 0.3, 1000 kg/m^3; ``--cells`` per block: 10 x 10 x 5 is 3,000 tets), the columns 5 cm
apart, the blocks of a column 3 cm apart and shifted 1 cm sideways each (an offset stack), over a
floor plane of 1e5 N/m; dt = 5 ms, Rayleigh mass damping 1/s, cg_tol 1e-4. With contact the
pile runs ``--steps`` steps (the deepest interpenetration over them is reported), then 10 more
are timed; without contact, 10 steps after 10 of warm-up (the blocks fall through each other:
only the rate is compared). Detection: ``SurfaceContact.detect`` at the final state, mean of 10.
No block may pass through another: besides the deepest interpenetration the steps report (over
the pairs the contact finds), the exact one (``Simulator.interpenetration``: every surface vertex
inside another block, whatever its depth) is measured at the end and every ``--check-every``
steps (each check's step, interpenetration and kinetic energy go to the JSON), and at the end
the pairs of blocks of one column still over each other whose order from the floor up changed.
Writes ``contact_piles.md`` and ``.json`` to ``--out``.
"""
import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import common  # noqa: E402

import tensormass_torch as tm  # noqa: E402

DT = 0.005


def pile(columns: int, cells, device, dtype):
    """The pile's bodies: columns x columns stacks of ``columns`` blocks."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    block = tm.beam_mesh(*cells, size=(0.2, 0.2, 0.1), dtype=dtype)
    bodies = []
    for i in range(columns):
        for j in range(columns):
            for k in range(columns):
                offset = torch.tensor([0.25 * i + 0.01 * k, 0.25 * j, 0.02 + 0.13 * k], dtype=dtype)
                bodies.append(tm.Body(tm.TetMesh(block.vertices + offset, block.elements, check=False), material))
    return bodies, block


def simulator(bodies, contact, device, dtype):
    return tm.Simulator(bodies, dt=DT, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=contact, rayleigh_mass=1.0,
                        device=device, dtype=dtype, cg_tol=1e-4)


def rate(sim, steps: int, device) -> float:
    common.sync(device)
    start = time.perf_counter()
    sim.step(steps)
    common.sync(device)
    return steps / (time.perf_counter() - start)


def measure(columns: int, cells, steps: int, friction: float, device, dtype, check_every: int = 0,
            swept: bool = False):
    bodies, block = pile(columns, cells, device, dtype)
    free = simulator(bodies, None, device, dtype)
    free.step(10)
    without = rate(free, 10, device)
    iterations_without = max(int(c.iterations.max()) for c in free.last_report.cg)
    del free
    sim = simulator(bodies, tm.Contact(friction=friction, swept=swept), device, dtype)
    deepest, checks, start = 0.0, [], time.perf_counter()
    for step in range(1, steps + 1):
        deepest = max(deepest, float(sim.step().contact.body_penetration.max()))
        if step == steps or (check_every and step % check_every == 0):
            checks.append([step, float(sim.interpenetration().max()), float(sim.kinetic_energy().sum())])
    inside = max(c[1] for c in checks)
    run_s = time.perf_counter() - start
    with_contact = rate(sim, 10, device)
    contact = sim.body_contact
    common.sync(device)
    start = time.perf_counter()
    for _ in range(10):
        pairs = contact.detect(sim.x, sim.v, DT)
    common.sync(device)
    detect_ms = 100.0 * (time.perf_counter() - start)
    iterations = max(int(c.iterations.max()) for c in sim.last_report.cg)
    solves = len(sim.last_report.cg)
    return dict(blocks=len(bodies), tets=len(bodies) * block.num_elements, surface_triangles=len(contact.triangles),
                pairs=len(pairs), steps=steps, run_s=run_s, deepest_m=deepest, steps_per_s_without=without,
                steps_per_s_with=with_contact, cost_ratio=without / with_contact, detect_ms=detect_ms,
                cg_iterations=iterations, cg_iterations_without=iterations_without, solves=solves,
                interpenetration_m=inside, mean_edge_m=contact.search, checks=checks,
                out_of_order=out_of_order(sim, columns))


def out_of_order(sim, columns: int) -> int:
    """How many pairs of blocks of one column, still over each other in plan (centroids less than
    15 cm apart: the blocks are 20 cm wide), are no longer in their starting order from the floor
    up: a block through the one under it, or a tumbling pile that stacked them again the other
    way (blocks knocked off, one falling to the floor first); the interpenetration tells them
    apart only while the first is still inside."""
    segments = sim.segments
    centroids = torch.stack([segments.sum(sim.x[:, i]) for i in range(3)], -1) / segments.lengths[:, None]
    stacks = centroids.reshape(columns * columns, columns, 3)  # [column, level from the floor, xyz]
    plan = torch.linalg.vector_norm(stacks[:, :, None, :2] - stacks[:, None, :, :2], dim=-1)
    below = torch.ones(columns, columns, dtype=torch.bool, device=sim.x.device).triu(1)  # level a under b
    flipped = (stacks[:, :, None, 2] >= stacks[:, None, :, 2]) & (plan < 0.15) & below
    return int(flipped.sum())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--columns", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--cells", type=int, nargs=3, default=[10, 10, 5])
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--friction", type=float, default=0.0)
    parser.add_argument("--swept", action="store_true", help="Contact(swept=True): pairs over each step's motion")
    parser.add_argument("--check-every", type=int, default=0,
                        help="measure the interpenetration every this many steps (0: at the end only)")
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "results" / "contact"))
    parser.add_argument("--quick", action="store_true", help="one small pile, a few steps (the tests' run)")
    args = parser.parse_args(argv)
    if args.quick:
        args.columns, args.cells, args.steps = [2], [2, 2, 1], 3
    dtype = getattr(torch, args.dtype)
    meta = common.metadata(args.device, dtype=args.dtype, cells=args.cells, friction=args.friction)
    columns = [("blocks", "blocks", None), ("tets", "tets", ","), ("surface_triangles", "surface triangles", ","),
               ("pairs", "pairs", ","), ("steps_per_s_without", "steps/s without", ".1f"),
               ("steps_per_s_with", "steps/s with", ".1f"), ("cost_ratio", "cost (x)", ".1f"),
               ("detect_ms", "detection (ms)", ".2f"), ("cg_iterations_without", "CG iterations without", None),
               ("cg_iterations", "CG iterations with", None), ("solves", "solves in the last step", None),
               ("deepest_m", "deepest in the reports (m)", ".2e"),
               ("interpenetration_m", "deepest inside another body (m)", ".2e"),
               ("out_of_order", "stacked blocks out of order", None),
               ("mean_edge_m", "mean surface edge (m)", ".2e")]
    notes = [f"{args.dtype}, blocks of {args.cells} cells, friction {args.friction:g}, swept {args.swept}, dt {DT} s, "
             f"{args.steps} steps with contact before the timed ones."]
    results = common.Results(args.out, "contact_piles", "Piles of blocks: steps/s with body contact against "
                             "without, detection time", meta, columns, notes)
    for c in args.columns:  # written as each pile is measured: a later failure loses nothing
        results.add(measure(c, args.cells, args.steps, args.friction, args.device, dtype, args.check_every,
                            args.swept), echo=False)
    results.finish()
    return results.records


if __name__ == "__main__":
    main()
