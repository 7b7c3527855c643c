"""The contact step's CG with the pairs' product inside the fused step length, which skips the
coupled runs of bodies that have stopped (``implicit_euler._WithPairs.matvec_alpha``, the
default), against the product called whole and its step length taken apart (what the CG does
where there is no fused path): two simulators from one state, stepped in alternated blocks in one
process, and per body the CG iterations of one step (how far apart the runs stop).

    python benchmarks/probes/contact_pairs_step_length_probe.py [--columns 10] [--shift 0.01]
                                                                [--steps 120] [--state DIR]
                                                                [--contact '{"friction": 0.5}']
                                                                [--timed 25] [--repeats 4]
                                                                [--device cuda]

The pile is ``contact_piles``' (``pile_arguments``), stepped ``--steps`` steps or taken from
``--state``. Each simulator takes two steps, then ``--repeats`` times each takes ``--timed`` steps
in turn. Prints ms a step and CG iterations a step of each block, how far apart the two states end
(the two paths are the same arithmetic: 0), and the first timed step's iterations per body;
returns (ms a step by path and block, that distance, those iterations ``[bodies]``).
"""
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.solver import implicit_euler  # noqa: E402


def main(argv=None):
    def extend(parser):
        parser.add_argument("--repeats", type=int, default=4)

    args = contact_piles.pile_arguments(argv, __doc__, timed=25, extend=extend)
    bodies, x, v = contact_piles.pile_start(args)
    fused = implicit_euler._WithPairs.matvec_alpha
    paths = {"in the step length": fused, "called whole": lambda self, *a: None}
    sims = {}
    for name in paths:
        sim = contact_piles.simulator(bodies, tm.Contact(**args.contact), args.device, torch.float32, "auto")
        sim.x, sim.v = x.clone(), v.clone()
        sims[name] = sim
    blocks = {name: [] for name in paths}
    try:
        for name, sim in sims.items():
            implicit_euler._WithPairs.matvec_alpha = paths[name]
            sim.step(2)
        for repeat in range(args.repeats):
            for name, sim in sims.items():
                implicit_euler._WithPairs.matvec_alpha = paths[name]
                iterations = []
                common.sync(args.device)
                start = time.perf_counter()
                for _ in range(args.timed):
                    report = sim.step()
                    iterations.append(sum(int(c.iterations.max()) for c in report.cg))
                    if repeat == 0 and len(iterations) == 1 and name == "in the step length":
                        per_body = report.cg[0].iterations
                common.sync(args.device)
                ms = (time.perf_counter() - start) / args.timed * 1e3
                blocks[name].append(ms)
                print(f"{name:20s} block {repeat}: {ms:.2f} ms a step, "
                      f"{sum(iterations) / len(iterations):.1f} CG iterations a step", flush=True)
    finally:
        implicit_euler._WithPairs.matvec_alpha = fused
    apart = float((sims["in the step length"].x - sims["called whole"].x).abs().max())
    print(f"the states end {apart:.3g} m apart")
    for name, times in blocks.items():
        print(f"{name:20s} mean of blocks 1-{args.repeats - 1}: {sum(times[1:]) / max(len(times) - 1, 1):.2f} ms")
    values, counts = torch.unique(per_body, return_counts=True)
    print(f"first step, CG iterations per body: mean {float(per_body.float().mean()):.1f}, most "
          f"{int(per_body.max())}; {dict(zip(values.tolist(), counts.tolist()))}")
    return blocks, apart, per_body


if __name__ == "__main__":
    main()
