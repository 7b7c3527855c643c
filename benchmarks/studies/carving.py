"""Carving cost: removing elements in place against rebuilding, and steps while carving.

    python benchmarks/studies/carving.py [--device cuda] [--scenes sofa,paper] [--models hooke,corotational]
                                         [--counts 10,100,1000,10000] [--scale 1] [--steps 50]
                                         [--cut-depths 0.25,0.5,1] [--out benchmarks/results/carving] [--quick]

On SOFA's beam (101,250 tets; ``--scale`` divides its resolution) and the paper's beam (307,200
tets, resolution 4 / scale), for R removed elements (the R elements nearest the beam's middle
cross-section: a local cut): the time of ``TensorMass.remove_elements`` (median of 3, each on a
fresh copy of the model that has made what removals need: that set-up, paid once by the first
removal, is measured on its own) and of ``Simulator.remove_elements`` between steps (median of 3
successive removals of R elements, after one untimed, from a simulator whose step graphs are
captured: model, masses, gravity and constraints updated in place), against, in the same run, building a ``TensorMass``
of the remaining elements and building a ``Simulator`` of them up to its first step done (what a
user would do without removals: node graph, captured graphs; median of 3 after one). Synchronised
wall clock. Then the
SOFA beam's steps/s without removals, with 10 elements removed before every step (one
``sim.step()`` call per step in both), and with a scalpel crossing its middle over the steps, cut
on the host and on the device (``Simulator(cut_on_device=True)``).
Cuts: one ``Simulator.cut`` across the middle section, from the top down through each of
``--cut-depths`` of the height (in place, in spare rows, after a small untimed cut; the elements
it re-points counted) against a simulator of the cut mesh up to its first step (median of 3 after one).
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

COLUMNS = [("scene", "scene", None), ("model", "model", None), ("form", "form", None),
           ("elements", "elements", None), ("prepare_ms", "first removal's set-up ms", ".2f"),
           ("removed", "removed", None), ("remove_ms", "model: remove ms", ".3f"),
           ("rebuild_ms", "model: rebuild ms", ".2f"), ("speedup", "rebuild / remove", ".1f"),
           ("sim_remove_ms", "simulator: remove ms", ".3f"),
           ("cut_elements", "cut: elements re-pointed", None), ("cut_nodes", "cut: nodes added", None),
           ("cut_ms", "simulator: cut ms", ".3f"),
           ("sim_rebuild_ms", "simulator: rebuild to a step ms", ".1f"),
           ("sim_speedup", "rebuild / change", ".0f"), ("steps_per_s", "steps/s", ".1f"),
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


def scene_of(name, model_name, device, scale):
    if name == "sofa":
        return builtin.sofa_beam(model=model_name, device=device, scale=scale)
    return builtin.paper_beam(resolution=max(4 // scale, 1), model=model_name, device=device)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--scenes", default="sofa,paper")
    p.add_argument("--models", default="hooke,corotational")
    p.add_argument("--counts", default="10,100,1000,10000")
    p.add_argument("--cut-depths", default="0.25,0.5,1", help="cuts down from the top through these fractions "
                   "of the beam's height")
    p.add_argument("--scale", type=int, default=1)
    p.add_argument("--steps", type=int, default=50)
    p.add_argument("--out", default="benchmarks/results/carving")
    p.add_argument("--quick", action="store_true", help="the beams at 1/5 resolution, 10 and 100 removed, 5 steps")
    args = p.parse_args(argv)
    if args.quick:
        args.scale, args.counts, args.steps, args.cut_depths = 5, "10,100", 5, "0.5"
    device = args.device
    results = common.Results(args.out, "carving", "Carving: in-place removal against a rebuild",
                             common.metadata(device, scale=args.scale),
                             COLUMNS, notes=["Removal of the R elements nearest the beam's middle section; model: "
                                             "`TensorMass.remove_elements` (median of 3 on fresh copies) against a "
                                             "`TensorMass` of the remaining elements; simulator: "
                                             "`Simulator.remove_elements` between steps (median of 3 successive "
                                             "removals after one) against a `Simulator` of the remaining elements "
                                             "up to its first step (median of 3 after one); steps/s: the SOFA "
                                             "beam, one `sim.step()` per step, with 10 elements removed before "
                                             "each step against none, and a scalpel across the middle over the "
                                             "steps."])
    for scene_name in args.scenes.split(","):
        for model_name in args.models.split(","):
            measure_scene(results, scene_name, model_name, device, args)
    results.finish()


def measure_scene(results, scene_name, model_name, device, args):
    scene = scene_of(scene_name, model_name, device, args.scale)
    sim = scene.simulator
    body = sim.bodies[0]
    mesh, material = body.mesh, body.material
    model = sim.model
    form = model.groups[0].form
    centroids = mesh.vertices[mesh.elements].mean(1)
    middle = 0.5 * float(mesh.vertices[:, 0].min() + mesh.vertices[:, 0].max())
    order = torch.argsort((centroids[:, 0] - middle).abs())
    n = mesh.elements.shape[0]
    same = dict(scene=scene.name, model=model_name, kind=mesh.kind, elements=n, form=form, device=str(device))
    prepare_s = timed(lambda m: m._prepare_removals(), device, setup=lambda: copy.deepcopy(model))
    results.add(common.record(**same, prepare_ms=1e3 * prepare_s))
    init = dict(sim._init_args)
    for count in common.parse_ints(args.counts):
        if 5 * count >= n:
            continue
        ids = order[:count]
        keep = torch.ones(n, dtype=torch.bool, device=mesh.elements.device)
        keep[ids] = False
        remove_s = timed(lambda m: m.remove_elements(ids), device, setup=lambda: prepared(model))
        rebuild_s = timed(lambda _: tm.TensorMass.packed(model.rest, [(mesh.elements[keep], material, mesh.kind)],
                                                         form=form), device)
        # the simulator: three successive removals of `count` elements between steps
        carved = scene_of(scene_name, model_name, device, args.scale).simulator
        carved.step(3)  # graphs captured
        carved.remove_elements(0, order[-1:])  # the first removal's set-up, not timed
        chunks = iter(order[k * count:(k + 1) * count] for k in range(4))
        sim_remove_s = timed(lambda _: carved.remove_elements(0, next(chunks)), device)
        kept = tm.TetMesh(mesh.vertices, mesh.elements[keep], check=False)
        holds = body.fixed.clone()
        holds[kept.unused_vertices()] = True  # vertices left with no element: held (tm.Body asks it)

        def rebuilt(_):
            fresh = tm.Simulator([tm.Body(kept, material, fixed=holds, name=body.name)], **init)
            fresh.step()

        sim_rebuild_s = timed(rebuilt, device, repeat=3)
        results.add(common.record(**same, removed=count, remove_ms=1e3 * remove_s, rebuild_ms=1e3 * rebuild_s,
                                  speedup=rebuild_s / remove_s, sim_remove_ms=1e3 * sim_remove_s,
                                  sim_rebuild_ms=1e3 * sim_rebuild_s, sim_speedup=sim_rebuild_s / sim_remove_s))
    for on_device in (False, True):
        for depth in (float(d) for d in args.cut_depths.split(",") if d):
            measure_cut(results, same, scene_name, model_name, device, args, middle, depth, on_device)
    if scene_name != "sofa":
        return
    for per_step in (0, 10):
        sim = scene_of(scene_name, model_name, device, args.scale).simulator
        sim.step(3)  # warm-up: graphs captured
        if per_step:
            sim.remove_elements(0, order[-1:])  # the first removal's set-up
        cursor = [0]

        def step(k, sim=sim, per_step=per_step):
            for _ in range(k):
                if per_step:
                    sim.remove_elements(0, order[cursor[0]:cursor[0] + per_step])
                    cursor[0] += per_step
                sim.step()

        seconds = timed(lambda _: step(args.steps), device, repeat=1, warmup=0)
        results.add(common.record(**same, steps=args.steps, steps_per_s=args.steps / seconds,
                                  removed_per_step=per_step))
    # a scalpel crossing the beam at its middle over the timed steps (edge along z, moving along y),
    # cut on the host and on the device (Simulator(cut_on_device=True), where it serves the scene)
    for on_device in (False, True):
        built = scene_of(scene_name, model_name, device, args.scale).simulator
        sim = tm.Simulator(built.bodies, **dict(built._init_args, cut_on_device=on_device))
        sim.step(3)
        # the edge goes up through the beam (y from 6 to 10) over the untimed steps and the timed ones
        untimed_limit = 20
        t0, t1 = sim.time, sim.time + (args.steps + untimed_limit + 2) * sim.options.dt
        sim.add_scalpel(tm.Scalpel(0, times=[t0, t1], edges=[[[middle, 6.1, -3.0], [middle, 6.1, 3.0]],
                                                             [[middle, 11.0, -3.0], [middle, 11.0, 3.0]]]))
        nodes = sim.bodies[0].mesh.num_vertices
        # untimed: the steps up to the first split node (its cut finds no spare rows and builds the
        # simulator again with room) and one more (the cut on the device makes its tables and
        # captures its graph), so that the timed steps are the steady state
        common.sync(device)
        untimed_start, untimed = time.perf_counter(), 1
        while sim.used_nodes[0] == nodes and untimed < untimed_limit:
            sim.step()
            untimed += 1
        sim.step()
        common.sync(device)
        untimed_s = time.perf_counter() - untimed_start
        seconds = timed(lambda _: sim.step(args.steps), device, repeat=1, warmup=0)
        added = sim.bodies[0].mesh.num_vertices - nodes
        where = "on the device" if sim._device_cuts is not None else "on the host, in place"
        results.add(common.record(**same, steps=args.steps, steps_per_s=args.steps / seconds, removed_per_step=0,
                                  note=f"a scalpel across the middle: {added} nodes added, cuts {where} (untimed "
                                       f"before these steps: {untimed} steps, up to the first split and one more, "
                                       f"{1e3 * untimed_s:.0f} ms)"))


def measure_cut(results, same, scene_name, model_name, device, args, middle, depth, on_device=False):
    """A cut across the beam's middle section from the top down through ``depth`` of its height
    (``Simulator.cut`` in place, in spare rows, between steps whose graphs are captured; a
    small cut near the free end before it, untimed, makes what cuts in place keep) against a
    simulator of the cut mesh up to its first step. ``on_device``: the cut a scalpel makes on the
    device instead (``DeviceCuts.cut``, synchronised; where it serves the scene, else not measured)."""
    scene = scene_of(scene_name, model_name, device, args.scale)
    init, bodies = dict(scene.simulator._init_args, cut_on_device=on_device), scene.simulator.bodies
    sim = tm.Simulator(bodies, **init, spare_nodes=4096)
    cuts = sim._device_cutter(0) if on_device else None
    if on_device and cuts is None:
        return

    def cut(blade):
        if cuts is None:
            sim.cut(0, blade)
        else:
            cuts.cut(blade.vertices)
            sim.step()  # (settles the cut: its nodes join the body)

    sim.step(3)
    vertices = bodies[0].mesh.vertices
    bottom, top = float(vertices[:, 1].min()), float(vertices[:, 1].max())
    z0, z1 = float(vertices[:, 2].min()) - 1.0, float(vertices[:, 2].max()) + 1.0
    layers = torch.unique(vertices[:, 0])
    near_end = float(layers[-2:].mean())  # between the last two layers of nodes
    shallow = top - 0.3 * (top - bottom)
    cut(tm.Blade.swept((near_end, top + 1, z0), (near_end, top + 1, z1), (near_end, shallow, z0),
                       (near_end, shallow, z1)))
    sim.step()
    before = sim.bodies[0].mesh
    lowest = top - depth * (top - bottom) - (0.01 * (top - bottom) if depth >= 1 else 0.0)
    # off the middle by a tenth of a cell: a plane through the cells' centres passes through
    # centroids, and a segment that only touches the blade is not cut
    x = middle + 0.1 * float(layers[1] - layers[0])
    blade = tm.Blade.swept((x, top + 1, z0), (x, top + 1, z1), (x, lowest, z0), (x, lowest, z1))
    if cuts is None:
        cut_s = timed(lambda _: sim.cut(0, blade), device, repeat=1, warmup=0)
    else:
        cut_s = timed(lambda _: cuts.cut(blade.vertices), device, repeat=1, warmup=0)
        sim.step()  # (settles it)
    after = sim.bodies[0].mesh
    changed = int((after.elements.to(before.elements.device) != before.elements).any(1).sum())
    added = after.num_vertices - before.num_vertices
    alive = [torch.nonzero(~sim.alive_elements(k)).flatten() for k in range(sim.num_bodies)]

    def rebuilt(_):
        fresh = tm.Simulator(sim.bodies, **init)
        for k, ids in enumerate(alive):
            if ids.numel():
                fresh.remove_elements(k, ids)
        fresh.step()

    rebuild_s = timed(rebuilt, device, repeat=3)
    results.add(common.record(**same, cut_elements=changed, cut_nodes=added, cut_ms=1e3 * cut_s,
                              sim_rebuild_ms=1e3 * rebuild_s, sim_speedup=rebuild_s / cut_s,
                              note=f"a cut down through {depth:g} of the height at the middle, "
                                   + ("on the device" if on_device else "in place")))


if __name__ == "__main__":
    main()
