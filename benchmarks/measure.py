"""The measurements the figure scripts share: whole implicit steps of a ``tm.Simulator`` on one
backend, the same steps through an assembled matrix, and the marginal time of one CG iteration.

Our solver is measured through the public API only (``Simulator.step``), so these numbers
follow whatever the solver does. Backends: ``"extension"`` runs with
``TENSORMASS_BACKEND=extension`` (the compiled ops required: an error, not a silent fallback,
when they are missing), ``"torch"`` with ``TENSORMASS_BACKEND=torch`` (the pure-torch path),
from the construction of the simulator to its last step.
"""
from __future__ import annotations

import time
from typing import Callable, Dict, Optional

import assembled
import torch
from common import error_text, forced_backend, is_cuda, last_cg_iterations, release, sync, time_call, time_steps

BACKEND_MODES = {"extension": "extension", "torch": "torch"}


def sim_size(sim) -> Dict[str, int]:
    return {"elements": int(sum(g.elements.shape[0] for g in sim.model.groups)),
            "nodes": int(sim.model.num_nodes), "objects": int(sim.num_bodies)}


def warm_up(sim, device, steps: int = 2) -> None:
    """Steps that pay the one-time costs (caches, allocator, graph capture) before timing. On
    the CPU one step with a single CG iteration: the same code paths at a fraction of the time."""
    if is_cuda(device):
        # one step alone, then a chain: a single step and chained steps run different CUDA graphs
        # (StepGraphs.step / run_steps), each captured the first time it runs
        sim.step(1)
        sim.step(steps)
        sync(device)
        return
    budget = sim.options.cg_max_iter
    sim.options.cg_max_iter = 1
    try:
        sim.step(1)
    finally:
        sim.options.cg_max_iter = budget


def run_simulator(make: Callable[[], object], backend: str, device, steps: int, max_seconds: float,
                  warmup: int = 2) -> Dict[str, object]:
    """Build ``make()`` and time its steps under ``backend``; a dict of record fields (with
    ``error`` when it failed) and ``_sim`` (the simulator, for byte counts) when it ran."""
    mode = BACKEND_MODES[backend]
    out: Dict[str, object] = {"backend": backend}
    start = time.perf_counter()
    try:
        with forced_backend(mode):  # no torch.no_grad(): timed as a user calls it
            sim = make()
            out.update(sim_size(sim))
            warm_up(sim, device, warmup)
            seconds, done = time_steps(sim.step, device, steps, max_seconds)
            iters = last_cg_iterations(sim)
    except Exception as exc:  # e.g. out of memory, a backend missing here: recorded, the run goes on
        out["error"] = error_text(exc)
        out["_wall_s"] = time.perf_counter() - start
        release(device)
        return out
    out.update(steps=done, steps_per_s=1.0 / seconds, ms_per_step=1e3 * seconds, cg_iterations=iters,
               ms_per_cg_iteration=1e3 * seconds / iters if iters else None)
    out["_sim"] = sim
    out["_wall_s"] = time.perf_counter() - start
    return out


def run_assembled(sim, gravity, layout: str, device, steps: int, max_seconds: float) -> Dict[str, object]:
    """Whole steps of ``sim``'s scene through ``assembled.AssembledStepper`` (layout "csr",
    "bsr" or "cupy"), plus its assembly time and the time of one CG iteration on the matrix
    (a solve of the step's budget, divided by it). Runs on the simulator's device and state."""
    out: Dict[str, object] = {"backend": layout}
    start = time.perf_counter()
    try:
        with torch.no_grad():
            stepper = assembled.AssembledStepper(sim, gravity, layout)
            stepper.step(1)  # warm-up (assembly, sparse handles, CuPy kernels)
            assembly = time_call(lambda: stepper.assemble(stepper.x), device, warmup=0, repeat=1)
            iters = stepper.iterations
            rhs = torch.randn_like(stepper.x) * stepper.free_col
            solve_s = time_call(lambda: stepper.solve(rhs), device, warmup=1, repeat=3)
            seconds, done = time_steps(stepper.step, device, steps, max_seconds)
    except Exception as exc:
        out["error"] = error_text(exc)
        out["_wall_s"] = time.perf_counter() - start
        release(device)
        return out
    out.update(steps=done, steps_per_s=1.0 / seconds, ms_per_step=1e3 * seconds, cg_iterations=iters,
               ms_per_cg_iteration=1e3 * solve_s / max(iters, 1), assembly_ms=1e3 * assembly,
               matrix_nnz=stepper.system.nnz, matrix_bytes=stepper.system.nbytes("bsr" if layout == "bsr" else "csr"),
               reassembled_per_step=stepper.reassemble)
    out["_wall_s"] = time.perf_counter() - start
    return out


def marginal_cg_ms(sim, device, low: int, high: int, steps: int, max_seconds: float) -> Optional[float]:
    """Milliseconds of one CG iteration as the difference of whole steps at two CG budgets:
    (t(high) - t(low)) / (high - low), each t the median of ``steps`` synchronised steps (the
    median resists the odd slow step). What a step does besides CG (forces, right-hand side,
    state update) cancels; the CG's own per-solve set-up cancels too."""
    saved = sim.options.cg_max_iter
    times = {}
    try:
        for budget in (low, high):
            sim.options.cg_max_iter = budget
            sim.step(1)  # warm-up at this budget (a solver may specialise on it)
            sync(device)
            ran = last_cg_iterations(sim)
            if ran is not None and ran != budget:
                raise RuntimeError(f"the step ran {ran} CG iterations with cg_max_iter={budget} and cg_tol=0: "
                                   "the marginal time per iteration cannot be taken this way")
            one = time_call(lambda: sim.step(1), device, warmup=0, repeat=1)
            repeat = max(1, min(steps, int(max_seconds / max(one, 1e-9))))
            times[budget] = time_call(lambda: sim.step(1), device, warmup=0, repeat=repeat)
    finally:
        sim.options.cg_max_iter = saved
    return 1e3 * (times[high] - times[low]) / (high - low)


class Estimator:
    """Predicts a measurement's seconds from the previous ones of the same series, so that sizes
    that would not fit the time limit are skipped: with one earlier size, linear in the size
    (right for work-bound runs, pessimistic for launch-bound ones); with two or more, the line
    through the last two (launch-bound runs grow slowly until the work dominates)."""

    def __init__(self):
        self.history: Dict[tuple, list] = {}

    def note(self, key, size: int, step_s: Optional[float], wall_s: float) -> None:
        self.history.setdefault(key, []).append((max(int(size), 1), step_s, wall_s))

    def _predict(self, key, size: int, column: int) -> float:
        points = [(p[0], p[column]) for p in self.history.get(key, []) if p[column] is not None]
        if not points:
            return 0.0
        n1, t1 = points[-1]
        if len(points) == 1 or points[-2][0] == n1:
            return t1 * size / n1
        n0, t0 = points[-2]
        slope = max((t1 - t0) / (n1 - n0), 0.0)
        return max(t1 + slope * (size - n1), t1 * min(size / n1, 1.0))

    def step_seconds(self, key, size: int) -> float:
        return self._predict(key, size, 1)

    def wall_seconds(self, key, size: int) -> float:
        return self._predict(key, size, 2)
