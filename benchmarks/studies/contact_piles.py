"""Contact between bodies at scale: piles of soft blocks in columns dropped onto a floor,
steps/s with body contact against without it in the same run, the detection's time against the
number of surface triangles, and the deepest interpenetration over the run.

    python benchmarks/studies/contact_piles.py [--columns 2 4 6] [--cells 10 10 5] [--steps 120]
                                               [--friction 0] [--model corotational] [--young 1e6]
                                               [--shift 0.01] [--no-swept] [--check-every 0]
                                               [--preconditioners auto none] [--rounds R ...] [--tolerance T]
                                               [--recheck-tolerance T]
                                               [--check-tols C ...] [--skins S ...] [--check-margins M ...]
                                               [--window 100] [--warm-start none] [--without-steps 0]
                                               [--paired-blocks on off]
                                               [--device cuda]
                                               [--dtype float32] [--state DIR --budget-s 540]
                                               [--save-state DIR]
                                               [--out benchmarks/results/contact] [--quick]

Each pile is columns x columns stacks of ``columns`` blocks (0.2 x 0.2 x 0.1 m, corotational, E =
1e6 Pa (``--model``, ``--young``), nu = 0.3, 1000 kg/m^3; ``--cells`` per block: 10 x 10 x 5 is
3,000 tets), the columns 5 cm apart, the blocks of a column 3 cm apart and shifted 1 cm sideways
each (an offset stack; ``--shift 0``: straight stacks), over a floor plane of 1e5 N/m; dt = 5 ms,
Rayleigh mass damping 1/s, cg_tol 1e-4. With contact the pile runs ``--steps`` steps (the deepest
interpenetration over them is reported), then 10 more are timed, once for each of
``--preconditioners`` (the Simulator's ``preconditioner``); without contact, with the same
preconditioner, 10 steps after 10 of warm-up (the blocks fall through each other: only the rate is
compared; the preconditioner is the same on both sides, as it changes the pile without contact
too: ``"rigid"``'s coarse correction carries the blocks' common fall, which plain CG iterates on). Detection:
``SurfaceContact.detect`` at the final state, mean of 10. ``--rounds``: a run with contact for each
``Contact(rounds=...)`` (how many more solves a step may take to check its contact set: the trade of
cost against transient interpenetration); ``--tolerance``: the ``Contact(tolerance=...)`` of every
run (how deep past its pair's model a vertex may end a step before the step takes a round),
``--recheck-tolerance`` its ``Contact(recheck_tolerance=...)`` (the same after a round's solve);
``--check-tols``: a run for each ``Contact(check_tol=...)`` (the CG tolerance of the solves a
contact-set check reads); ``--skins``: a run for each ``Contact(skin=...)`` (the broad phase's
candidates kept while the surfaces move less); ``--check-margins``: a run for each
``Contact(check_margin=...)`` (how far from the step's prediction a solve may leave the surfaces for
the step's checks to take the step's own candidates). No block may pass through another: besides the
deepest interpenetration the steps report (over the pairs the contact finds), the exact one
(``Simulator.interpenetration``: every surface vertex inside another block, whatever its depth) is
measured at the end and every ``--check-every`` steps (each check's step, interpenetration, kinetic
energy and blocks out of order go to the JSON), and at the end the pairs of blocks of one column
still over each other whose order from the floor up changed. The run's time is the stepping's alone
(``stepping_s``, ``steps_per_s_run``, ``cost_ratio_run`` against the pile without contact), recorded
every ``--window`` steps (``windows``: first step, last step, seconds, solves, CG iterations, the
largest of a solve's objects summed over its solves) with the checks timed apart
(``check_s``; ``run_s`` is both). ``--paired-blocks on off``: a run for each
``Simulator(paired_blocks=...)`` (block Jacobi with the nodes contact pairs couple merged, the
default, or each node's own block). ``--without-steps N`` also times the pile without contact over N
steps from the start (``steps_per_s_without_run``; the blocks fall through each other onto the
floor) and gives the run's cost against that (``cost_ratio_run_against_run``). A run longer than one sitting:
``--state DIR --budget-s S`` saves the state after S seconds of stepping and stops; the same command
goes on from it. ``--save-state DIR`` keeps each run's end state (``DIR/columns{C}_{preconditioner}...``,
``x.pt`` and ``v.pt``) for the probes' ``--state``. Writes ``contact_piles.md`` and ``.json`` to ``--out``.
"""
import argparse
import json
import sys
import time
from pathlib import Path
from typing import Optional

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import common  # noqa: E402

import tensormass_torch as tm  # noqa: E402

DT = 0.005


#: The blocks' model and Young's modulus (Pa). Tumbling blocks turn by tens of degrees, and the
#: linear model (hooke) is not invariant under rotation: a block turned by theta about its normal
#: settles stretched by 1 / cos(theta) in its plane, growing into its neighbours. Blocks of 1e5 Pa
#: (a gel) falling a metre invert elements where they land, and an inverted element lets vertices
#: through whatever the contact does (docs/contact.md, Limits).
MODEL, YOUNG = "corotational", 1e6

#: How far sideways (m) each block of a column starts from the one under it. Offset columns make a
#: pile rather than stacks: they lean, and their blocks slide or tip off (frictionless offset
#: columns never come to rest, docs/contact.md). 0 gives straight stacks, which can.
SHIFT = 0.01


def pile(columns: int, cells, device, dtype, model: str = MODEL, young: float = YOUNG, shift: float = SHIFT,
         levels: Optional[int] = None):
    """The pile's bodies: columns x columns stacks of ``levels`` blocks (None: ``columns``) of
    material ``model`` with Young's modulus ``young``, each block ``shift`` (m) sideways from the
    one under it."""
    material = tm.Material(young=young, poisson=0.3, density=1000, model=model)
    block = tm.beam_mesh(*cells, size=(0.2, 0.2, 0.1), dtype=dtype)
    bodies = []
    for i in range(columns):
        for j in range(columns):
            for k in range(columns if levels is None else levels):
                offset = torch.tensor([0.25 * i + shift * k, 0.25 * j, 0.02 + 0.13 * k], dtype=dtype)
                bodies.append(tm.Body(tm.TetMesh(block.vertices + offset, block.elements, check=False), material))
    return bodies, block


def simulator(bodies, contact, device, dtype, preconditioner="auto", warm_start=False, paired_blocks=True):
    return tm.Simulator(bodies, dt=DT, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=contact, rayleigh_mass=1.0,
                        device=device, dtype=dtype, cg_tol=1e-4, preconditioner=preconditioner,
                        warm_start=warm_start, paired_blocks=paired_blocks)


def pile_arguments(argv, description: str, timed: int, extend=None):
    """The probes' command line for a pile with contact (:func:`pile_simulator`): --columns,
    --levels, --cells, --shift, --steps, --timed (``timed`` steps by default), --state, --contact
    and --device, and those ``extend`` (a function of the ``argparse.ArgumentParser``, or None) adds,
    parsed from ``argv`` (None: the process's)."""
    parser = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    if extend is not None:
        extend(parser)
    parser.add_argument("--columns", type=int, default=10)
    parser.add_argument("--levels", type=int, default=None, help="blocks a stack (default: --columns)")
    parser.add_argument("--cells", type=int, nargs=3, default=[10, 10, 5])
    parser.add_argument("--shift", type=float, default=SHIFT, help="each block's start sideways from the one under it")
    parser.add_argument("--steps", type=int, default=120, help="steps with contact before (without --state)")
    parser.add_argument("--timed", type=int, default=timed, help="steps looked at")
    parser.add_argument("--state", default=None, help="a folder of contact_piles.py --state (x.pt, v.pt)")
    parser.add_argument("--contact", type=json.loads, default={}, help="tm.Contact's keyword arguments, JSON")
    parser.add_argument("--device", default=common.default_device())
    return parser.parse_args(argv)


def pile_simulator(args, dtype=torch.float32, bodies=None, preconditioner=None):
    """The pile of :func:`pile_arguments`' ``args`` with contact, stepped ``args.steps`` steps
    or taken from the state ``args.state`` holds (``x.pt``, ``v.pt``, as ``--state`` saves it),
    with ``preconditioner`` (None: ``args.preconditioner`` where the probe has that option, else
    ``"auto"``); ``bodies``: the pile's, where the caller made them already (None: made here)."""
    if bodies is None:
        bodies, _ = pile(args.columns, args.cells, args.device, dtype, shift=args.shift, levels=args.levels)
    preconditioner = preconditioner or getattr(args, "preconditioner", "auto")
    sim = simulator(bodies, tm.Contact(**args.contact), args.device, dtype, preconditioner)
    if args.state is not None:
        sim.x = torch.load(Path(args.state) / "x.pt").to(sim.x)
        sim.v = torch.load(Path(args.state) / "v.pt").to(sim.v)
    else:
        sim.step(args.steps)
    return sim


def pile_start(args, dtype=torch.float32):
    """(bodies, x, v): the pile of :func:`pile_arguments`' ``args`` and the state its simulators
    start from (:func:`pile_simulator`'s, stepped or loaded), for probes that make several."""
    bodies, _ = pile(args.columns, args.cells, args.device, dtype, shift=args.shift, levels=args.levels)
    start = pile_simulator(args, dtype, bodies, "auto")
    return bodies, start.x.clone(), start.v.clone()


def rate(sim, steps: int, device) -> float:
    common.sync(device)
    start = time.perf_counter()
    sim.step(steps)
    common.sync(device)
    return steps / (time.perf_counter() - start)


def without_contact(bodies, device, dtype, preconditioner: str = "auto", warm_start=False, steps: int = 0) -> dict:
    """The same pile without contact, with the same ``preconditioner`` and ``warm_start`` as the run
    it is compared with (the blocks fall through each other: only the rate counts): 10 steps timed
    after 10, and with ``steps`` > 0 the rate over that many steps from the start too
    (``steps_per_s_without_run``: the blocks fall through each other onto the floor, whose penalty
    rows the solves then carry, as the run with contact carries its pairs)."""
    free = simulator(bodies, None, device, dtype, preconditioner, warm_start)
    free.step(10)
    without = rate(free, 10, device)
    iterations = max(int(c.iterations.max()) for c in free.last_report.cg)
    record = dict(steps_per_s_without=without, cg_iterations_without=iterations)
    if steps > 0:
        free = simulator(bodies, None, device, dtype, preconditioner, warm_start)
        record["steps_per_s_without_run"] = rate(free, steps, device)
        record["cg_iterations_without_end"] = max(int(c.iterations.max()) for c in free.last_report.cg)
    del free
    common.release(device)
    return record


def measure(columns: int, cells, steps: int, friction: float, device, dtype, check_every: int = 0,
            swept: bool = True, preconditioner: str = "auto", baseline: Optional[dict] = None,
            state: Optional[Path] = None, budget_s: Optional[float] = None, window: int = 100,
            warm_start=False, without_steps: int = 0, model: str = MODEL, young: float = YOUNG, shift: float = SHIFT,
            paired_blocks: bool = True, save_state: Optional[Path] = None, **settings) -> Optional[dict]:
    """One pile with contact (``baseline``: :func:`without_contact`'s with the same
    ``preconditioner``, measured here when None),
    ``settings``: its ``tm.Contact``'s (the library's defaults for those not given).
    With ``state`` (a folder), the run goes on from the state saved there (positions,
    velocities, step and what was measured so far) and, when ``budget_s`` seconds of stepping
    have passed, saves it there and returns None: a run longer than one sitting of a machine
    resumes where it stopped. From the saved positions and velocities only: the simulator's
    carried state (such as the coupled solves' layout) starts afresh, so a resumed run matches the
    uninterrupted one to roundoff at first, not bit for bit, and a tumbling pile then drifts
    apart (``contact_pile_1000_corotational_2000_steps.md``). ``save_state`` (a folder): where
    the run's end state goes (``x.pt``, ``v.pt``: the probes' ``--state``)."""
    bodies, block = pile(columns, cells, device, dtype, model, young, shift)
    sim = simulator(bodies, tm.Contact(friction=friction, swept=swept, **settings), device, dtype, preconditioner,
                    warm_start, paired_blocks)
    saved = state / "meta.json" if state is not None else None
    if saved is not None and saved.exists():
        progress = json.loads(saved.read_text())
        sim.x = torch.load(state / "x.pt").to(sim.x)
        sim.v = torch.load(state / "v.pt").to(sim.v)
    else:
        progress = dict(step=0, deepest=0.0, checks=[], run_s=0.0,
                        **(baseline if baseline is not None else
                           without_contact(bodies, device, dtype, preconditioner, warm_start, without_steps)))
    progress.setdefault("windows", [])
    progress.setdefault("check_s", 0.0)
    deepest = torch.tensor(progress["deepest"], dtype=sim.x.dtype, device=sim.x.device)
    solves, iterations = 0, torch.zeros((), dtype=torch.int64, device=sim.x.device)  # over the window
    common.sync(device)
    start = window_start = time.perf_counter()
    window_from = progress["step"]
    for step in range(progress["step"] + 1, steps + 1):
        # the deepest kept on the device: the loop reads nothing back between the checks
        report = sim.step()
        deepest = torch.maximum(deepest, report.contact.body_penetration.max())
        solves += len(report.cg)
        for result in report.cg:  # kept on the device too
            iterations += result.iterations.max()
        progress["step"] = step
        check = step == steps or (check_every and step % check_every == 0)
        boundary = check or step % window == 0
        if boundary:  # the stepping's time, the checks' apart
            common.sync(device)
            now = time.perf_counter()
            progress["windows"].append([window_from, step, now - window_start, solves, int(iterations)])
            window_from, solves = step, 0
            iterations.zero_()
        if check:
            progress["deepest"] = max(progress["deepest"], float(deepest))
            progress["checks"].append([step, float(sim.interpenetration().max()), float(sim.kinetic_energy().sum()),
                                       out_of_order(sim, columns)])
            common.sync(device)
            progress["check_s"] += time.perf_counter() - now
            stepping = sum(w[2] for w in progress["windows"])
            print(f"step {step}: inside {progress['checks'][-1][1]:.3e} m, out of order {progress['checks'][-1][3]}, "
                  f"{step / (progress['run_s'] + time.perf_counter() - start):.2f} steps/s with the checks, "
                  f"{step / stepping:.2f} without them", flush=True)
        if boundary:  # the next window starts after the check
            window_start = time.perf_counter()
        if state is not None and budget_s is not None and step < steps and time.perf_counter() - start > budget_s:
            progress["deepest"] = max(progress["deepest"], float(deepest))
            progress["run_s"] += time.perf_counter() - start
            state.mkdir(parents=True, exist_ok=True)
            torch.save(sim.x.cpu(), state / "x.pt")
            torch.save(sim.v.cpu(), state / "v.pt")
            saved.write_text(json.dumps(progress))
            print(f"paused at step {step} of {steps}; the state is in {state}", flush=True)
            return None
    progress["deepest"] = max(progress["deepest"], float(deepest))
    progress["run_s"] += time.perf_counter() - start
    stepping_s = sum(w[2] for w in progress["windows"])
    inside = max(c[1] for c in progress["checks"])
    if save_state is not None:
        save_state.mkdir(parents=True, exist_ok=True)
        torch.save(sim.x.cpu(), save_state / "x.pt")
        torch.save(sim.v.cpu(), save_state / "v.pt")
    with_contact = rate(sim, 10, device)
    contact = sim.body_contact
    common.sync(device)
    start = time.perf_counter()
    for _ in range(10):
        pairs = contact.detect(sim.x, sim.v, DT)
    common.sync(device)
    detect_ms = 100.0 * (time.perf_counter() - start)
    report = sim.last_report
    without = progress["steps_per_s_without"]
    return dict(blocks=len(bodies), tets=len(bodies) * block.num_elements, surface_triangles=len(contact.triangles),
                pairs=len(pairs), steps=steps, run_s=progress["run_s"], stepping_s=stepping_s,
                check_s=progress["check_s"], steps_per_s_run=steps / stepping_s,
                cost_ratio_run=without * stepping_s / steps, windows=progress["windows"],
                **({} if "steps_per_s_without_run" not in progress else dict(
                    steps_per_s_without_run=progress["steps_per_s_without_run"],
                    cg_iterations_without_end=progress["cg_iterations_without_end"],
                    cost_ratio_run_against_run=progress["steps_per_s_without_run"] * stepping_s / steps)),
                deepest_m=progress["deepest"],
                preconditioner=preconditioner, paired_blocks=paired_blocks, warm_start=sim.options.warm_start,
                rounds=contact.settings.rounds,
                tolerance_m=contact.tolerance,
                recheck_tolerance_m=contact.recheck_tolerance,
                check_tol=contact.settings.check_tol, skin=contact.skin,
                check_margin_m=contact.check_margin,
                steps_per_s_without=without,
                steps_per_s_with=with_contact,
                cost_ratio=without / with_contact, detect_ms=detect_ms,
                cg_iterations=max(int(c.iterations.max()) for c in report.cg),
                cg_iterations_step=sum(int(c.iterations.max()) for c in report.cg),
                cg_iterations_without=progress["cg_iterations_without"], solves=len(report.cg),
                interpenetration_m=inside, mean_edge_m=contact.search, checks=progress["checks"],
                out_of_order=out_of_order(sim, columns))


def column_centroids(sim, columns: int) -> torch.Tensor:
    """The blocks' centroids ``[column, level from the floor, 3]`` (the pile's bodies in order)."""
    segments = sim.segments
    centroids = torch.stack([segments.sum(sim.x[:, i]) for i in range(3)], -1) / segments.lengths[:, None]
    return centroids.reshape(columns * columns, columns, 3)


def out_of_order(sim, columns: int) -> int:
    """How many pairs of blocks of one column, still over each other in plan (centroids less than
    15 cm apart: the blocks are 20 cm wide), are no longer in their starting order from the floor
    up: the block that started above lies more than half a block's thickness (5 cm) below the
    other. A block through the one under it, or a tumbling pile that stacked them again the
    other way (blocks knocked off, one falling to the floor first); the interpenetration tells
    them apart only while the first is still inside. (Two blocks side by side at one height, as
    two knocked on their edges against each other, are not counted: the margin.)"""
    stacks = column_centroids(sim, columns)
    plan = torch.linalg.vector_norm(stacks[:, :, None, :2] - stacks[:, None, :, :2], dim=-1)
    below = torch.ones(columns, columns, dtype=torch.bool, device=sim.x.device).triu(1)  # level a under b
    flipped = (stacks[:, :, None, 2] > stacks[:, None, :, 2] + 0.05) & (plan < 0.15) & below
    return int(flipped.sum())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--columns", type=int, nargs="+", default=[2, 4, 6])
    parser.add_argument("--cells", type=int, nargs=3, default=[10, 10, 5])
    parser.add_argument("--steps", type=int, default=120)
    parser.add_argument("--friction", type=float, default=0.0)
    parser.add_argument("--model", default=MODEL, choices=list(tm.MODELS),
                        help="the blocks' material model (default corotational: the blocks tumble)")
    parser.add_argument("--young", type=float, default=YOUNG, help="the blocks' Young's modulus (Pa)")
    parser.add_argument("--shift", type=float, default=SHIFT,
                        help="how far sideways (m) each block of a column starts from the one under it (0: straight "
                             "stacks)")
    parser.add_argument("--swept", action=argparse.BooleanOptionalAction, default=True,
                        help="Contact(swept=...): pairs over each step's motion (the default) or at its start")
    parser.add_argument("--preconditioners", nargs="+", default=["auto"],
                        choices=["auto", "none", "jacobi", "rigid", "multigrid"],
                        help="a run with contact for each (the pile without contact is measured once)")
    parser.add_argument("--rounds", type=int, nargs="+", default=[tm.Contact().rounds],
                        help="a run with contact for each Contact(rounds=...) (and each preconditioner)")
    parser.add_argument("--tolerance", type=float, default=None,
                        help="Contact(tolerance=...) (m): how deep past its model a vertex may end before a round "
                             "(default: the library's, 1/400 of the mean surface edge)")
    parser.add_argument("--recheck-tolerance", type=float, default=None,
                        help="Contact(recheck_tolerance=...) (m): the same after a round's solve (default: the "
                             "library's, 1/100 of the mean surface edge)")
    parser.add_argument("--check-tols", type=lambda t: None if t == "none" else float(t), nargs="+",
                        default=[tm.Contact().check_tol],
                        help="a run with contact for each Contact(check_tol=...) (the CG tolerance of the solves "
                             "a contact-set check reads; default: the library's; none: cg_tol for every solve)")
    parser.add_argument("--skins", type=lambda t: None if t == "none" else float(t), nargs="+",
                        default=[tm.Contact().skin],
                        help="a run with contact for each Contact(skin=...) (m; none: the library's, 1/10 of the "
                             "search; 0: every detection searches)")
    parser.add_argument("--check-margins", type=lambda t: None if t == "none" else float(t), nargs="+",
                        default=[tm.Contact().check_margin],
                        help="a run with contact for each Contact(check_margin=...) (m; none: the library's, "
                             "1/16 of the search; 0: every check searches)")
    parser.add_argument("--state", default=None,
                        help="a folder to save the run's state in when --budget-s runs out, and to go on from")
    parser.add_argument("--budget-s", type=float, default=None, help="seconds of stepping before saving (--state)")
    parser.add_argument("--save-state", default=None,
                        help="a folder to keep each run's end state in (x.pt, v.pt, in a folder a run: the "
                             "probes' --state)")
    parser.add_argument("--check-every", type=int, default=0,
                        help="measure the interpenetration every this many steps (0: at the end only)")
    parser.add_argument("--warm-start", default=False, choices=["none", "extrapolate", "project"],
                        help="the Simulator's warm_start, with contact and without")
    parser.add_argument("--paired-blocks", nargs="+", default=["on"], choices=["on", "off"],
                        help="a run with contact for each Simulator(paired_blocks=...) (block Jacobi's merged "
                             "contact nodes)")
    parser.add_argument("--without-steps", type=int, default=0,
                        help="also time the pile without contact over this many steps from the start (0: not)")
    parser.add_argument("--window", type=int, default=100,
                        help="the run's stepping time is recorded every this many steps (and at each check)")
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "results" / "contact"))
    parser.add_argument("--quick", action="store_true", help="one small pile, a few steps (the tests' run)")
    args = parser.parse_args(argv)
    if args.quick:
        args.columns, args.cells, args.steps = [2], [2, 2, 1], 3
    dtype = getattr(torch, args.dtype)
    meta = common.metadata(args.device, dtype=args.dtype, cells=args.cells, friction=args.friction, model=args.model,
                           young=args.young, shift=args.shift)
    columns = [("blocks", "blocks", None), ("tets", "tets", ","), ("surface_triangles", "surface triangles", ","),
               ("pairs", "pairs", ","), ("steps_per_s_without", "steps/s without", ".1f"),
               ("steps_per_s_with", "steps/s with", ".1f"), ("cost_ratio", "cost (x)", ".1f"),
               ("steps_per_s_run", "steps/s over the run", ".1f"), ("cost_ratio_run", "cost over the run (x)", ".1f"),
               ("check_s", "checks (s)", ".1f"),
               ("steps_per_s_without_run", "steps/s without over the run", ".1f"),
               ("cost_ratio_run_against_run", "cost over the run against the run without (x)", ".2f"),
               ("detect_ms", "detection (ms)", ".2f"), ("cg_iterations_without", "CG iterations without", None),
               ("preconditioner", "preconditioner", None), ("rounds", "rounds", None),
               ("tolerance_m", "tolerance (m)", ".2e"), ("recheck_tolerance_m", "recheck tolerance (m)", ".2e"),
               ("check_tol", "check_tol", None),
               ("skin", "skin (m)", None), ("check_margin_m", "check margin (m)", ".2e"),
               ("cg_iterations", "CG iterations with (most of one solve)", None),
               ("cg_iterations_step", "CG iterations of the last step", None),
               ("solves", "solves in the last step", None),
               ("deepest_m", "deepest in the reports (m)", ".2e"),
               ("interpenetration_m", "deepest inside another body (m)", ".2e"),
               ("out_of_order", "stacked blocks out of order", None),
               ("mean_edge_m", "mean surface edge (m)", ".2e")]
    notes = [f"{args.dtype}, {args.model} blocks of {args.cells} cells, E = {args.young:g} Pa, "
             f"friction {args.friction:g}, each block {args.shift:g} m sideways from the one under it, "
             f"swept {args.swept}, dt {DT} s, "
             f"{args.steps} steps with contact before the timed ones."]
    results = common.Results(args.out, "contact_piles", "Piles of blocks: steps/s with body contact against "
                             "without, detection time", meta, columns, notes)
    for c in args.columns:  # written as each pile is measured: a later failure loses nothing
        baselines = {}  # the pile without contact, measured once for each preconditioner
        for preconditioner, paired, rounds, check_tol, skin, margin in [
                (p, q, r, t, k, m) for p in args.preconditioners for q in args.paired_blocks for r in args.rounds
                for t in args.check_tols for k in args.skins for m in args.check_margins]:
            suffix = "" if args.rounds == [tm.Contact().rounds] else f"_rounds{rounds}"
            suffix += "" if args.check_tols == [tm.Contact().check_tol] else f"_check{check_tol}"
            suffix += "" if args.skins == [tm.Contact().skin] else f"_skin{skin}"
            suffix += "" if args.check_margins == [tm.Contact().check_margin] else f"_margin{margin}"
            suffix += "" if paired == "on" else "_unpaired"
            name = f"columns{c}_{preconditioner}{suffix}"
            state = None if args.state is None else Path(args.state) / name
            end_state = None if args.save_state is None else Path(args.save_state) / name
            record = measure(c, args.cells, args.steps, args.friction, args.device, dtype, args.check_every,
                             args.swept, preconditioner, baselines.get(preconditioner), state, args.budget_s,
                             args.window, args.warm_start, args.without_steps, args.model, args.young,
                             args.shift, paired == "on", rounds=rounds, tolerance=args.tolerance,
                             recheck_tolerance=args.recheck_tolerance, check_tol=check_tol, skin=skin,
                             check_margin=margin, save_state=end_state)
            if record is None:  # paused: the state is saved, the rest waits for the next run
                results.finish()
                return results.records
            baselines[preconditioner] = {k: record[k] for k in ("steps_per_s_without", "cg_iterations_without",
                                                                "steps_per_s_without_run", "cg_iterations_without_end")
                                         if k in record}
            results.add(record, echo=False)
    results.finish()
    return results.records


if __name__ == "__main__":
    main()
