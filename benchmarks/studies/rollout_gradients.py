"""Gradients through rollouts: the adjoint's time against the forward's, and memory against steps.

    python benchmarks/studies/rollout_gradients.py [--device cuda] [--scenes sofa_beam,paper_beam]
        [--models hooke,corotational] [--steps 50] [--memory-steps 25,50,100,200,1000] [--checkpoint 10]
        [--identify hooke,corotational] [--out benchmarks/results/gradients] [--quick]

For each scene and model (float32, the scene's own settings): the simulator's own steps/s
(``sim.step``, chained and captured where it can be), then a rollout of ``--steps`` steps whose
loss depends on the last state, with the per-element Young's moduli and the initial positions
requiring grad (the moduli given, the rollout builds the simulator again with them: that set-up
is in its forward's time), then with the initial positions only: the forward's and the
backward's wall time per step, in the two modes of
``tm.rollout``: ``exact`` (both solves converged to the scene's tolerance: the SOFA beam's
10-iteration budget lifted) and ``budget`` (``exact=False``: the solves as the scene runs them).
Memory: the peak allocated during forward and backward of rollouts of ``--memory-steps`` steps
from initial positions that require grad (budget mode), keeping every state or every
``--checkpoint``-th (CUDA only). Identification (``--identify``): ``examples/identify_moduli.py
--per-element`` at the SOFA beam's resolution (75 x 15 x 15 cells, 101,250 tets and as many
unknown moduli, float64, 20 steps, 30 L-BFGS iterations): wall time, misfit, the moduli's relative
error. ``--scenes stack``: ``scenes/stack.toml``, three blocks dropped onto each other and a floor
(contact between bodies; the model overrides the file's hooke), timed once its blocks have landed
(after the ``sim.step`` rows' steps).
"""
from __future__ import annotations

import argparse
import importlib.util
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import torch

import tensormass_torch as tm
from tensormass_torch.sim import builtin

ROOT = Path(__file__).resolve().parents[2]
COLUMNS = [("scene", "scene", None), ("model", "model", None), ("elements", "elements", None),
           ("mode", "mode", None), ("leaves", "gradients of", None), ("steps", "steps", None),
           ("sim_steps_per_s", "sim.step steps/s", ".1f"),
           ("forward_ms", "rollout forward ms/step", ".2f"), ("backward_ms", "backward ms/step", ".2f"),
           ("ratio", "backward / rollout forward", ".2f"), ("step_ratio", "backward / sim.step", ".1f"),
           ("checkpoint", "checkpoint every", None),
           ("peak_mib", "peak MiB", ".0f"), ("state_mib", "one state (x, v) MiB", ".2f"),
           ("rollouts", "identification: rollouts + gradients", None), ("wall_s", "wall s", ".1f"),
           ("misfit", "misfit first -> last", None),
           ("moduli_error", "moduli's relative error: median / 90 % / max", None)]


def make_scene(name: str, model: str, device, scale: int):
    if name == "stack":  # contact between bodies: its steps and their backward eager
        return tm.load_scene(ROOT / "scenes" / "stack.toml", device=device, model=model).simulator
    if name == "sofa_beam":
        return builtin.sofa_beam(model=model, device=device, scale=scale).simulator
    return builtin.paper_beam(resolution=max(4 // scale, 1), model=model, device=device).simulator


def timed_rollout(sim, steps: int, exact: bool, device, moduli: bool = True):
    """(forward s, backward s) of a rollout whose loss is the last state's, with x0 and (``moduli``)
    the per-element Young's moduli as leaves."""
    leaves = {"x0": sim.x.clone().requires_grad_(True)}
    if moduli:
        leaves["young"] = torch.full((sim.element_ptr[-1],), float(sim.bodies[0].material.young), dtype=sim.dtype,
                                     device=sim.device, requires_grad=True)
    common.sync(device)
    start = time.perf_counter()
    run = tm.rollout(sim, steps, exact=exact, frames=[steps], **leaves)
    loss = run.x[-1].square().sum()
    common.sync(device)
    middle = time.perf_counter()
    loss.backward()
    common.sync(device)
    end = time.perf_counter()
    assert all(bool(torch.isfinite(t.grad).all()) for t in leaves.values())
    return middle - start, end - middle

def per_step_rate(results) -> float:
    """The last ``sim.step`` row's steps/s."""
    return next(r["sim_steps_per_s"] for r in reversed(results.records) if r.get("sim_steps_per_s"))


def peak_memory(sim, steps: int, every, device) -> float:
    """Peak MiB allocated over a rollout of ``steps`` from initial positions that require grad,
    and its backward, beyond what was allocated before (no material given: the simulator is not
    built again, so this is the rollout's own memory)."""
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    x0 = sim.x.clone().requires_grad_(True)
    run = tm.rollout(sim, steps, x0=x0, checkpoint_every=every, frames=[steps], exact=False)
    run.x[-1].square().sum().backward()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2 ** 20

def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--scenes", default="sofa_beam,paper_beam")
    parser.add_argument("--models", default="hooke,corotational")
    parser.add_argument("--steps", type=int, default=None)
    parser.add_argument("--memory-steps", default=None)
    parser.add_argument("--checkpoint", type=int, default=10)
    parser.add_argument("--scale", type=int, default=None, help="divide the scenes' resolution")
    parser.add_argument("--modes", default="budget,exact")
    parser.add_argument("--identify", default=None, help="models of the identification run ('' for none)")
    parser.add_argument("--out", default="benchmarks/results/gradients")
    parser.add_argument("--quick", action="store_true", help="tiny sizes (a smoke run)")
    args = parser.parse_args(argv)
    common.fill_defaults(args, normal=dict(steps=50, memory_steps="25,50,100,200,1000", scale=1,
                                           identify="hooke,corotational"),
                         quick=dict(steps=3, memory_steps="4,8", scale=8, identify="hooke"))
    device = torch.device(args.device)
    meta = common.metadata(device, steps=args.steps, checkpoint=args.checkpoint, scale=args.scale)
    results = common.Results(args.out, "rollout_gradients",
                             "Gradients through rollouts: backward against forward, memory against steps", meta,
                             COLUMNS, notes=[__doc__.split("\n\n", 2)[2].strip()])
    for scene in args.scenes.split(","):
        for model in args.models.split(","):
            sim = make_scene(scene, model, device, args.scale)
            base = dict(scene=scene, model=model, elements=sim.element_ptr[-1])
            sim.step(5)  # warm: captured graphs, the simulator's state off rest
            per_step, done = common.time_steps(sim.step, device, steps=max(args.steps, 20), max_seconds=20.0)
            results.add(common.record(**base, mode="sim.step", steps=done, sim_steps_per_s=1.0 / per_step))
            for mode in args.modes.split(","):
                for moduli in (True, False):
                    timed_rollout(sim, 2, mode == "exact", device, moduli)  # warm: the adjoint's graphs
                    forward, backward = timed_rollout(sim, args.steps, mode == "exact", device, moduli)
                    results.add(common.record(**base, mode=mode, leaves="young, x0" if moduli else "x0",
                                              steps=args.steps, forward_ms=1e3 * forward / args.steps,
                                              backward_ms=1e3 * backward / args.steps, ratio=backward / forward,
                                              step_ratio=backward * per_step_rate(results) / args.steps))
            if common.is_cuda(device):
                state = 2 * sim.x.numel() * sim.x.element_size() / 2 ** 20
                for steps in common.parse_ints(args.memory_steps):
                    for every in (None, args.checkpoint):
                        results.add(common.record(**base, mode="budget", steps=steps, checkpoint=every or "-",
                                                  peak_mib=peak_memory(sim, steps, every, device), state_mib=state))
            del sim
            common.release(device)
    for model in filter(None, args.identify.split(",")):
        results.add(identification(model, args.scale, device))
    results.finish()
    return results.records


def identification(model: str, scale: int, device) -> dict:
    """examples/identify_moduli.py with one unknown modulus per element, at the SOFA beam's size."""
    spec = importlib.util.spec_from_file_location("identify_moduli", ROOT / "examples" / "identify_moduli.py")
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    cells = [str(max(75 // scale, 2)), str(max(15 // scale, 1)), str(max(15 // scale, 1))]
    out = example.main(["--cells", *cells, "--per-element", "--steps", "20", "--iterations", "30", "--model", model,
                        "--device", str(device), "--dtype", "float64"])
    nx, ny, nz = map(int, cells)
    q = out["relative_error_quantiles"]
    return common.record(scene="identify_moduli", model=model, elements=6 * nx * ny * nz, mode="per element",
                         rollouts=out["evaluations"], wall_s=out["wall_s"],
                         misfit=f"{out['first_misfit']:.2e} -> {out['misfit']:.2e}",
                         moduli_error=f"{q[0]:.3f} / {q[1]:.3f} / {q[2]:.3f}")

if __name__ == "__main__":
    main()
