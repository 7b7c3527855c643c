"""Steps per second of whole implicit Euler steps on the benchmark scenes (benchmarks/README.md).

    python benchmarks/suite/step_bench.py --device cuda --out $OUT      # all scenes, both backends
    ... --integrators backward_euler,newmark                          # each scene with each integrator

Scenes: SOFA's GPU benchmark beam (101,250 tets, 10 CG iterations, contact plane) and the
paper's 307,200-tet beam (25 CG iterations), each with the extension and the pure-torch path
in the same process. CG runs a fixed budget (require_convergence=False, tol=0) so that every
variant does the same work. Timing, records and writers: ``common`` / ``measure`` (each
record also has the floor of one CG iteration and the ratio of ms per step / CG iterations to
it). Writes step_bench.md / step_bench.json under --out.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch
from common import Budget, Results, copy_bandwidth, metadata, record, release
from measure import run_simulator

from tensormass_torch.sim.builtin import sofa_beam

PAPER_BEAM_ELEMENTS = 307_200

COLUMNS = [("scene", "scene", None), ("model", "model", None), ("elements", "elements", None),
           ("backend", "backend", None), ("integrator", "integrator", None), ("cg_iterations", "CG it", None),
           ("ms_per_step", "ms/step", ".2f"),
           ("steps_per_s", "steps/s", ".1f"), ("ms_per_cg_iteration", "ms/CG it", ".3f"),
           ("floor_ratio", "x floor", ".1f")]


def paper_beam(model, device, dtype):
    return common.cantilever_sim("tet", model, PAPER_BEAM_ELEMENTS, device, dtype, cg_iterations=25)[0]


def sofa(model, device, dtype):
    sim = sofa_beam(model=model, device=device, dtype=dtype).simulator
    sim.options.cg_tol = 0.0  # SOFA runs its 10 iterations; no early exit, no host check
    sim.options.check_every = 1000
    return sim


SCENES = {"sofa_beam": (sofa, ("hooke", "corotational")), "paper_beam": (paper_beam, ("hooke", "stvk"))}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--out", default="benchmarks/results")
    parser.add_argument("--backends", default="extension,torch")
    parser.add_argument("--scenes", default="sofa_beam,paper_beam")
    parser.add_argument("--integrators", default="backward_euler", help="StepOptions.integrator values, each timed")
    parser.add_argument("--max-seconds", type=float, default=10.0, help="time limit of one measurement's steps")
    parser.add_argument("--budget-s", type=float, default=None, help="wall-clock limit: later measurements are skipped")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    bandwidth = copy_bandwidth(device)
    meta = metadata(device, dtype="float32", copy_bandwidth_GBps={"device": bandwidth / 1e9}, argv=vars(args))
    results = Results(args.out, "step_bench", "Implicit Euler steps", meta, COLUMNS)
    budget = Budget(args.budget_s)
    for scene in args.scenes.split(","):
        make, models = SCENES[scene]
        for model in models:
            for backend, integrator in ((b, i) for b in args.backends.split(",") for i in args.integrators.split(",")):
                rec = record(scene=scene, model=model, kind="tet", objects=1, backend=backend, integrator=integrator,
                             device=device.type, dtype="float32")
                if budget.remaining() <= 0:
                    rec["skipped"] = "budget spent"
                    results.add(rec)
                    continue

                def built(model=model, integrator=integrator):
                    sim = make(model, device, torch.float32)
                    sim.options = dataclasses.replace(sim.options, integrator=integrator)
                    return sim

                out = run_simulator(built, backend, device, args.steps, args.max_seconds)
                sim = out.pop("_sim", None)
                out.pop("_wall_s", None)
                rec.update(out)
                if sim is not None:
                    common.add_floor(rec, common.sim_cg_bytes(sim)["total"], bandwidth)
                del sim
                release(device)
                results.add(rec)
    results.finish()
    return results


if __name__ == "__main__":
    main()
