"""Where a step of a pile with body contact spends its time, phase by phase: each of the step's
contact and solver functions timed with a synchronising timer around it (calls a step, ms a
step, and for the CG its iterations and ms an iteration), after the step's own rate without
the timers.

    python benchmarks/probes/contact_step_phases_probe.py [--columns 10] [--steps 120] [--timed 10]
                                                          [--state DIR] [--contact '{"rounds": 1}']
                                                          [--device cuda]

The pile is ``contact_piles``' (columns x columns x columns blocks), stepped ``--steps`` steps
with contact, or taken from a state ``contact_piles.py --state`` saved (``DIR/x.pt``, ``v.pt``),
then 10 steps more; ``--contact``: keyword arguments of its ``tm.Contact`` as JSON. The timers
serialise the device at each call, so the phases' sum exceeds the step's rate: they say where the
time goes, not what it costs overlapped. Nested phases are each counted (a solve holds its CG).
"""
import functools
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

from tensormass_torch.ops import contact as contact_ops  # noqa: E402
from tensormass_torch.physics import body_contact  # noqa: E402
from tensormass_torch.solver import cg, implicit_euler, preconditioner  # noqa: E402

#: (owner, attribute) of each phase timed; the label is the owner's short name and the attribute.
PHASES = [(contact_ops, name) for name in ("candidate_pairs", "nearest_pairs")] + \
    [(body_contact.SurfaceContact, name) for name in ("at_state", "nearby", "candidates", "_search", "_motion",
                                                      "_step_candidates", "settled", "relinearise", "select")] + \
    [(body_contact.ContactPairs, name) for name in ("forces", "dforces", "stiffness_blocks")] + \
    [(body_contact.PairStiffness, "load"), (body_contact, "coupled_ranges"), (preconditioner.JacobiScaling, "load"),
     (cg.CGSolver, "solve"), (cg.CGSolver, "resume")] + \
    [(implicit_euler, name) for name in ("_step_system", "_pairs_rhs", "_jacobi", "_coupled_solver",
                                         "_solve_pausing", "system_diagonal_blocks")]


def timed(owner, name, device, times: dict):
    """Wrap ``owner.name`` with a synchronising timer adding to ``times[label]`` [seconds, calls,
    CG iterations]; returns the original (to restore)."""
    original = getattr(owner, name)
    label = f"{getattr(owner, '__name__', type(owner).__name__).rpartition('.')[2]}.{name}"

    @functools.wraps(original)
    def wrapper(*args, **kwargs):
        common.sync(device)
        start = time.perf_counter()
        out = original(*args, **kwargs)
        common.sync(device)
        entry = times.setdefault(label, [0.0, 0, 0])
        entry[0] += time.perf_counter() - start
        entry[1] += 1
        if isinstance(out, cg.CGResult):
            entry[2] += int(out.iterations.max())
        return out

    setattr(owner, name, wrapper)
    return original


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=10)
    sim = contact_piles.pile_simulator(args)
    sim.step(10)
    rate = contact_piles.rate(sim, args.timed, args.device)
    times: dict = {}
    originals = [(owner, name, timed(owner, name, args.device, times)) for owner, name in PHASES]
    try:
        common.sync(args.device)
        start = time.perf_counter()
        sim.step(args.timed)
        common.sync(args.device)
        synced = (time.perf_counter() - start) / args.timed
    finally:
        for owner, name, original in originals:
            setattr(owner, name, original)
    report = sim.last_report
    print(f"{sim.num_bodies} blocks, contact {args.contact}: {1e3 / rate:.1f} ms a step ({rate:.1f} steps/s), "
          f"{1e3 * synced:.1f} ms timed; the last step's solves {[int(c.iterations.max()) for c in report.cg]}, "
          f"{len(report.contact_solves[-1][0])} pairs")
    for label, (seconds, calls, iterations) in sorted(times.items(), key=lambda item: -item[1][0]):
        line = f"  {label:36s} {1e3 * seconds / args.timed:8.2f} ms a step  {calls / args.timed:5.2f} calls a step"
        if iterations:
            line += f"  {iterations / args.timed:6.1f} iterations a step, {1e3 * seconds / iterations:.3f} ms each"
        print(line)
    return dict(steps_per_s=rate, timed_s=synced, phases=times)


if __name__ == "__main__":
    main()
