"""When the blocks of a pile's columns change their order, and how close they are then: the pile of
``contact_piles`` stepped with contact, and at every step, for each pair of one column's blocks
whose centroids are within 15 cm in plan, whether the block that started above is still above;
each change is an event (step, column, levels, now above or not, the centroids' distance in
plan and in space, how deep each of the two blocks' surface vertices is inside the other (the
exact signed distance to its whole surface, as ``Simulator.interpenetration`` measures it, for
this pair only), and each block's tilt: the angle between the vertical and its thin axis, through
the linear map that best carries its rest vertices to their positions (0: lying flat, 90 degrees:
on an edge).

    python benchmarks/probes/contact_pile_flips_probe.py [--columns 10] [--steps 1000] [--rounds 2]
                                                         [--friction 0] [--shift 0.01]
                                                         [--out events.json] [--device cuda]

A block passing through another crosses it with their volumes overlapping: at the crossing the
centroids are level, and two blocks of 0.2 x 0.2 x 0.1 m that do not overlap have centroids at
least 10 cm apart (face to face), 20 cm lying flat side by side. Prints the progress every 100
steps and the events' summary; writes the events to ``--out`` (JSON).
"""
import argparse
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.sim.diagnostics import depth_inside  # noqa: E402


def inside(x: torch.Tensor, nodes: torch.Tensor, faces: torch.Tensor) -> float:
    """How deep the surface vertices ``nodes`` are inside the closed surface ``faces`` at ``x``
    (0 where none is)."""
    depths = depth_inside(x, nodes, faces)[1]
    return float(depths.max()) if len(depths) else 0.0


def tilts(x: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """Each block's tilt in degrees ``[B]`` for the blocks' positions ``x [B * V, 3]`` and one
    block's rest vertices ``rest [V, 3]``: the angle between the vertical and the image of the rest
    block's z axis (its thin one) by the least-squares linear map A with A (X - X_mean) ~ x - x_mean."""
    rest = rest - rest.mean(0)
    x = x.reshape(-1, *rest.shape)
    x = x - x.mean(1, keepdim=True)
    maps = torch.einsum("bvi,vj->bij", x, rest) @ torch.linalg.inv(rest.T @ rest)  # [B, 3, 3]
    axis = torch.nn.functional.normalize(maps[:, :, 2], dim=-1)
    return torch.rad2deg(torch.acos(axis[:, 2].abs().clamp(max=1.0)))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--columns", type=int, default=10)
    parser.add_argument("--cells", type=int, nargs=3, default=[10, 10, 5])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=tm.Contact().rounds)
    parser.add_argument("--friction", type=float, default=0.0, help="Contact(friction=...)")
    parser.add_argument("--shift", type=float, default=contact_piles.SHIFT,
                        help="each block's start sideways from the one under it (m; 0: straight stacks)")
    parser.add_argument("--out", default="contact_pile_flips.json")
    parser.add_argument("--device", default=common.default_device())
    args = parser.parse_args(argv)
    n = args.columns
    bodies, block = contact_piles.pile(n, args.cells, args.device, torch.float32, shift=args.shift)
    contact = tm.Contact(rounds=args.rounds, friction=args.friction)
    sim = contact_piles.simulator(bodies, contact, args.device, torch.float32)
    rest = block.vertices.to(sim.x)
    faces = {body: f.to(sim.x.device) for body, f in sim.surface_triangles().items()}
    surface = {body: torch.unique(f) for body, f in faces.items()}
    below = torch.ones(n, n, dtype=torch.bool, device=sim.x.device).triu(1)  # level a under level b

    before, events = None, []
    start = time.perf_counter()
    for step in range(1, args.steps + 1):
        sim.step()
        centroids = contact_piles.column_centroids(sim, n)
        above = centroids[:, None, :, 2] > centroids[:, :, None, 2]  # [column, a, b]: b over a
        if before is not None:
            plan = torch.linalg.vector_norm(centroids[:, :, None, :2] - centroids[:, None, :, :2], dim=-1)
            space = torch.linalg.vector_norm(centroids[:, :, None] - centroids[:, None, :], dim=-1)
            changed = ((above != before) & below & (plan < 0.15)).nonzero().tolist()
            tilt = tilts(sim.x, rest) if changed else None
            for column, a, b in changed:
                event = dict(step=step, column=column, a=a, b=b, b_above=bool(above[column, a, b]),
                             plan_m=float(plan[column, a, b]), space_m=float(space[column, a, b]))
                one, other = column * n + a, column * n + b
                event.update(inside_a_m=inside(sim.x, surface[one], faces[other]),
                             inside_b_m=inside(sim.x, surface[other], faces[one]),
                             tilt_a_deg=float(tilt[one]), tilt_b_deg=float(tilt[other]))
                events.append(event)
        before = above
        if step % 100 == 0:
            print(f"step {step}: {time.perf_counter() - start:.0f} s, {len(events)} events, "
                  f"out of order {contact_piles.out_of_order(sim, n)}", flush=True)
    Path(args.out).write_text(json.dumps(events))
    final = {}
    for event in events:
        final[(event["column"], event["a"], event["b"])] = event
    depths = [max(e["inside_a_m"], e["inside_b_m"]) for e in events]
    print(f"{len(events)} events, {len(final)} pairs, {sum(not e['b_above'] for e in final.values())} ending "
          f"reversed; the closest centroids at an event {min((e['space_m'] for e in events), default=float('nan')):.4f} m; "
          f"deepest inside the other at an event {max(depths, default=0.0):.2e} m")
    return events


if __name__ == "__main__":
    main()
