"""Carving cost: removing elements in place against rebuilding the model, and steps while carving.

    python benchmarks/studies/carving.py [--device cuda] [--models hooke,corotational] [--counts 10,100,1000,10000]
                                         [--scale 1] [--steps 50] [--out benchmarks/results/carving] [--quick]

On SOFA's beam (101,250 tets; ``--scale`` divides its resolution): for R removed elements (the R
elements nearest the beam's mid-plane x = 9.5: a local cut), the time of ``TensorMass.remove_elements``
(median of 3, each on a fresh copy of the model that has made what removals need: that set-up,
paid once by the first removal, is measured on its own; synchronised wall clock) against the time to build
a ``TensorMass`` of the remaining elements, in the same run. Then the simulator's steps/s without
removals and with 10 elements removed before every step (the integrator's caches and captured
graphs are built again after each removal: the cost that fixed capacities are to remove, docs/topology-changes.md).
"""
from __future__ import annotations

import argparse
import copy
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import torch

import tensormass_torch as tm
from tensormass_torch.sim import builtin

COLUMNS = [("model", "model", None), ("form", "form", None), ("elements", "elements", None),
           ("prepare_ms", "first removal's set-up ms", ".2f"), ("removed", "removed", None),
           ("remove_ms", "remove ms", ".3f"), ("rebuild_ms", "rebuild ms", ".2f"),
           ("speedup", "rebuild / remove", ".1f"), ("steps_per_s", "steps/s", ".1f"),
           ("removed_per_step", "removed per step", None)]


def timed(fn, device, repeat=3, setup=None, warmup=1):
    """Median seconds of ``fn(setup())`` over ``repeat`` synchronised calls after ``warmup``."""
    times = []
    for k in range(warmup + repeat):
        state = setup() if setup is not None else None
        common.sync(device)
        start = time.perf_counter()
        fn(state)
        common.sync(device)
        if k >= warmup:
            times.append(time.perf_counter() - start)
    return statistics.median(times)


def prepared(model):
    """A copy of ``model`` that has made what removals need (its first removal's extra cost,
    measured on its own as ``prepare_ms``)."""
    model = copy.deepcopy(model)
    model._prepare_removals()
    return model


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--models", default="hooke,corotational")
    p.add_argument("--counts", default="10,100,1000,10000")
    p.add_argument("--scale", type=int, default=1)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--out", default="benchmarks/results/carving")
    p.add_argument("--quick", action="store_true", help="the beam at 1/5 resolution, 10 and 100 removed, 5 steps")
    args = p.parse_args(argv)
    if args.quick:
        args.scale, args.counts, args.steps = 5, "10,100", 5
    device = args.device
    results = common.Results(args.out, "carving", "Carving: in-place removal against a rebuild",
                             common.metadata(device, scale=args.scale), COLUMNS,
                             notes=["Removal: `TensorMass.remove_elements` of the R elements nearest x = 9.5, "
                                    "median of 3 on fresh copies; rebuild: `TensorMass` of the remaining "
                                    "elements; steps/s: `Simulator.step` with 10 elements removed before each "
                                    "step, against none."])
    for model_name in args.models.split(","):
        scene = builtin.sofa_beam(model=model_name, device=device, scale=args.scale)
        sim = scene.simulator
        body = sim.bodies[0]
        mesh, material = body.mesh, body.material
        model = sim.model
        form = model.groups[0].form
        centroids = mesh.vertices[mesh.elements].mean(1)
        order = torch.argsort((centroids[:, 0] - 9.5).abs())
        n = mesh.elements.shape[0]
        prepare_s = timed(lambda m: m._prepare_removals(), device, setup=lambda: copy.deepcopy(model))
        results.add(common.record(scene="sofa_beam", model=model_name, kind=mesh.kind, elements=n, form=form,
                                  device=str(device), prepare_ms=1e3 * prepare_s))
        for count in common.parse_ints(args.counts):
            if count >= n:
                continue
            ids = order[:count]
            keep = torch.ones(n, dtype=torch.bool, device=mesh.elements.device)
            keep[ids] = False
            remove_s = timed(lambda m: m.remove_elements(ids), device, setup=lambda: prepared(model))
            rebuild_s = timed(lambda _: tm.TensorMass.packed(model.rest, [(mesh.elements[keep], material, mesh.kind)],
                                                             form=form), device)
            results.add(common.record(scene="sofa_beam", model=model_name, kind=mesh.kind, elements=n, form=form,
                                      device=str(device), removed=count, remove_ms=1e3 * remove_s,
                                      rebuild_ms=1e3 * rebuild_s, speedup=rebuild_s / remove_s))
        for per_step in (0, 10):
            sim = builtin.sofa_beam(model=model_name, device=device, scale=args.scale).simulator
            sim.step(3)  # warm-up: graphs captured
            cursor = [0]

            def step(k, sim=sim, per_step=per_step):
                for _ in range(k):
                    if per_step:
                        sim.remove_elements(0, order[cursor[0]:cursor[0] + per_step])
                        cursor[0] += per_step
                    sim.step()

            seconds = timed(lambda _: step(args.steps), device, repeat=1, warmup=0)
            results.add(common.record(scene="sofa_beam", model=model_name, kind=mesh.kind, elements=n, form=form,
                                      device=str(device), steps=args.steps, steps_per_s=args.steps / seconds,
                                      removed_per_step=per_step))
    results.finish()


if __name__ == "__main__":
    main()
