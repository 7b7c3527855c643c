"""Why a pile's steps take contact rounds: at each check of a step's solve, how many (vertex,
body) pairs joined the set because the solve left the vertex inside with no active pair
(misses) and how many because it ended deeper than its active pair's linear model
(re-linearisations), by how much (the five largest), and how many of the first check's were also
the step before's; then each step's solves and CG iterations.

    python benchmarks/probes/contact_rounds_probe.py [--columns 10] [--steps 120] [--timed 12]
                                                     [--state DIR] [--contact '{"tolerance": 6e-4}']
                                                     [--device cpu]

The pile is ``contact_piles``' (columns x columns x columns blocks), stepped ``--steps`` steps with
contact, or taken from a state ``contact_piles.py --state`` saved (``DIR/x.pt``, ``v.pt``); then
``--timed`` steps are looked at. ``--contact``: ``tm.Contact``'s keyword arguments as JSON. The
counts follow ``SurfaceContact.relinearise``'s test (a vertex deeper than its model by more than
the check's tolerance); the linear end-gap misses that ``implicit_euler_step`` adds itself are
not counted here. Iteration counts are the device's arithmetic's, so the CPU's stand for the
GPU's to rounding.
"""
import math
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_piles  # noqa: E402

from tensormass_torch.physics import body_contact  # noqa: E402


def checked(log: list):
    """``SurfaceContact.relinearise`` wrapped to add, for each call, what its test finds to ``log``."""
    original = body_contact.SurfaceContact.relinearise

    def relinearise(self, x, dx, pairs, active, v=None, solution=-1, tolerance=None, later=False):
        end, _ = self.nearby(x + dx, found=self._step_candidates(x, dx, later))
        objects = max(self.num_objects, 1)
        key = pairs.nodes[:, 0] * objects + pairs.objects[:, 1]
        end_key = end.nodes[:, 0] * objects + end.objects[:, 1]
        held = torch.zeros_like(end_key, dtype=torch.bool)
        model = torch.full_like(end.gap, math.inf)
        if len(pairs):
            sorted_key, order = torch.sort(key)
            position = torch.searchsorted(sorted_key, end_key).clamp(max=len(pairs) - 1)
            index = order[position]
            held = (sorted_key[position] == end_key) & active[index]
            model = torch.where(held, pairs.end_gap(dx)[index], model)
        limit = self.tolerance if tolerance is None else tolerance
        excess = torch.clamp(model, max=0.0) - end.gap
        deeper = excess > limit
        log.append(dict(solution=solution, tolerance=limit,
                        misses=sorted((excess[deeper & ~held]).tolist(), reverse=True),
                        relinearised=sorted((excess[deeper & held]).tolist(), reverse=True),
                        keys=set(end_key[deeper].tolist())))
        return original(self, x, dx, pairs, active, v, solution, tolerance, later)

    body_contact.SurfaceContact.relinearise = relinearise
    return original


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=12)
    sim = contact_piles.pile_simulator(args)
    log: list = []
    original = checked(log)
    steps, before = [], set()
    try:
        for step in range(args.timed):
            log.clear()
            report = sim.step()
            iterations = [int(c.iterations.max()) for c in report.cg]
            print(f"step {step}: solves {iterations} ({sum(iterations)} CG iterations), "
                  f"deepest report {1e3 * float(report.contact.body_penetration.max()):.3f} mm", flush=True)
            for entry in log:
                print(f"  check of solve {entry['solution']} at {1e3 * entry['tolerance']:.3f} mm: "
                      f"{len(entry['misses'])} misses (mm past: {[round(1e3 * e, 3) for e in entry['misses'][:5]]}), "
                      f"{len(entry['relinearised'])} re-linearised "
                      f"(mm past the model: {[round(1e3 * e, 3) for e in entry['relinearised'][:5]]})")
            first = log[0]["keys"] if log else set()
            if log:
                print(f"  of the first check's {len(first)}, {len(first & before)} were also the step before's")
            before = first
            steps.append(dict(iterations=iterations, checks=[{k: v for k, v in e.items() if k != "keys"} for e in log]))
    finally:
        body_contact.SurfaceContact.relinearise = original
    total = sum(sum(s["iterations"]) for s in steps)
    print(f"{args.timed} steps, contact {args.contact}: {sum(len(s['iterations']) for s in steps) / args.timed:.2f} "
          f"solves and {total / args.timed:.1f} CG iterations a step; "
          f"inside another body at the end {1e3 * float(sim.interpenetration().max()):.3f} mm")
    return steps


if __name__ == "__main__":
    main()
