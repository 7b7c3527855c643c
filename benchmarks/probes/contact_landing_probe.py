"""Where a pile's steps spend their time while it lands: each step synchronised and timed alone,
with what it made on the way (CUDA graphs captured, CG solvers made for new layouts of the coupled
solves, loads of the rigid correction that computed its bodies' part afresh), its solves and CG
iterations and its pairs, summed over windows of steps from the drop; then the slowest steps.

    python benchmarks/probes/contact_landing_probe.py [--columns 10] [--steps 120] [--timed 200]
                                                      [--window 20] [--state DIR] [--warm]
                                                      [--contact '{"friction": 0.5}']
                                                      [--preconditioner auto] [--out landing.json]
                                                      [--device cuda]

The pile is ``contact_piles``' (``pile_arguments``), stepped ``--steps`` steps first (0: looked at
from the drop; the probes' default is 120) or taken from ``--state``; ``--timed`` steps are then
looked at.
``--warm``: the pile without contact takes 20 steps first, in the same process, as
``contact_piles.py`` times its run after that pile's (the process's first step, with its CUDA
and library set-up, is then not the run's). The per-step synchronisation leaves the host's
overlap with the device out: the windows' sum exceeds the run's stepping time a little.
"""
import json
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

from tensormass_torch.solver import implicit_euler, rigid_modes  # noqa: E402

COUNTS = ("captures", "solvers", "fresh_loads")


class Counters:
    """Counts of what the steps make, by wrapping what makes it: a CUDA graph's capture
    (``torch.cuda.CUDAGraph.capture_begin``), a coupled solve's new ``CGSolver``
    (``implicit_euler.CGSolver``) and a fresh computation of the rigid correction's bodies' part
    (``rigid_modes.lever_arms``). :meth:`restore` puts them back."""

    def __init__(self):
        self.counts = dict.fromkeys(COUNTS, 0)
        counts = self.counts
        self._originals = [(torch.cuda.CUDAGraph, "capture_begin"), (implicit_euler, "CGSolver"),
                           (rigid_modes, "lever_arms")]
        self._saved = [getattr(owner, name) for owner, name in self._originals]
        capture_begin, solver, lever_arms = self._saved

        def counted_capture(graph, *args, **kwargs):
            counts["captures"] += 1
            return capture_begin(graph, *args, **kwargs)

        class CountedSolver(solver):
            def __init__(self, *args, **kwargs):
                counts["solvers"] += 1
                super().__init__(*args, **kwargs)

        def counted_arms(*args, **kwargs):
            counts["fresh_loads"] += 1
            return lever_arms(*args, **kwargs)

        for (owner, name), wrapped in zip(self._originals, (counted_capture, CountedSolver, counted_arms)):
            setattr(owner, name, wrapped)

    def restore(self):
        for (owner, name), original in zip(self._originals, self._saved):
            setattr(owner, name, original)


def extend(parser):
    parser.add_argument("--window", type=int, default=20, help="steps a line sums")
    parser.add_argument("--warm", action="store_true", help="the pile without contact takes 20 steps first")
    parser.add_argument("--preconditioner", default="auto", help="the Simulator's preconditioner")
    parser.add_argument("--out", default=None, help="a JSON file for the steps' figures")


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=200, extend=extend)
    dtype = torch.float32
    bodies, _ = contact_piles.pile(args.columns, args.cells, args.device, dtype, shift=args.shift,
                                   levels=args.levels)
    if args.warm:
        free = contact_piles.simulator(bodies, None, args.device, dtype, args.preconditioner)
        free.step(20)
        common.sync(args.device)
        del free
    counters = Counters()
    try:
        sim = contact_piles.pile_simulator(args, dtype, bodies)
        rows = []
        for step in range(args.timed):
            before = dict(counters.counts)
            common.sync(args.device)
            start = time.perf_counter()
            report = sim.step()
            common.sync(args.device)
            ms = 1e3 * (time.perf_counter() - start)
            rows.append(dict(step=step, ms=ms, iterations=[int(c.iterations.max()) for c in report.cg],
                             pairs=len(report.contact_solves[-1][0]) if report.contact_solves else 0,
                             **{k: counters.counts[k] - before[k] for k in COUNTS}))
    finally:
        counters.restore()
    print(f"{sim.num_bodies} blocks, --contact {json.dumps(args.contact)}, {args.preconditioner}, "
          f"from step {args.steps if args.state is None else args.state}; by window of {args.window} steps:")
    print("   steps      ms a step  CG its a step  solves a step  captures  solvers  fresh loads  pairs at its end")
    for first in range(0, len(rows), args.window):
        window = rows[first:first + args.window]
        n = len(window)
        print(f"  {first:4d}-{first + n:<4d} {sum(r['ms'] for r in window) / n:10.1f} "
              f"{sum(sum(r['iterations']) for r in window) / n:13.1f} {sum(len(r['iterations']) for r in window) / n:14.2f}"
              f" {sum(r['captures'] for r in window):9d} {sum(r['solvers'] for r in window):8d} "
              f"{sum(r['fresh_loads'] for r in window):12d} {window[-1]['pairs']:17,d}")
    slowest = sorted(rows, key=lambda r: -r["ms"])[:10]
    print("  slowest steps (step: ms, iterations of each solve, captures):",
          ", ".join(f"{r['step']}: {r['ms']:.0f}, {r['iterations']}, {r['captures']}" for r in slowest))
    common.write_blocks(args.out, args, rows)
    return rows


if __name__ == "__main__":
    main()
