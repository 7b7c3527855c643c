"""Where a removal's and a device cut's synchronised time goes, on the SOFA beam (hooke; CUDA unless ``--device``):
each change timed to its return on the host and to the device's end (synchronised), the GPU time
of its kernels and the host time of its ops (torch.profiler), against a simulator rebuilt from
the changed mesh up to its first step (median of ``--repeats``).

    python benchmarks/probes/change_latency_probe.py [--repeats 5] [--profile] [--cprofile] [--device cuda]

The removals take the elements nearest the beam's middle, ``count`` at a time between steps (the
first removal, which makes the removal tables, untimed). The device cut is a blade down through
half of the height at three sections (``DeviceCuts.cut``; a first cut near the free end, untimed,
makes its tables and captures its graph), each followed by a step.
"""
import argparse
import statistics
import time

import torch
from cut_probe import section  # (this folder: the probes run as scripts)

import tensormass_torch as tm
from tensormass_torch.sim import builtin


def sync(device):
    if device == "cuda":
        torch.cuda.synchronize()


def beam(device, **options):
    built = builtin.sofa_beam(model="hooke", device=device).simulator
    return tm.Simulator(built.bodies, **dict(built._init_args, **options))


def timed(change, device):
    """(host ms to return, ms to the device's end) of ``change()``."""
    sync(device)
    start = time.perf_counter()
    change()
    returned = time.perf_counter()
    sync(device)
    return 1e3 * (returned - start), 1e3 * (time.perf_counter() - start)


def profiled(change, device, rows=25):
    from torch.profiler import ProfilerActivity, profile

    sync(device)
    with profile(activities=[ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])) as prof:
        change()
        sync(device)
    averages = prof.key_averages()
    kernels = sum(e.device_time_total for e in averages if e.device_type == torch.autograd.DeviceType.CUDA)
    print(f"  GPU time of its kernels: {kernels:.1f} us")
    print(averages.table(sort_by="cpu_time_total", row_limit=rows, max_name_column_width=50))


def rebuild_ms(sim, init, repeats, device):
    removed = [torch.nonzero(~sim.alive_elements(k)).flatten() for k in range(sim.num_bodies)]
    bodies = sim.bodies

    def rebuilt():
        fresh = tm.Simulator(bodies, **init)
        for k, ids in enumerate(removed):
            if ids.numel():
                fresh.remove_elements(k, ids)
        fresh.step()
    return statistics.median(timed(rebuilt, device)[1] for _ in range(repeats))


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--profile", action="store_true")
    p.add_argument("--device", default="cuda")
    p.add_argument("--cprofile", action="store_true", help="the host functions of 50 removals of 100, by own time")
    args = p.parse_args()
    device = args.device
    # removals
    sim = beam(device)
    sim.step(3)
    mesh = sim.bodies[0].mesh
    order = torch.argsort((mesh.vertices[mesh.elements].mean(1)[:, 0] - 10.0).abs())
    sim.remove_elements(0, order[-1:])
    cursor = [0]

    def removal(count):
        ids = order[cursor[0]:cursor[0] + count]
        cursor[0] += count
        return lambda: sim.remove_elements(0, ids)
    for count in (10, 100, 1000):
        runs = []
        for _ in range(args.repeats):
            runs.append(timed(removal(count), device))
            sim.step()
        print(f"remove {count}: host {statistics.median(r[0] for r in runs):.3f} ms, synchronised "
              f"{statistics.median(r[1] for r in runs):.3f} ms; runs {[round(r[1], 3) for r in runs]}", flush=True)
    if args.profile:
        print("a removal of 100:")
        profiled(removal(100), device)
        sim.step()
    if args.cprofile:
        import cProfile
        import pstats

        changes = [removal(100) for _ in range(50)]
        profiler = cProfile.Profile()
        for change in changes:
            profiler.enable()
            change()
            profiler.disable()
            sim.step()
        pstats.Stats(profiler).sort_stats("tottime").print_stats(30)
    print(f"rebuilt to a step: {rebuild_ms(sim, sim._init_args, args.repeats, device):.2f} ms", flush=True)
    # cuts on the device
    sim = beam(device, cut_on_device=True, spare_nodes=4096)
    sim.step(3)
    cuts = sim._device_cutter(0)
    v = sim.bodies[0].mesh.vertices
    lo, hi = float(v[:, 0].min()), float(v[:, 0].max())
    layers = torch.unique(v[:, 0])
    cell = float(layers[1] - layers[0])
    cuts.cut(section(sim, lo + 0.9 * (hi - lo) + 0.1 * cell, 0.3).vertices)  # tables made, graph captured
    sim.step()
    runs = []
    for frac in (0.3, 0.5, 0.7):
        blade = section(sim, lo + frac * (hi - lo) + 0.1 * cell, 0.5)
        runs.append(timed(lambda: cuts.cut(blade.vertices), device))
        sim.step()
    print(f"device cut through half the height: host {statistics.median(r[0] for r in runs):.3f} ms, synchronised "
          f"{statistics.median(r[1] for r in runs):.3f} ms; runs {[round(r[1], 3) for r in runs]}", flush=True)
    if args.profile:
        print("a device cut through half the height:")
        blade = section(sim, lo + 0.4 * (hi - lo) + 0.1 * cell, 0.5)
        profiled(lambda: cuts.cut(blade.vertices), device)
        sim.step()
    print(f"rebuilt to a step: {rebuild_ms(sim, dict(sim._init_args, cut_on_device=True), args.repeats, device):.2f} ms")


if __name__ == "__main__":
    main()
