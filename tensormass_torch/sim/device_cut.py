"""Cuts made where the body is: a scalpel's cut of every step as a few kernels on the simulator's
device, with no host synchronisation and, on CUDA, replayed from one captured graph.

The host cut (``Simulator.cut``) reads the positions back, finds the cut on the host and edits host
copies of the model's tables: its cost is host work, whatever the cut's size, and a step after it
cannot be queued before it is done. Here the cut is the ``cutting`` ops' device
passes (``ops.cutting.cut_on_device``: the faces the blade crosses, the split of the cut nodes'
stars, the elements re-pointed into the body's spare rows), then the model's lists and lumped
masses of the split nodes and their copies (``cutting_move_lists``), the node graph's rows of every
node whose neighbours changed (``node_graph_rebuild_hooke_rows``), the new nodes' rest positions,
constraints and state (``cutting_copy_rows``) and the gravity load: what the captured step reads,
written in place.

What it serves (``DeviceCuts.unavailable`` says why not, and the simulator then cuts on the host): a
simulator of one body whose model is one hooke tensor-form group stepped over its node graph (the
GPU's default for hooke), with spare rows, no prescribed motion or held nodes, no warm start by
projection, no BDF2 history, no inversion check, no tools or body contact. Everything else the
model holds about its topology (its edges and their plans, the host's copies of its tables, the
bodies' meshes) is left as it was and made again from the device's elements when something reads
it (``Simulator._refresh_views``, ``Simulator._settle_topology``).

A cut that does not fit (more new nodes than spare rows, a row or a chunk of the solve with more
slots than it was given) is not made, or is made only in part: ``status`` says so after the step,
and the simulator builds itself again from the cut mesh with room and runs the step again.
"""
from __future__ import annotations

from typing import Optional

import torch

from ..mesh.cutting import STRIP_TRIANGLES
from ..ops import cutting as ops_cutting
from ..ops import library, node_graph
from ..ops import solve as ops_solve

__all__ = ["DeviceCuts"]


class DeviceCuts:
    """The device cut of body 0 of ``sim`` (see the module docstring). ``cut(corners)`` queues a scalpel
    strip's cut (no host synchronisation); ``settle()`` reads, once the step after it has synchronised, how
    many nodes it added and whether it fitted."""

    @staticmethod
    def unavailable(sim) -> Optional[str]:
        """Why the cut on the device cannot serve ``sim``, or None where it can."""
        model, variants = sim.model, sim.options.variants
        if sim.num_bodies != 1:
            return "more than one body"
        if len(model.groups) != 1 or model.groups[0].form != "tensor" or model.groups[0].model != "hooke":
            return "not one hooke tensor-form group"
        if not (variants.hooke_matvec == "node" and node_graph.step_rhs_serves(model.groups[0], (), variants)):
            return "the step does not run over the node graph"
        if sim.ptr[1] - sim.used_nodes[0] <= 0:
            return "no spare rows"
        if sim._has_prescribed:
            return "prescribed motion"
        if sim._held is not None:
            return "held nodes"
        if sim.options.warm_start == "project":
            return "warm_start='project'"
        if sim.options.integrator == "bdf2":
            return "the bdf2 integrator"
        if sim._inversion is not None:
            return "an inversion check"
        if sim.tools is not None or sim.body_contact is not None:
            return "tools or body contact"
        return None

    def __init__(self, sim):
        model = sim.model
        model._prepare_removals()
        group = model.groups[0]
        self.sim, self.model, self.group = sim, model, group
        device = model.rest.device
        self.device = device
        self.faces = ops_cutting.face_table(group.elements, sim._slits[0])
        neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group, sim.options.variants.node_graph_window)
        self.graph = (neighbor, node_k, incidences)
        # each element's pair tensors, formed once: a cut re-points elements, never reshapes them
        self.pair_k = node_graph.hooke_pair_tensors(model.rest, group.elements, group.measure, group.young,
                                                    group.poisson).to(node_k.dtype)
        self.row_of = None if rows is None else node_graph._row_of(group, rows)
        # the solve's chunks and the slots their captured launches were given, where a solve ran
        captured = ops_solve.captured_chunk_slots(group)
        # (no solve yet: no chunk to check)
        self.chunks = ((torch.zeros(1, dtype=torch.int64, device=device), 0) if captured is None
                       else (captured[0].to(device=device, dtype=torch.int64), int(captured[1])))
        num_nodes = model.num_nodes
        used, room = sim.used_nodes[0], sim.ptr[1] - sim.used_nodes[0]
        self.max_rows = room
        self.limits = torch.tensor([used, room], dtype=torch.int64, device=device)
        self.last_cut = torch.zeros(2, dtype=torch.int64, device=device)  # the cut's rows: (first new node, how many)
        self.parents = torch.arange(num_nodes, device=device)
        self.status = torch.zeros(1, dtype=torch.int32, device=device)
        self.touched = torch.zeros(num_nodes, dtype=torch.uint8, device=device)
        self.blade_vertices = torch.zeros(4, 3, dtype=model.rest.dtype, device=device)
        self.blade_triangles = torch.tensor(STRIP_TRIANGLES, device=device)
        # the first cut also examines the nodes of the faces parted before (the slit)
        self.scratch: dict = {"recheck": self.faces[2].clone()}
        self.copy_rows = library.op_or_reference(ops_cutting.COPY_ROWS, device)
        self.alive = (~model.removed).contiguous()
        # the state the cut reads and writes the new nodes' rows into, then the step starts from
        # (the simulator's state tensors are replaced by each step: a captured graph needs these)
        self.positions, self.velocities = torch.empty_like(sim.x), torch.empty_like(sim.v)
        self.captured = None
        self.pending = 0  # cuts queued since the last settle
        pinned = device.type == "cuda"
        # (the rows in use after the cuts so far, status: 1 once a cut did not fit) on the device,
        # and its copy on the host: several cuts queued before one step add up
        self.outcome = torch.zeros(2, dtype=torch.int64, device=device)
        self.report = torch.zeros(2, dtype=torch.int64, pin_memory=pinned)
        self.report_array = self.report.numpy()
        self.used = used  # the rows in use at the last settle
        # the strip's corners on their way to the device (the graph's first copy reads them; written
        # once the cut before has read them)
        self.staging = torch.zeros(4, 3, dtype=model.rest.dtype, pin_memory=pinned)
        self.staging_array = self.staging.numpy()  # (written through numpy: cheaper than a torch copy)
        self.reported = torch.cuda.Event() if pinned else None
        self.added = 0  # nodes the settled cuts added

    def cut(self, corners: torch.Tensor) -> None:
        """Queue the cut along a scalpel's strip (``corners [4, 3]``, ``Scalpel.strip``: the two
        triangles (0, 1, 2) and (0, 2, 3)) at the positions now."""
        if corners.shape != (4, 3):
            raise ValueError(f"the cut on the device takes a scalpel's strip (corners [4, 3]), got "
                             f"{tuple(corners.shape)}")
        cuda = self.device.type == "cuda"
        if self.pending and self.reported is not None:
            self.reported.synchronize()  # (a cut queued before this one may not have read the staging buffer yet)
        self.staging_array[...] = corners.detach().cpu().numpy()
        self.positions.copy_(self.sim.x)
        self.velocities.copy_(self.sim.v)
        if cuda and self.sim.options.cuda_graphs:
            if self.captured is None:
                graph = torch.cuda.CUDAGraph()
                # the warm-up examines no slit: it splits nothing (the first cut, replayed, does)
                recheck = self.scratch["recheck"]
                held = recheck.clone()
                recheck.zero_()
                stream = torch.cuda.Stream(self.device)
                stream.wait_stream(torch.cuda.current_stream(self.device))
                with torch.cuda.stream(stream):  # warm-up before capture, as torch asks: not a cut
                    self._passes(warm_up=True)
                torch.cuda.current_stream(self.device).wait_stream(stream)
                recheck.copy_(held)
                with torch.cuda.graph(graph):
                    self._passes()
                self.captured = graph
            self.captured.replay()
        else:
            self._passes()
        self.sim._replace_state(self.positions, self.velocities)
        if self.reported is not None:
            self.reported.record()
        self.pending += 1

    def _passes(self, warm_up: bool = False) -> None:
        """The cut's passes, in order (what the captured graph holds). ``warm_up``: run them on a
        blade that crosses nothing (before a capture: kernels loaded, buffers made), changing
        nothing."""
        sim, model, group = self.sim, self.model, self.group
        op = library.op_or_reference
        vertices = self.blade_vertices
        if warm_up:  # a blade far from the body: no face crossed, no node split
            vertices = torch.full_like(vertices, 1e30)
        else:  # (captured: the host writes the staging buffer before each replay)
            vertices.copy_(self.staging, non_blocking=True)
        ops_cutting.cut_on_device(self.positions, group.elements, model.node_slots, self.alive, self.faces, vertices,
                                  self.blade_triangles, self.limits, self.parents, self.scratch)
        op(ops_cutting.COUNT_NEW_NODES, self.device)(self.scratch["ends"], self.limits, self.last_cut, self.status)
        self.touched.zero_()
        op(ops_cutting.MOVE_LISTS, self.device)(group.elements, self.scratch["group"], self.scratch["new_count"],
                                                self.scratch["offset"], self.limits, self.parents,
                                                model.element_share, self.alive, model.node_slots, model.mass,
                                                model.node_elements, self.touched)
        for values in (model.rest, sim.system.free, sim.fixed, sim.prescribed, self.positions, self.velocities):
            self.copy_rows(self.last_cut, self.parents, self.max_rows, values)
        neighbor, node_k, incidences = self.graph
        op("node_graph_rebuild_hooke_rows", self.device)(
            self.pair_k, group.elements, model.node_slots, self.alive, self.touched, self.row_of, neighbor.shape[0],
            neighbor, node_k, incidences, self.status, self.scratch["group"])  # (the ranks are read by now)
        torch.mul(model.mass[:, None], sim.gravity, out=sim.system.external)
        # (a chunk of the solve now holding more slots than its launches sets the status too)
        op(ops_cutting.CLOSE_CUT, self.device)(self.last_cut, incidences, self.chunks[0], self.chunks[1], self.limits,
                                               self.status, self.outcome)
        self.report.copy_(self.outcome, non_blocking=True)

    def settle(self):
        """``(added, fitted)`` of the cuts queued since the last call, once the step after them
        synchronised (reads the pinned report; waits for it only if the step did not)."""
        if not self.pending:
            return 0, True
        if self.reported is not None:
            self.reported.synchronize()
        self.pending = 0
        used, status = (int(value) for value in self.report_array)  # (numpy: no torch call on the host)
        added, self.used = used - self.used, used
        self.added += added
        return added, status == 0

