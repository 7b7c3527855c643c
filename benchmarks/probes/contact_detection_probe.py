"""Where a detection of the contact between bodies spends its time, with the broad phase's walk
over the hash and the narrow phase as the ops (``ops.contact``) and as their tensor-op
references, at one state of a pile.

    python benchmarks/probes/contact_detection_probe.py [--columns 4 10] [--steps 60] [--device cuda]
                                                        [--cells 10 10 5] [--dtype float32]
                                                        [--profile FILE]

Each pile is ``contact_piles``' (columns x columns x columns blocks), stepped ``--steps`` steps
with contact; at that state, the mean of 10 (after one): the broad phase
(``SurfaceContact.candidates``, swept at the state's velocities) and a whole detection
(``detect``) through the ops and through the references, whether both found the same candidates
and pairs, then steps/s over 10 steps each way (from the same state). Prints one JSON line per
pile. ``--profile FILE``: then, for each pile, Python's profile of 3 steps (cumulative time,
the functions a step spends its time under) and torch's of one step and of one detection
(operators by self CUDA time on the GPU, by self CPU time on the CPU, with their calls),
appended to FILE.
"""
import argparse
import json
import sys
import time
from functools import partial
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.ops import contact as contact_ops  # noqa: E402
from tensormass_torch.physics import body_contact  # noqa: E402


class Phases:
    """Swaps the broad phase's walk and the narrow phase for their references while in use
    (``native`` False)."""

    NAMES = ("candidate_pairs", "nearest_pairs")

    def __init__(self, native: bool):
        self.native = native

    def __enter__(self):
        self.saved = {name: getattr(body_contact.contact_ops, name) for name in self.NAMES}
        for name in self.NAMES:
            setattr(body_contact.contact_ops, name, partial(getattr(contact_ops, name), native=self.native))

    def __exit__(self, *exc):
        for name, fn in self.saved.items():
            setattr(body_contact.contact_ops, name, fn)


def mean_ms(fn, device, repeats=10):
    fn()
    common.sync(device)
    start = time.perf_counter()
    for _ in range(repeats):
        out = fn()
    common.sync(device)
    return 1e3 * (time.perf_counter() - start) / repeats, out


def profiles(sim, out, label):
    """Python's profile of 3 steps and torch's of one step and one detection, appended to ``out``."""
    import cProfile
    import io
    import pstats

    from torch.profiler import ProfilerActivity, profile

    device = sim.x.device.type
    profiler = cProfile.Profile()
    profiler.enable()
    sim.step(3)
    common.sync(device)
    profiler.disable()
    text = io.StringIO()
    pstats.Stats(profiler, stream=text).sort_stats("cumulative").print_stats(40)
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    tables = []
    for what, fn in (("one step", lambda: sim.step()),
                     ("one detection", lambda: sim.body_contact.detect(sim.x, sim.v, contact_piles.DT))):
        with profile(activities=activities) as prof:
            fn()
            common.sync(device)
        key = "self_cuda_time_total" if device == "cuda" else "self_cpu_time_total"
        tables.append(f"## {label}: {what}\n" + prof.key_averages().table(sort_by=key,
                                                                         row_limit=30, max_name_column_width=50))
    with open(out, "a") as f:
        f.write(f"# {label}: 3 steps, cumulative\n{text.getvalue()}\n" + "\n".join(tables) + "\n")


def probe(columns, cells, steps, device, dtype, profile_to=None):
    bodies, _ = contact_piles.pile(columns, cells, device, dtype)
    sim = contact_piles.simulator(bodies, tm.Contact(), device, dtype)
    sim.step(steps)
    contact, x, v = sim.body_contact, sim.x.clone(), sim.v.clone()
    row = dict(blocks=len(bodies), surface_triangles=len(contact.triangles), surface_vertices=len(contact.vertices),
               steps=steps)
    found = {}
    for native in (True, False):
        name = "op" if native else "reference"
        with Phases(native):
            row[f"candidates_ms_{name}"], found[name] = mean_ms(lambda: contact.candidates(x, v, contact_piles.DT),
                                                                device)
            row[f"detect_ms_{name}"], pairs = mean_ms(lambda: contact.detect(x, v, contact_piles.DT), device)
            found[name + "_pairs"] = pairs.nodes
    row["candidates"] = len(found["op"][0])
    row["same_candidates"] = all(torch.equal(a, b) for a, b in zip(found["op"], found["reference"]))
    row["same_pairs"] = torch.equal(found["op_pairs"], found["reference_pairs"])
    # pairs one found and the other did not: a tie between two triangles within rounding, or a
    # distance at the reach, decided the other way by the op's fused arithmetic
    both = torch.cat([found["op_pairs"], found["reference_pairs"]])
    row["pairs"] = len(found["op_pairs"])
    row["pairs_differing"] = int((torch.unique(both, dim=0, return_counts=True)[1] == 1).sum())
    for native in (True, False):
        name = "op" if native else "reference"
        sim.x, sim.v = x.clone(), v.clone()
        with Phases(native):
            sim.step(2)
            row[f"steps_per_s_{name}"] = contact_piles.rate(sim, 10, device)
            row[f"solves_last_step_{name}"] = len(sim.last_report.cg)
    if profile_to:
        profiles(sim, profile_to, f"{len(bodies)} blocks")
    return row


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--columns", type=int, nargs="+", default=[4])
    parser.add_argument("--cells", type=int, nargs=3, default=[10, 10, 5])
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--profile", default=None, help="append profiles of each pile's steps to this file")
    args = parser.parse_args(argv)
    for columns in args.columns:
        print(json.dumps(probe(columns, tuple(args.cells), args.steps, args.device, getattr(torch, args.dtype),
                               args.profile)),
              flush=True)


if __name__ == "__main__":
    main()
