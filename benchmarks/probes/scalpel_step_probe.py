"""Where a scalpel step's time goes: the SOFA beam stepped one ``sim.step()`` at a time, uncut and
while a scalpel crosses its middle (cut on the host and on the device), with the host's time split
into the scalpel's cut, the step and the settling of the cut (and the median and slowest step, and
the rebuilds with room a cut that did not fit made), the GPU time of the device cut's
replayed graph, and (``--profile``) the host functions that take the most time.

    python benchmarks/probes/scalpel_step_probe.py [--steps 60] [--warm 40] [--span 200] [--trials 3] [--profile] [--kernels]

The scalpel's edge (along z) goes up from y = 6.1 (inside the beam) to y = 11 over ``--span``
steps at the beam's middle; ``--warm`` steps are untimed (the rebuild with spare rows, the device
cut's tables and capture), then ``--steps`` are timed, synchronised at the end. The host cut runs
once; then ``--trials`` times an uncut simulator and one cutting on the device, alternately (the
host's speed drifts between runs: each ratio is of neighbouring runs).
"""
import argparse
import cProfile
import io
import pstats
import statistics
import time

import torch

import tensormass_torch as tm
from tensormass_torch.sim import builtin


def beam(on_device: bool):
    built = builtin.sofa_beam(model="hooke", device="cuda").simulator
    return tm.Simulator(built.bodies, **dict(built._init_args, cut_on_device=on_device))


def timed_steps(sim, steps):
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        sim.step()
    torch.cuda.synchronize()
    return time.perf_counter() - start


def add_scalpel(sim, span):
    vertices = sim.bodies[0].mesh.vertices
    middle = float(vertices[:, 0].min() + vertices[:, 0].max()) / 2
    t0, t1 = sim.time, sim.time + span * sim.options.dt
    sim.add_scalpel(tm.Scalpel(0, times=[t0, t1], edges=[[[middle, 6.1, -3.0], [middle, 6.1, 3.0]],
                                                         [[middle, 11.0, -3.0], [middle, 11.0, 3.0]]]))


def split_host_time(sim, steps):
    """Host seconds a step in the scalpel's cut, the step itself and the settling (wrapped methods)."""
    spent = {"cut": 0.0, "advance": 0.0, "settle": 0.0}
    calls = {key: [] for key in spent}  # each call's seconds
    originals = {}

    def wrap(name, key):
        original = getattr(sim, name)
        originals[name] = original

        def timed_call(*args, **kwargs):
            start = time.perf_counter()
            try:
                return original(*args, **kwargs)
            finally:
                spent[key] += time.perf_counter() - start
                calls[key].append(time.perf_counter() - start)
        setattr(sim, name, timed_call)

    wrap("_apply_scalpels", "cut")
    wrap("_advance", "advance")
    wrap("_settle_device_cuts", "settle")
    rebuilds = [0]
    rebuild = sim._rebuild_from_device

    def counted(*args, **kwargs):
        rebuilds[0] += 1
        return rebuild(*args, **kwargs)
    sim._rebuild_from_device = counted
    each, used = [], []
    cuts = sim._device_cuts
    replays = ReplayTimes(cuts) if cuts is not None and cuts.captured is not None else None
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        sim.step()
        each.append(time.perf_counter())
        used.append(sim.used_nodes[0])
    torch.cuda.synchronize()
    total = time.perf_counter() - start
    if replays is not None:  # the cut graph's GPU time, in steps that split nodes and in the others
        gpu = replays.close()
        splitting = [b > a for a, b in zip([used[0]] + used[:-1], used)][:len(gpu)]
        for label, pick in (("splitting", True), ("not splitting", False)):
            times = [t for t, split_now in zip(gpu, splitting) if split_now == pick]
            if times:
                print(f"  the cut graph's GPU time in {len(times)} steps {label}: median "
                      f"{1e3 * statistics.median(times):.1f} us, most {1e3 * max(times):.1f} us")
    for name in list(originals) + ["_rebuild_from_device"]:
        delattr(sim, name)
    in_order = [b - a for a, b in zip([start] + each[:-1], each)]
    gaps = sorted(in_order)
    split = {key: value / steps for key, value in spent.items()}
    split.update(median=gaps[len(gaps) // 2], slowest=gaps[-1])
    slow = [f"{k}: {1e3 * t:.1f} ms (cut {1e3 * calls['cut'][k]:.1f}, step {1e3 * calls['advance'][k]:.1f})"
            for k, t in enumerate(in_order) if t > 4 * split["median"]]
    if slow:
        print("  steps over 4x the median (index in the timed steps):", ", ".join(slow))
    print(f"  pipelined CG still on: {sim.options.pipelined}; CG statuses of the last step: "
          f"{sim.last_report.cg[0].converged.tolist() if sim.last_report.cg else None} converged")
    return total, split, rebuilds[0]


class ReplayTimes:
    """CUDA events around each replay of a device cut's graph (``close()``: their milliseconds)."""

    def __init__(self, cuts):
        self.cuts, self.graph, self.events = cuts, cuts.captured, []
        cuts.captured = self

    def replay(self):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        self.graph.replay()
        end.record()
        self.events.append((start, end))

    def close(self):
        self.cuts.captured = self.graph
        torch.cuda.synchronize()
        return [a.elapsed_time(b) for a, b in self.events]


def replay_gpu_us(cuts, repeats=50):
    """GPU microseconds of one replay of the device cut's graph (a strip that crosses no new face)."""
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    torch.cuda.synchronize()
    start.record()
    for _ in range(repeats):
        cuts.captured.replay()
    end.record()
    torch.cuda.synchronize()
    return 1e3 * start.elapsed_time(end) / repeats


def scalpel_run(on_device, args, last):
    """One simulator cutting with the scalpel: its steps/s over the timed steps (printed with the
    host's split); ``last``: also the graph's GPU time, the kernels and the profile asked for."""
    sim = beam(on_device)
    sim.step(3)
    add_scalpel(sim, args.span)
    nodes = sim.used_nodes[0]
    timed_steps(sim, args.warm)
    total, split, rebuilds = split_host_time(sim, args.steps)
    where = "device" if sim.device_cuts_active else "host"
    parts = ", ".join(f"{key} {1e6 * value:.0f} us" for key, value in split.items())
    print(f"scalpel cut on the {where}: {args.steps / total:.1f} steps/s ({1e6 * total / args.steps:.0f} us a "
          f"step; host: {parts}); {sim.used_nodes[0] - nodes} nodes added over {args.warm + args.steps} steps; "
          f"{rebuilds} rebuilds with room in the timed steps")
    if last and on_device and sim.device_cuts_active:
        cuts = sim._device_cuts
        if cuts.captured is not None:
            print(f"  the device cut's graph, replayed alone: {replay_gpu_us(cuts):.1f} us of GPU time")
        if args.kernels:  # the device cut's passes, eagerly, kernel by kernel: again, then a strip further
            from torch.profiler import ProfilerActivity, profile
            dt = sim.options.dt
            scalpel = sim.scalpels[0]
            further = scalpel.strip(sim.time - dt, float(scalpel.times[-1]))
            for label, corners in (("the last strip again", None), ("the rest of the scalpel's path at once", further)):
                if corners is not None:
                    cuts.staging_array[...] = corners.numpy()
                before = cuts.limits[0].item()
                with profile(activities=[ProfilerActivity.CUDA]) as prof:
                    cuts._passes()
                    torch.cuda.synchronize()
                print(f"{label}: {cuts.limits[0].item() - before} nodes added")
                print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=10, max_name_column_width=60))
        if args.profile:
            profiler = cProfile.Profile()
            profiler.enable()
            timed_steps(sim, args.steps)
            profiler.disable()
            text = io.StringIO()
            pstats.Stats(profiler, stream=text).sort_stats("tottime").print_stats(25)
            print(text.getvalue())
    return args.steps / total


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--steps", type=int, default=60)
    parser.add_argument("--warm", type=int, default=40)
    parser.add_argument("--span", type=int, default=200)
    parser.add_argument("--trials", type=int, default=3, help="uncut and cut on the device, alternately")
    parser.add_argument("--profile", action="store_true")
    parser.add_argument("--kernels", action="store_true", help="the device cut's kernels (torch.profiler)")
    args = parser.parse_args()

    scalpel_run(False, args, last=False)  # the host cut, once
    uncut_rates, cut_rates = [], []
    for trial in range(args.trials):
        sim = beam(False)
        sim.step(3)
        uncut = timed_steps(sim, args.steps)
        uncut_rates.append(args.steps / uncut)
        print(f"uncut: {uncut_rates[-1]:.1f} steps/s, one sim.step() a step ({1e6 * uncut / args.steps:.0f} us a step)")
        cut_rates.append(scalpel_run(True, args, last=trial == args.trials - 1))
    ratios = ", ".join(f"{c / u:.2f}" for c, u in zip(cut_rates, uncut_rates))
    print(f"cut on the device against uncut, trial by trial: {ratios}; medians: "
          f"{statistics.median(cut_rates):.1f} / {statistics.median(uncut_rates):.1f} = "
          f"{statistics.median(cut_rates) / statistics.median(uncut_rates):.2f}")


if __name__ == "__main__":
    main()
