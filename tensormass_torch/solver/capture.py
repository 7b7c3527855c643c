"""Device work on buffers that keep their storage, run through a CUDA graph captured once and
replayed: the CG's iterations (``solver.cg``), block Jacobi's paired loads
(``solver.preconditioner``), the adjoint's and the partitioned solver's (a module of its own so
that each of them can use it without importing the others)."""
from __future__ import annotations

import gc
from typing import Callable

import torch


def run_captured(graphs: dict, key, work: Callable[[], None]) -> bool:
    """Run ``work`` (device work on buffers that keep their storage) through a CUDA graph kept in
    ``graphs[key]``: the first time eagerly (which warms every op up), then captured; replayed
    from the next call on. A capture that fails (an op that cannot be captured) is remembered as
    False and the work stays eager: the same arithmetic. Capturing runs nothing, so the buffers
    keep their values. Returns whether a graph was replayed.

    Python's cycle collector is paused while capturing: a collection there can free another
    simulator's unreachable graphs and buffers, and destroying a graph during a capture
    invalidates the capture (seen: a chained step's capture failing after an earlier simulator
    of the same process became garbage)."""
    graph = graphs.get(key)
    if graph is None:
        work()
        graph = torch.cuda.CUDAGraph()
        collecting = gc.isenabled()
        gc.disable()
        try:
            with torch.cuda.graph(graph):
                work()
        except Exception:  # noqa: BLE001 (not capturable: the eager path is as correct)
            graph = False
        finally:
            if collecting:
                gc.enable()
        graphs[key] = graph
        return False
    if graph is False:
        work()
        return False
    graph.replay()
    return True


__all__ = ["run_captured"]
