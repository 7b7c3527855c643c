"""Where a cut's time goes, and how long cuts take with repeats: the SOFA beam on one device.

    python benchmarks/probes/cut_probe.py [--device cuda] [--models hooke,corotational] [--profile FILE]

Per model, medians over repeats (each on a fresh simulator with spare rows, its graphs captured):
a scalpel crossing the middle over 100 steps (steps/s; the first cut, untimed, gives the body its
spare rows), the same simulator's uncut steps (one ``sim.step()`` each), a cut through half of the
height at three places (ms, each a fresh section), a removal of 1,000 elements (ms, three in a
row). ``--profile FILE`` adds a torch.profiler table of 10 scalpel steps, grouped by the Python
frames that issued each op (which part of the cut launches what). Uses only the public API, so
that one script times two trees (``PYTHONPATH`` picks the package).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

import tensormass_torch as tm
from tensormass_torch.sim import builtin


def sync(device):
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def fresh(model, device):
    scene = builtin.sofa_beam(model=model, device=device)
    sim = tm.Simulator(scene.simulator.bodies, **scene.simulator._init_args, spare_nodes=4096)
    sim.step(3)
    sync(device)
    return sim


def section(sim, x, depth):
    """A blade down through ``depth`` of the beam's height where it is now (it sags), at ``x``."""
    v = sim.positions(0)
    near = v[(v[:, 0] - x).abs() < 1.0]
    bottom, top = float(near[:, 1].min()), float(near[:, 1].max())
    z0, z1 = float(v[:, 2].min()) - 1.0, float(v[:, 2].max()) + 1.0
    low = top - depth * (top - bottom)
    return tm.Blade.swept((x, top + 1, z0), (x, top + 1, z1), (x, low, z0), (x, low, z1))


def median_ms(sim, device, make_change, count: int) -> float:
    """Median ms of ``count`` changes, each timed alone between steps: ``make_change(k)`` (untimed:
    a blade placed where the body is now) returns the k-th change to time."""
    times = []
    for k in range(count):
        change = make_change(k)
        sync(device)
        t = time.perf_counter()
        change()
        sync(device)
        times.append(1e3 * (time.perf_counter() - t))
        sim.step()
    return statistics.median(times)


def measure(model, device, steps=100):
    sim = fresh(model, device)
    v = sim.bodies[0].mesh.vertices
    lo, hi = float(v[:, 0].min()), float(v[:, 0].max())
    layers = torch.unique(v[:, 0])
    cell = float(layers[1] - layers[0])
    middle = 0.5 * (lo + hi)
    out = {}
    # uncut steps, one sim.step() each
    sync(device)
    t = time.perf_counter()
    for _ in range(steps):
        sim.step()
    sync(device)
    out["uncut_steps_per_s"] = steps / (time.perf_counter() - t)
    # cuts through half the height at three sections (the first cut in place at another one, untimed)
    sim.cut(0, section(sim, lo + 0.8 * (hi - lo) + 0.1 * cell, 0.3))
    sim.step()

    def cut_at(k, fracs=(0.3, 0.5, 0.7)):
        blade = section(sim, lo + fracs[k] * (hi - lo) + 0.1 * cell, 0.5)
        return lambda: sim.cut(0, blade)

    out["half_cut_ms"] = median_ms(sim, device, cut_at, 3)
    # removals of 1,000 elements between steps
    mesh = sim.bodies[0].mesh
    order = torch.argsort((mesh.vertices[mesh.elements].mean(1)[:, 0] - (lo + 0.15 * (hi - lo))).abs())
    sim.remove_elements(0, order[:1])
    out["remove_1000_ms"] = median_ms(
        sim, device, lambda k: (lambda: sim.remove_elements(0, order[1 + 1000 * k:1 + 1000 * (k + 1)])), 3)
    # a scalpel across the middle over `steps` steps
    sim = fresh(model, device)
    t0 = sim.time
    sim.add_scalpel(tm.Scalpel(0, times=[t0, t0 + steps * sim.options.dt],
                               edges=[[[middle, 5.0, -3.0], [middle, 5.0, 3.0]], [[middle, 11.0, -3.0], [middle, 11.0, 3.0]]]))
    sim.step()  # the first cut: spare rows made
    sync(device)
    t = time.perf_counter()
    sim.step(steps - 1)
    sync(device)
    out["scalpel_steps_per_s"] = (steps - 1) / (time.perf_counter() - t)
    return out, sim


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--models", default="hooke,corotational")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--profile", default=None)
    args = p.parse_args()
    for model in args.models.split(","):
        runs = [measure(model, args.device)[0] for _ in range(args.repeats)]
        summary = {k: statistics.median(r[k] for r in runs) for k in runs[0]}
        print(model, " ".join(f"{k} {v:.3f}" for k, v in summary.items()),
              "| runs:", [" ".join(f"{r[k]:.2f}" for k in r) for r in runs], flush=True)
    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        sim = fresh(args.models.split(",")[0], args.device)
        t0 = sim.time
        v = sim.bodies[0].mesh.vertices
        middle = 0.5 * float(v[:, 0].min() + v[:, 0].max())
        sim.add_scalpel(tm.Scalpel(0, times=[t0, t0 + 100 * sim.options.dt],
                                   edges=[[[middle, 5.0, -3.0], [middle, 5.0, 3.0]],
                                          [[middle, 11.0, -3.0], [middle, 11.0, 3.0]]]))
        sim.step(20)
        activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if args.device.startswith("cuda") else [])
        with profile(activities=activities, with_stack=True, record_shapes=True) as prof:
            sim.step(10)
            sync(args.device)
        with open(args.profile, "w") as f:
            f.write(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=40) + "\n")
            f.write(prof.key_averages(group_by_stack_n=4).table(sort_by="self_cpu_time_total", row_limit=60,
                                                                max_name_column_width=40) + "\n")


if __name__ == "__main__":
    main()
