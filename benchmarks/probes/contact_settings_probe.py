"""Contact settings compared on one pile in one process: a simulator for each setting, all
started from the same state and stepped in alternated blocks of steps, beside the pile without
contact. Rates measured in separate processes differ by 10-15 % on the piles (the machine's
state, not the setting); alternated blocks in one process put that drift on every setting alike.

    python benchmarks/probes/contact_settings_probe.py [--columns 10] [--levels L] [--shift 0.01]
                                                       [--steps 120] [--state DIR]
                                                       [--contact '{"friction": 0.5}']
                                                       [--setting NAME=JSON ...] [--timed 10]
                                                       [--repeats 3] [--save-state DIR]
                                                       [--out settings.json] [--device cuda]

The pile is ``contact_piles``' (``pile_arguments``; ``--columns 1 --levels 10``: one stack of ten),
stepped ``--steps`` steps with ``--contact`` or taken from ``--state``; ``--save-state DIR`` keeps
that state (``x.pt``, ``v.pt``) for later runs. Each ``--setting`` is a name and a JSON object: the
keyword arguments of its ``tm.Contact``, over ``--contact``'s, ``"preconditioner"``,
``"warm_start"`` and ``"paired_blocks"``, the Simulator's, ``"rigid_grouping"``, the groups of
``preconditioner="rigid"``'s coarse solve (``"contact"``, its default, or ``"morton"``), and
``"rigid_refresh"``, the loads between two computations of its bodies' part, ``"rigid_lag_pairs"``,
whether its lagged loads keep the last coarse inverses whole, and ``"check_ahead"``, the stretches
of a paused solve its contact check runs beside on the GPU (``DynamicsSystem.check_ahead``; 0: after
the solve), ``"settled_wait"``, the most steps its settled test waits after failures
(``SurfaceContact.settled_wait``; 0: it tests at every step) (by default one setting,
``default={}``). Every simulator takes two steps before the blocks, then ``--repeats`` times each
takes ``--timed`` steps in turn; the pile without contact (as ``contact_piles.py`` times it: the
blocks dropped from the start, falling through each other) takes its block first. For each block: ms
a step, CG iterations a step (every solve's), solves a step, and at its end the kinetic energy and
the deepest pair of the last step. Settings that are exact alternatives of each other (``skin``)
take the same iterations.
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

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.solver.rigid_modes import RigidModeCorrection  # noqa: E402


def setting(text: str):
    """``NAME=JSON`` -> (name, dict)."""
    name, sep, value = text.partition("=")
    if not sep or not name:
        raise SystemExit(f"--setting takes NAME=JSON, got {text!r}")
    settings = json.loads(value)
    if not isinstance(settings, dict):
        raise SystemExit(f"--setting {name}: the JSON must be an object, got {value!r}")
    return name, settings


def extend(parser):
    parser.add_argument("--setting", type=setting, action="append", default=None,
                        help="NAME=JSON: tm.Contact's keyword arguments (and 'preconditioner', 'rigid_grouping', "
                             "'warm_start', 'paired_blocks', 'rigid_refresh', 'rigid_lag_pairs', "
                             "'check_ahead', 'settled_wait')")
    parser.add_argument("--repeats", type=int, default=3, help="blocks of --timed steps for each setting")
    parser.add_argument("--save-state", default=None, help="a folder to keep the pile's starting state in")
    parser.add_argument("--out", default=None, help="a JSON file for the blocks' figures")


def block(sim, steps: int, device) -> dict:
    """``steps`` steps of ``sim``: ms a step, CG iterations a step, solves a step, and the kinetic
    energy and the deepest pair (m) after them."""
    iterations = solves = 0
    common.sync(device)
    start = time.perf_counter()
    for _ in range(steps):
        report = sim.step()
        iterations += sum(int(c.iterations.max()) for c in report.cg)  # (a read the step makes anyway)
        solves += len(report.cg)
    common.sync(device)
    ms = 1e3 * (time.perf_counter() - start) / steps
    deepest = report.contact.body_penetration if report.contact is not None else None
    return dict(ms=ms, iterations=iterations / steps, solves=solves / steps, kinetic_energy=float(sim.kinetic_energy().sum()),
                deepest_m=None if deepest is None or not deepest.numel() else float(deepest.max()))


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=10, extend=extend)
    settings = dict(args.setting or [("default", {})])
    dtype = torch.float32
    bodies, x, v = contact_piles.pile_start(args, dtype)
    if args.save_state is not None:
        folder = Path(args.save_state)
        folder.mkdir(parents=True, exist_ok=True)
        torch.save(x.cpu(), folder / "x.pt")
        torch.save(v.cpu(), folder / "v.pt")
    without = contact_piles.simulator(bodies, None, args.device, dtype)
    without.step(10)
    sims = {}
    for name, options in settings.items():
        options = dict(options)
        preconditioner = options.pop("preconditioner", "auto")
        rigid = {key: options.pop(f"rigid_{key}") for key in ("grouping", "refresh", "lag_pairs")
                 if f"rigid_{key}" in options}
        check_ahead = options.pop("check_ahead", None)
        settled_wait = options.pop("settled_wait", None)
        warm_start = options.pop("warm_start", False)
        paired_blocks = options.pop("paired_blocks", True)
        sim = contact_piles.simulator(bodies, tm.Contact(**{**args.contact, **options}), args.device, dtype,
                                      preconditioner, warm_start, paired_blocks)
        if rigid:  # the rigid correction's groups and lag (the others its defaults)
            sim.system._rigid = RigidModeCorrection(**rigid)
        if check_ahead is not None:
            sim.system.check_ahead = int(check_ahead)
        if settled_wait is not None:
            sim.body_contact.settled_wait = int(settled_wait)
        sim.x, sim.v = x.clone(), v.clone()
        sim.step(2)
        sims[name] = sim
    blocks = {name: [] for name in ["without contact", *sims]}
    for _ in range(args.repeats):
        blocks["without contact"].append(block(without, args.timed, args.device))
        for name, sim in sims.items():
            blocks[name].append(block(sim, args.timed, args.device))
    print(f"{len(bodies)} blocks, --contact {json.dumps(args.contact)}; ms a step / CG iterations / solves, "
          f"{args.repeats} blocks of {args.timed} steps each:")
    for name, runs in blocks.items():
        print(f"  {name:24s} " + "   ".join(f"{r['ms']:6.1f} / {r['iterations']:5.1f} / {r['solves']:.1f}"
                                           for r in runs))
    common.write_blocks(args.out, args, blocks)
    return blocks


if __name__ == "__main__":
    main()
