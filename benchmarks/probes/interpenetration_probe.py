"""The exact interpenetration check of a pile (``Simulator.interpenetration``: all bodies in one
batched distance query) against the same measure body by body (each body's surface against the
surface vertices of the bodies whose boxes meet its box, ``sim.diagnostics.depth_inside``, a
Python loop over the bodies): seconds a check (``--repeats`` of the batched one) and the largest
difference between the two.

    python benchmarks/probes/interpenetration_probe.py [--columns 10] [--steps 120] [--state DIR]
                                                       [--repeats 3] [--device cuda]

The pile is ``contact_piles``' (``pile_arguments``), stepped ``--steps`` steps with contact or
taken from ``--state``.
"""
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

from tensormass_torch.sim.diagnostics import depth_inside  # noqa: E402


def body_by_body(sim) -> torch.Tensor:
    """``[B]`` the interpenetration, one distance query per body with neighbours."""
    x = sim.x
    faces = sim.surface_triangles()
    surface = {i: torch.unique(f) for i, f in faces.items()}
    tet = list(faces)
    lower = torch.stack([x[surface[i]].amin(0) for i in tet])
    upper = torch.stack([x[surface[i]].amax(0) for i in tet])
    overlap = ((lower[:, None] <= upper[None]) & (lower[None] <= upper[:, None])).all(-1)
    overlap.fill_diagonal_(False)
    depth = x.new_zeros(sim.num_bodies)
    for k, near in enumerate(overlap.tolist()):
        if any(near):
            others = torch.cat([surface[tet[j]] for j, n in enumerate(near) if n])
            nodes, inside = depth_inside(x, others, faces[tet[k]], lower[k], upper[k])
            depth.scatter_reduce_(0, sim.segments.node_object[nodes], inside, "amax")
    return depth


def timed(fn, device):
    common.sync(device)
    start = time.perf_counter()
    value = fn()
    common.sync(device)
    return value, time.perf_counter() - start


def main(argv=None):
    def extend(parser):
        parser.add_argument("--repeats", type=int, default=3, help="batched checks timed")
    args = contact_piles.pile_arguments(argv, __doc__, timed=0, extend=extend)
    sim = contact_piles.pile_simulator(args)
    print(f"{common.metadata(args.device)['device_name']}; {sim.num_bodies} bodies")
    batched = []
    for _ in range(args.repeats):
        depth, seconds = timed(sim.interpenetration, args.device)
        batched.append(seconds)
        print(f"batched: {seconds:.3f} s, deepest {float(depth.max()):.4e} m, bodies inside {int((depth > 0).sum())}",
              flush=True)
    reference, seconds = timed(lambda: body_by_body(sim), args.device)
    difference = float((reference - depth).abs().max())
    print(f"body by body: {seconds:.3f} s, deepest {float(reference.max()):.4e} m; largest difference "
          f"{difference:.3e}")
    return dict(batched_s=batched, body_by_body_s=seconds, difference=difference)


if __name__ == "__main__":
    main()
