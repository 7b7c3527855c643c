"""What the rigid bodies' coarse correction (``preconditioner="rigid"``) saves and costs on a pile
with body contact: from one state, each preconditioner's ms a step and CG iterations a step, in
turn and twice; then, with "rigid", the ms of a load of the correction and of its pieces (a
synchronising timer around ``RigidModeCorrection.load`` and around ``solver.rigid_modes``' lever arms,
contact groups (the matching within them), own blocks and group matrices; medians over the loads
of ``--timed`` steps) and of one application, eager and captured in a CUDA graph.

    python benchmarks/probes/rigid_modes_probe.py [--columns 10] [--steps 150] [--timed 5]
                                                  [--state DIR] [--contact '{}'] [--device cuda]

The pile is ``contact_piles``' (columns x columns x columns blocks), stepped ``--steps`` steps with
contact (the default preconditioner), or taken from a state ``contact_piles.py --state`` saved; each
preconditioner then starts from that state, steps twice (warm-up) and is timed over ``--timed``.
"""
import dataclasses
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402
import contact_settings_probe  # noqa: E402

from tensormass_torch.solver import rigid_modes  # noqa: E402

#: the load's pieces timed (functions of ``solver.rigid_modes``, patched while the load is timed)
PIECES = ("lever_arms", "contact_groups", "contact_clusters", "own_blocks", "group_matrices")


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=5)
    sim = contact_piles.pile_simulator(args)
    device = args.device
    start_x, start_v = sim.x.clone(), sim.v.clone()
    print(f"{common.metadata(device)['device_name']}; {sim.x.shape[0]:,} nodes", flush=True)
    for preconditioner in ("jacobi", "rigid", "jacobi", "rigid"):
        sim.options = dataclasses.replace(sim.options, preconditioner=preconditioner)
        sim.x, sim.v = start_x.clone(), start_v.clone()
        sim.step(2)
        figures = contact_settings_probe.block(sim, args.timed, device)
        print(f"{preconditioner}: {figures['ms']:.1f} ms a step, {figures['iterations']:.1f} CG iterations a step",
              flush=True)
    correction = sim.system._rigid
    times = {name: [] for name in ("load", *PIECES)}

    def timed(name, function):
        def run(*a, **k):
            common.sync(device)
            began = time.perf_counter()
            out = function(*a, **k)
            common.sync(device)
            times[name].append(time.perf_counter() - began)
            return out

        return run

    plain = {name: getattr(rigid_modes, name) for name in PIECES}
    correction.load = timed("load", correction.load)
    for name in PIECES:
        setattr(rigid_modes, name, timed(name, plain[name]))
    try:
        sim.step(args.timed)
    finally:
        del correction.load
        for name in PIECES:
            setattr(rigid_modes, name, plain[name])
    medians = {name: 1e3 * sorted(t)[len(t) // 2] for name, t in times.items() if t}
    print(f"load: {len(times['load'])} in {args.timed} steps; ms each (median): "
          + ", ".join(f"{name} {ms:.2f}" for name, ms in medians.items()), flush=True)
    r = torch.randn_like(sim.x)
    for _ in range(3):
        correction(r)
    common.sync(device)
    began = time.perf_counter()
    for _ in range(50):
        correction(r)
    common.sync(device)
    print(f"one application, eager: {1e6 * (time.perf_counter() - began) / 50:.0f} us", flush=True)
    if device.startswith("cuda"):
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            for _ in range(10):
                correction(r)
        common.sync(device)
        began = time.perf_counter()
        for _ in range(10):
            graph.replay()
        common.sync(device)
        print(f"one application, captured: {1e6 * (time.perf_counter() - began) / 100:.0f} us", flush=True)
    return medians


if __name__ == "__main__":
    main()
