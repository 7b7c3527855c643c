"""Element removals between CUDA steps replayed from captured graphs.

A removal in place (``TensorMass._remove_checked`` and the simulator's masses, gravity and
constraints) is a dozen small launches, each queued from Python: their host time, not their GPU
work, is most of its cost (docs/topology-changes.md). Here those launches are captured once per capacity (a power of
two, 16 ids and up) and replayed. Before each replay the ids, padded to the capacity by repeating
the last id, are copied into the graph's input buffer: a copy from pageable memory, ordered on the
stream, so the graph holds no copy node and nothing waits for an event. Repeating an id is
harmless: every write of a removal is idempotent (the flags set, and each node and edge it touched
summed again from the elements left on it, see ``ops.topology``).

What stays on the host: the ids' checks, the host's copies of the removed flags and element masses
(``TensorMass._removed_on_host``), the zeroed velocities of the nodes left with no element (the
state tensors are new at each step: a graph cannot hold them) and whatever else
``Simulator.remove_elements`` does after (surfaces for contact, the inversion check).

Replays write through the tensors' storage without torch knowing, so after each replay the
version counters of the tensors that the eager removal writes are bumped (found once, by the
versions the eager removal changed) and the node graph's cache stamped again, as the eager path
leaves them: a cache keyed on versions is rebuilt after a replay exactly as after an eager removal.
Graphs hold the addresses of what they read and write. A fingerprint of those tensors (the model's
buffers, the cached node graph's, the system's loads and constraint mask: their data pointers and
sizes) is taken at capture and compared before each replay; any change (a cut in place that grew a
table, a system built again) drops the graphs and the next removal captures again.

A capture that fails warns once and leaves the removals eager from then
on: the removal that tried it was made eagerly before the capture.

Serves a simulator on CUDA with CUDA graphs on, whose model is one element group (several groups
pick each group's ids by a mask, a host read) and whose system already has its constraint mask
(the first removal from a system built without one builds it again, eagerly).
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..ops import node_graph

__all__ = ["CapturedRemovals"]

SMALLEST_CAPACITY = 16


@dataclass
class _Capture:
    graph: torch.cuda.CUDAGraph
    ids: torch.Tensor  # [capacity] int64 on the device: the ids the graph reads
    isolated: torch.Tensor  # [V] bool on the device: nodes on no element after the removal


class CapturedRemovals:
    """The captured removals of ``sim`` (see the module docstring). ``remove(ids)`` removes the
    checked model ids ``ids [R]`` (sorted int64 on the CPU) and updates the masses, gravity and
    constraints in place, with no host synchronisation once a graph of its capacity exists."""

    @staticmethod
    def unavailable(sim) -> Optional[str]:
        """Why removals of ``sim`` cannot be replayed from graphs, or None where they can."""
        if sim._captured_removals is not None and sim._captured_removals.failed:
            return f"a capture failed: {sim._captured_removals.failed}"
        if sim.device.type != "cuda":
            return "not on CUDA"
        if not sim.options.cuda_graphs:
            return "cuda_graphs is off"
        if len(sim.model.groups) != 1:
            return "more than one element group"
        if sim.system.free is None:
            return "the system has no constraint mask yet"
        return None

    def __init__(self, sim):
        self.sim = sim
        self.captures: dict = {}  # capacity -> _Capture
        self.written: Optional[list] = None  # the tensors an eager removal bumps the versions of
        self.fingerprint = None
        #: why a capture failed (the removals then run eagerly from the next on), or None
        self.failed: Optional[str] = None

    def _tensors(self) -> list:
        """What the captured passes read and write and a topology change may reallocate: the
        model's buffers, the node graph cached on its group, the system's loads and constraint
        mask, gravity."""
        sim, group = self.sim, self.sim.model.groups[0]
        tensors = list(sim.model.buffers())
        cache = group.__dict__.get("_native_hooke_graph")
        if cache is not None:
            tensors += [*cache[0], *cache[2]]
        row_of = group.__dict__.get("_row_of")
        if row_of is not None:
            tensors.append(row_of[1])
        return tensors + [sim.system.external, sim.system.free, sim.gravity]

    def _fingerprint(self) -> tuple:
        return tuple((t.data_ptr(), t.numel()) for t in self._tensors())

    def remove(self, ids: torch.Tensor) -> None:
        sim = self.sim
        fingerprint = self._fingerprint()
        if fingerprint != self.fingerprint:  # (first use, or something moved: capture again)
            self.captures.clear()
            self.fingerprint, self.written = fingerprint, None
        capacity = max(SMALLEST_CAPACITY, 1 << (ids.numel() - 1).bit_length())
        capture = self.captures.get(capacity)
        if capture is None:
            capture = self._capture(capacity, ids)
        else:
            self._stage(capture, ids)
            capture.graph.replay()
            torch.autograd.graph.increment_version(self.written)
            node_graph.stamp_again(sim.model.groups[0])
        with torch.no_grad():
            sim.v.masked_fill_(capture.isolated[:, None], 0.0)

    @staticmethod
    def _stage(capture: _Capture, ids: torch.Tensor) -> None:
        """``ids`` padded by their last into the graph's input (stream-ordered after any replay
        still reading it)."""
        padded = np.empty(capture.ids.numel(), dtype=np.int64)
        padded[:ids.numel()] = ids.numpy()
        padded[ids.numel():] = padded[ids.numel() - 1]
        capture.ids.copy_(torch.from_numpy(padded), non_blocking=True)

    def _passes(self, capture: _Capture) -> None:
        """The removal on the device, in place (what the graph holds)."""
        sim = self.sim
        sim.model._remove_on_device(capture.ids)
        torch.eq(sim.model.node_elements, 0, out=capture.isolated)  # (TensorMass.isolated_nodes, into a kept buffer)
        sim._loads_follow_masses(capture.isolated)

    def _capture(self, capacity: int, ids: torch.Tensor) -> _Capture:
        """A graph of the removal of ``capacity`` ids, made while removing ``ids`` eagerly (the
        warm-up torch asks before a capture is the removal itself: it is idempotent)."""
        sim = self.sim
        device = sim.model.rest.device
        capture = _Capture(graph=torch.cuda.CUDAGraph(),
                           ids=torch.empty(capacity, dtype=torch.int64, device=device),
                           isolated=torch.empty(sim.model.num_nodes, dtype=torch.bool, device=device))
        self._stage(capture, ids)
        tensors = self._tensors()
        before = [t._version for t in tensors]
        self._passes(capture)  # the removal, eagerly
        if self.written is None:
            self.written = [t for t, version in zip(tensors, before) if t._version != version]
        try:
            with torch.cuda.graph(capture.graph):
                self._passes(capture)
        except RuntimeError as error:  # (torch.AcceleratorError among them)
            # The removal is made (eagerly, above) and a failed capture leaves nothing behind, so
            # the simulation goes on; its later removals run eagerly, as without CUDA graphs.
            self.failed = str(error).splitlines()[0] if str(error) else type(error).__name__
            warnings.warn(f"a removal's CUDA graph could not be captured ({self.failed}); removals "
                          f"run eagerly from now on", RuntimeWarning, stacklevel=4)
            return capture
        self.captures[capacity] = capture
        return capture
