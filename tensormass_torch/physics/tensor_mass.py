"""TensorMass: the elastic force field of a mesh (or of a packed batch of meshes) as a module."""
from __future__ import annotations

from typing import Optional, Sequence

import numpy as np
import torch
from torch import nn

from .. import ops
from ..errors import MaterialError, MeshError, SceneError
from ..mesh.topology import add_at, incidence_slots, padded_sum
from ..ops import library, topology
from ..ops.variants import DEFAULT, KernelVariants
from .groups import FORMS, ElementGroup
from .materials import Material

#: The form ``form="auto"`` picks for each model: the one that reads fewer bytes per product.
#: ``hooke`` in Cotin's vertex/edge tensors reads about 3/4 of its stress form; ``stvk`` in
#: Picinbono's element tensors reads 25x its stress form and loses precision under large motions
#: in float32 (the measurements: ``benchmarks/results/h200/ops_bench.md``, docs/physics.md).
AUTO_FORM = {"hooke": "tensor", "stvk": "stress", "corotational": "stress"}
#: Edge rows reserved per spare node for cuts in place (``TensorMass.reserve_slots``): a node a
#: cut splits off brings about half its parent's edges (what the tetrahedral beams' cuts bring:
#: docs/topology-changes.md); a cut past the pool grows it.
EDGES_PER_NEW_NODE = 10


def _resolve_form(form: str, material) -> str:
    if form == "auto":
        if any(isinstance(getattr(material, name), torch.Tensor) and getattr(material, name).requires_grad
               for name in ("young", "poisson")):
            return "stress"  # the tensor form precomputes: no gradient to material parameters
        return AUTO_FORM[material.model]
    if form not in FORMS:
        raise MaterialError(f"unknown form {form!r}; expected 'auto', 'stress' or 'tensor'")
    return form


def _per_element(material, name: str, num_elements: int, like: torch.Tensor):
    """Material parameter ``name`` per element: a plain number stays a number (a batch of many
    bodies then makes one tensor per group, not one per body: :func:`_cat_per_element`), anything
    else becomes ``material.per_element``'s tensor ``[N]``."""
    value = getattr(material, name)
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    return material.per_element(name, num_elements, like)


def _cat_per_element(values, counts, like: torch.Tensor) -> torch.Tensor:
    """The per-element tensor ``[sum(counts)]`` of parts whose values are numbers or tensors
    ``[count]`` (in ``like``'s dtype and device; numbers copied to the device once)."""
    if all(isinstance(v, float) for v in values):
        per_part = torch.tensor(values, dtype=like.dtype).to(like.device)
        repeats = torch.tensor(counts, dtype=torch.int64).to(like.device)
        return per_part.repeat_interleave(repeats, output_size=sum(counts))
    return torch.cat([torch.full((n,), v, dtype=like.dtype, device=like.device) if isinstance(v, float) else v.to(like)
                      for v, n in zip(values, counts)])


def checked_element_ids(ids, removed: Optional[torch.Tensor], count: int, owner: str) -> torch.Tensor:
    """Element ids to remove as a sorted int64 CPU tensor, or one MeshError naming the problem:
    not 1-D integers, out of range of the ``count`` elements of ``owner`` (a label for the
    message), given twice, or already removed (``removed``: a CPU bool tensor ``[count]``, or None
    where none is). Checked on the host, against the host's copy of the removed mask, so that a
    removal between GPU steps waits for nothing (ids given on the GPU are read back once); in
    numpy, whose calls on a few hundred ids cost the host a fraction of torch's."""
    ids = torch.as_tensor(ids)
    if ids.dim() != 1 or (ids.numel() and (ids.dtype.is_floating_point or ids.dtype == torch.bool)):
        raise MeshError(f"element ids must be a 1-D integer sequence, got {ids.dtype} of shape {tuple(ids.shape)}")
    if ids.numel() == 0:
        return torch.zeros(0, dtype=torch.int64)
    sorted_ids = np.sort(ids.detach().cpu().numpy().astype(np.int64, copy=False))
    low, high = int(sorted_ids[0]), int(sorted_ids[-1])
    if low < 0 or high >= count:
        raise MeshError(f"element id {low if low < 0 else high} out of range: {owner} has {count} elements "
                        f"(0 .. {count - 1})")
    twice = sorted_ids[1:] == sorted_ids[:-1]
    if twice.any():
        raise MeshError(f"element ids given twice: {np.unique(sorted_ids[1:][twice])[:8].tolist()}")
    if removed is not None:
        gone = removed.numpy()[sorted_ids]
        if gone.any():
            raise MeshError(f"elements already removed: {sorted_ids[gone][:8].tolist()}")
    return torch.from_numpy(sorted_ids)


class TensorMass(nn.Module):
    """Tensor-Mass elastic forces, energy and force differentials of a mesh.

    Args:
        mesh: a ``TetMesh`` or ``TriMesh`` (rest shape).
        material: a :class:`Material` (scalar or per-element ``[N]`` parameters).
        form: ``"stress"``, ``"tensor"`` or ``"auto"`` (the faster, see ``AUTO_FORM``).

    Positions ``x`` are ``[V, d]`` with d the mesh dimension; the module follows ``.to()``.
    """

    def __init__(self, mesh, material: Material, form: str = "auto"):
        super().__init__()
        self._build(mesh.vertices, [(mesh.elements, material, mesh.kind)], form)

    @classmethod
    def packed(cls, rest: torch.Tensor, parts: Sequence, form: str = "auto") -> "TensorMass":
        """A model over concatenated nodes: ``rest [V, d]`` and parts ``(elements [N_i, n], material, kind)``
        with global node ids. Parts of the same kind, model and form share one group (one launch)."""
        self = cls.__new__(cls)
        nn.Module.__init__(self)
        self._build(rest, parts, form)
        return self

    def _build(self, rest, parts, form):
        self.dim = rest.shape[1]
        self.num_nodes = rest.shape[0]
        self.register_buffer("rest", rest)
        like = rest
        grouped = {}
        first_id = 0
        for elements, material, kind in parts:
            n_elem = elements.shape[0]
            model_form = _resolve_form(form, material)
            key = (kind, material.model, model_form, material.rotation if material.model == "corotational" else None,
                   material.tangent_for(model_form))
            young, poisson, density = (_per_element(material, name, n_elem, like)
                                       for name in ("young", "poisson", "density"))
            scale = _per_element(material, "thickness", n_elem, like) if kind == "tri" else None
            grouped.setdefault(key, []).append((elements, young, poisson, density, scale, first_id))
            first_id += n_elem
        groups = []
        masses = []
        for (kind, model, model_form, rotation, tangent), items in grouped.items():
            counts = [int(it[0].shape[0]) for it in items]
            elements = torch.cat([it[0] for it in items]).to(rest.device)
            young, poisson, density = (_cat_per_element([it[i] for it in items], counts, like) for i in (1, 2, 3))
            scale = _cat_per_element([it[4] for it in items], counts, like) if kind == "tri" else None
            group = ElementGroup(rest, elements, young, poisson, model, model_form, scale, rotation or "polar",
                                 tangent)
            groups.append(group)
            masses.append((elements, density * group.measure.detach()))
            # what a first removal needs to recover: each body's own tensors or plain numbers
            # (nothing allocated here; group_sources makes the tensors when asked)
            group.__dict__["_sources"] = [(it[5], n, it[1], it[2], it[3]) for it, n in zip(items, counts)]
        self.groups = nn.ModuleList(groups)
        self.num_elements = first_id
        self.register_buffer("mass", self._lumped_mass(masses))

    def _lumped_mass(self, element_masses) -> torch.Tensor:
        """Lumped masses ``[V]``: each element gives rho V_T / n to each of its n nodes."""
        nodes = torch.cat([e.reshape(-1) for e, _ in element_masses])
        shares = torch.cat([(m[:, None] / e.shape[1]).expand(e.shape).reshape(-1) for e, m in element_masses])
        slots, num_slots, _ = incidence_slots(nodes, self.num_nodes)
        return padded_sum(shares, nodes, slots, num_slots, self.num_nodes)

    def group_sources(self, group):
        """``(ids, young, poisson, density)`` of ``group``'s rows as built: the model's element ids
        ``[N_g]`` (int64) and the per-element material ``[N_g]`` (detached, in the model's dtype
        and on its device: the model may have moved since it was built)."""
        like = self.rest
        sources = group.__dict__["_sources"]
        ids = torch.cat([torch.arange(first, first + n, device=like.device) for first, n, *_ in sources])
        young, poisson, density = (_cat_per_element([s[k] for s in sources], [s[1] for s in sources], like)
                                   .detach() for k in (2, 3, 4))
        return ids, young, poisson, density

    # ---------------------------------------------------------------- topology changes
    def remove_elements(self, ids) -> float:
        """Remove elements in place, the Tensor-Mass way: each group drops their contribution
        (``ElementGroup.remove_rows``: the hooke tensor form sums the edges they touched again
        from the elements left on them) and the nodes they touched sum their lumped masses again
        from the elements left; forces, products, energy and masses are then those of a model
        built from the remaining elements (to rounding). Nothing is
        reallocated: every buffer, the gather plans and the node graphs keep their storage, so a
        solver's caches and captured CUDA graphs stay valid. Nodes left with no element keep mass
        0 exactly. The model of a ``Simulator``: use ``sim.remove_elements``, which also updates
        the integrator (masses, gravity, constraints).

        Args:
            ids: element ids ``[R]`` in the model's numbering (the parts' elements in order, as
                built; ids stay those of the original elements after removals).

        Returns:
            the mass removed (the removed elements' total, from a host copy: no device read).

        Raises:
            MeshError: an id out of range, given twice or already removed (nothing changed).
        """
        return self._remove_checked(self._check_removal(ids))

    def _remove_checked(self, ids: torch.Tensor) -> float:
        """:meth:`remove_elements` of ids already checked (``checked_element_ids``: sorted int64 on
        the CPU): :meth:`_remove_on_device` then :meth:`_removed_on_host`, a few launches that
        never wait for the device. Returns the mass removed."""
        if ids.numel() == 0:
            return 0.0
        self._prepare_removals()
        self._remove_on_device(ids.to(device=self.rest.device, non_blocking=True))
        return self._removed_on_host(ids)

    def _remove_on_device(self, ids: torch.Tensor) -> None:
        """The device's part of a removal of the checked ids ``[R]`` (int64, on the model's
        device; repeats allowed: every write is idempotent): the removed flags set, then each
        group's rows and the nodes they touch refreshed (``ops.topology``). Needs
        :meth:`_prepare_removals` first."""
        buffers = self._buffers  # (read once: nn.Module's attribute lookup costs the host more)
        removed, element_row = buffers["removed"], buffers["element_row"]
        index = element_row.dtype  # the ops' one index dtype (the elements')
        removed.index_fill_(0, ids, True)  # first: the refreshes read the flags
        for g, group in enumerate(self.groups):
            if len(self.groups) == 1:
                picked = ids  # one group: no mask, no host read
            else:
                picked = ids[buffers["element_group"][ids] == g]
                if picked.numel() == 0:
                    continue
            rows = element_row[picked]  # (in the index dtype)
            elements = group.elements if group.elements.dtype == index else group.elements.to(index)
            group.remove_rows(rows, self.rest, removed, element_row)
            topology.refresh_nodes(elements, rows, buffers["node_slots"], buffers["element_share"], removed,
                                   buffers["mass"], buffers["node_elements"])

    def _removed_on_host(self, ids: torch.Tensor) -> float:
        """The host's part of a removal of the checked ids (sorted int64 on the CPU): its copy of
        the removed flags set. Returns the mass removed, from its copy of the element masses."""
        host_ids = ids.numpy()
        self._removed_host.numpy()[host_ids] = True
        return float(self._element_mass_host.numpy()[host_ids].sum())

    def _check_removal(self, ids) -> torch.Tensor:
        return checked_element_ids(ids, self.removed_host(), self.num_elements, "the model")

    def removed_host(self) -> Optional[torch.Tensor]:
        """The host's copy of the removed mask ``[N]`` (CPU bool), or None before any removal."""
        return self.__dict__.get("_removed_host")

    def alive_elements(self) -> torch.Tensor:
        """``[N]`` bool over the model's element ids: those not removed."""
        if "removed" not in self._buffers:
            return torch.ones(self.num_elements, dtype=torch.bool, device=self.rest.device)
        return ~self.removed

    def isolated_nodes(self) -> torch.Tensor:
        """``[V]`` bool: nodes on no element (none ever, or every one removed or re-pointed):
        mass 0, no stiffness."""
        if "removed" not in self._buffers:
            used = torch.zeros(self.num_nodes, dtype=torch.bool, device=self.rest.device)
            for group in self.groups:
                used[group.elements.reshape(-1).long()] = True
            return ~used
        return self.node_elements == 0

    def _prepare_removals(self) -> None:
        """The data removals need, made at the first one (none before: a model never cut pays
        nothing): over the model's element ids ``[N]`` the removed flags, each element's group,
        its row there and its share of mass on each of its nodes (``element_share``); each node's
        incidence list (``node_slots [S, V]``: model element ids in the order the lumped masses
        were summed, -1 past the last) and alive element count (``node_elements [V]`` int32); per
        group what ``ElementGroup.prepare_removals`` keeps; on the host, the removed flags and the
        element masses. Index tensors have the elements' dtype."""
        if "removed" in self._buffers:
            return
        like = self.rest
        index = self.groups[0].elements.dtype
        element_group = torch.empty(self.num_elements, dtype=torch.long, device=like.device)
        element_row = torch.empty(self.num_elements, dtype=index, device=like.device)
        element_mass = like.new_empty(self.num_elements)
        element_share = like.new_empty(self.num_elements)
        nodes, items = [], []
        for g, group in enumerate(self.groups):
            ids, young, poisson, density = self.group_sources(group)
            group.prepare_removals(young, poisson, ids.to(index))
            element_group[ids] = g
            element_row[ids] = torch.arange(ids.numel(), device=like.device, dtype=index)
            element_mass[ids] = density * group.measure.detach()
            element_share[ids] = element_mass[ids] / group.nodes_per_element  # as _lumped_mass divides
            nodes.append(group.elements.reshape(-1).long())
            items.append(ids.to(index).repeat_interleave(group.nodes_per_element))
        nodes = torch.cat(nodes)
        self.register_buffer("element_group", element_group)
        self.register_buffer("element_row", element_row)
        self.register_buffer("element_share", element_share)
        self.register_buffer("node_slots", topology.incidence_table(nodes, torch.cat(items), self.num_nodes))
        self.register_buffer("node_elements", torch.bincount(nodes, minlength=self.num_nodes).to(torch.int32))
        self.register_buffer("removed", torch.zeros(self.num_elements, dtype=torch.bool, device=like.device))
        # the host's copies (plain attributes: they stay on the CPU when the model moves), so that
        # ids are checked and removed mass is counted without reading the device
        self.__dict__["_removed_host"] = torch.zeros(self.num_elements, dtype=torch.bool)
        self.__dict__["_element_mass_host"] = element_mass.to("cpu", torch.float64)

    def _cut_tables(self) -> dict:
        """The model's integer tables a cut reads and edits, on the host: ``node_slots``,
        ``element_group``, ``element_row`` (the model's own on the CPU; on an accelerator copies
        made at the first cut and kept equal by each cut: see ``ElementGroup.cut_tables``)."""
        tables = self.__dict__.get("_cut_host")
        if tables is None:
            on_copy = any(group._plans_on_a_copy() for group in self.groups)
            copy = (lambda t: t.to("cpu", copy=True)) if on_copy else (lambda t: t)
            tables = {name: copy(getattr(self, name)) for name in ("node_slots", "element_group", "element_row")}
            self.__dict__["_cut_host"] = tables
        return tables

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        self.__dict__.pop("_cut_host", None)  # made again from the moved tensors at the next cut
        return self

    @torch.no_grad()
    def repoint_elements(self, ids, nodes: torch.Tensor, new_nodes: torch.Tensor, parents: torch.Tensor) -> bool:
        """Re-point elements to new nodes in place (a cut: ``mesh.cutting`` says which): elements
        ``ids [M]`` (model ids, one group's, alive) get the node ids ``nodes [M, n]``; where an id
        changes it is one of ``new_nodes [K]``, rows no element uses yet (spare rows, or nodes
        whose elements were all removed or re-pointed), each a copy of ``parents [K]`` (its rest
        position). Per group, :meth:`ElementGroup.edit_cut` (the group's tables and the model's
        lists edited in one host call) and :meth:`ElementGroup.write_cut`; the lumped masses of
        the nodes left and joined summed again from their lists (as :meth:`remove_elements` does).
        Forces, products, energy and masses are then those of a model built from the new elements
        (to rounding). Nothing is reallocated (the node graphs, a solver's buffers and captured
        CUDA graphs keep their storage) but the hooke tensor form's edge arrays where the new
        edges outgrow their pool (:meth:`reserve_slots`).

        The cut is planned on the host (on copies of the integer tables where the model is on an
        accelerator: ``ElementGroup.cut_tables``), so it reads nothing from the device; what the
        device needs is sent in one copy (``ops.topology.upload``) and written by a few launches.
        Give ``ids``, ``nodes``, ``new_nodes`` and ``parents`` on the CPU for no device read at all.

        Returns:
            whether solves captured before must be captured again (:meth:`ElementGroup.write_cut`).

        Raises:
            MeshError: ids not of one group, or not alive (nothing changed).
            CapacityError: a node would need more slots than its group's plan has (nothing
                changed; :meth:`reserve_slots` gives room).
        """
        ids = checked_element_ids(ids, self.removed_host(), self.num_elements, "the model")
        if ids.numel() == 0:
            return False
        self._prepare_removals()
        tables = self._cut_tables()
        groups = torch.unique(tables["element_group"][ids])
        if groups.numel() != 1:
            raise MeshError(f"elements re-pointed together must be of one group, got groups {groups.tolist()}")
        group = self.groups[int(groups[0])]
        nodes = torch.as_tensor(nodes).to("cpu")
        if nodes.shape != (ids.numel(), group.nodes_per_element):
            raise MeshError(f"nodes must be [{ids.numel()}, {group.nodes_per_element}], got {tuple(nodes.shape)}")
        index = tables["element_row"].dtype
        rows = tables["element_row"][ids]
        node_slots = tables["node_slots"]
        # the group's tables and node_slots edited in one host call: the room is checked first, so
        # that a CapacityError leaves everything as it was
        group_sends, done = group.edit_cut(rows, ids, nodes, node_slots, tables["element_row"], self._removed_host)
        sends = {f"group_{k}": v for k, v in group_sends.items()}
        both = done["both"].to(index)  # the rows' nodes before and after: their masses summed again
        sends.update(new_nodes=torch.as_tensor(new_nodes).to("cpu", torch.int64),
                     parents=torch.as_tensor(parents).to("cpu", torch.int64), both=both,
                     both_rows=torch.arange(both.shape[0], dtype=index))
        if node_slots is not self.node_slots:
            sends.update(slot_nodes=done["slot_nodes"], slot_lists=done["node_slot_lists"])
        sent = topology.upload(sends, self.rest.device)
        self.rest.index_copy_(0, sent["new_nodes"].long(), self.rest[sent["parents"]])
        if node_slots is not self.node_slots:
            self.node_slots.index_copy_(1, sent["slot_nodes"].long(), sent["slot_lists"])
        stale = group.write_cut({k[6:]: v for k, v in sent.items() if k.startswith("group_")}, self.rest,
                                self.removed, self.element_row, cut=(rows, done["old_nodes"], nodes))
        topology.refresh_nodes(sent["both"], sent["both_rows"], self.node_slots, self.element_share, self.removed,
                               self.mass, self.node_elements)
        return stale

    def reserve_slots(self, extra: Optional[int] = None, spare_nodes: int = 0) -> None:
        """Room for cuts in place in the groups whose nodes gain items when cut (the hooke tensor
        form's edges: :meth:`ElementGroup.reserve_slots`): ``extra`` more slots per node (None:
        half the group's slots, at least 8: a node next to a cut gains an edge per neighbour
        split) and a pool of edge rows for the edges ``spare_nodes`` new nodes bring
        (``EDGES_PER_NEW_NODE`` each; a cut past the pool grows it, moving the edge arrays).
        Before the first solve (the node graphs take their slot count from the plans)."""
        for group in self.groups:
            group.reserve_slots(max(8, group.plan.num_slots // 2) if extra is None else extra,
                                EDGES_PER_NEW_NODE * int(spare_nodes))

    # ---------------------------------------------------------------- evaluation
    def _check_positions(self, name: str, x: torch.Tensor):
        if not isinstance(x, torch.Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(x).__name__}")
        if x.shape != (self.num_nodes, self.dim):
            raise SceneError(f"{name} has shape {tuple(x.shape)}; expected [{self.num_nodes}, {self.dim}]")
        if x.dtype != self.rest.dtype or x.device != self.rest.device:
            raise SceneError(f"{name} is {x.dtype} on {x.device} but the model holds {self.rest.dtype} on "
                             f"{self.rest.device}; move one with .to()")

    def forward(self, x: torch.Tensor, variants: KernelVariants = DEFAULT) -> torch.Tensor:
        """Elastic forces ``[V, d]`` at positions ``x [V, d]``; ``variants``: the kernels that
        compute them (the solver's ``StepOptions.variants``; every variant gives the same forces)."""
        self._check_positions("x", x)
        return self.displacement_forces(x - self.rest, variants)

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """Elastic energy (0-dim tensor) at positions ``x [V, d]``."""
        self._check_positions("x", x)
        return self.displacement_energy(x - self.rest)

    def dforce(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """(dF/dx) dx ``[V, d]``: the stiffness times ``dx [V, d]``, never assembled."""
        self._check_positions("dx", dx)
        return self.tangent(x)(dx)

    def tangent(self, x: torch.Tensor):
        """The stiffness at ``x [V, d]`` as a function ``dx [V, d] -> (dF/dx) dx [V, d]``.

        What the products share at one ``x`` (the corotational rotations) is computed once here,
        so a solver calls this once per linearisation and the function once per CG iteration.
        """
        self._check_positions("x", x)
        return self.displacement_tangent(x - self.rest)

    # The same at displacements u = x - rest [V, d]. A solver that keeps u (rather than x) keeps
    # its digits: in float32, x = rest + u rounds u to ~1e-7 of the body's size, a large
    # relative error for the small displacements of a stiff body.

    def displacement_forces(self, u: torch.Tensor, variants: KernelVariants = DEFAULT) -> torch.Tensor:
        """Elastic forces ``[V, d]`` at displacements ``u [V, d]`` from the rest shape."""
        self._check_positions("u", u)
        total = None
        for group in self.groups:
            f = ops.forces(group, u, variants=variants)
            total = f if total is None else total + f
        return total

    def displacement_energy(self, u: torch.Tensor) -> torch.Tensor:
        """Elastic energy (0-dim tensor) at displacements ``u [V, d]``."""
        self._check_positions("u", u)
        return sum(ops.energy(group, u) for group in self.groups)

    def displacement_tangent(self, u: torch.Tensor, states=None):
        """``dx -> (dF/dx) dx`` at displacements ``u [V, d]`` (see :meth:`tangent`); ``states``:
        ``[ops.linearize(g, u) for g in groups]`` when the caller has them (computed here when None)."""
        self._check_positions("u", u)
        if states is None:
            states = [ops.linearize(group, u) for group in self.groups]

        def apply(dx: torch.Tensor) -> torch.Tensor:
            total = None
            for group, state in zip(self.groups, states):
                f = ops.dforces(group, u, dx, state)
                total = f if total is None else total + f
            return total

        return apply

    @property
    def is_linear(self) -> bool:
        """Whether the forces are linear in the displacements (every group ``hooke``):
        f(u) + (dF/du) w = f(u + w), one pass over the elements instead of two."""
        return all(group.model == "hooke" for group in self.groups)

    def linearized_forces(self, u: torch.Tensor, w: torch.Tensor, states=None) -> torch.Tensor:
        """``f(u) + (dF/du)(u) w  [V, d]`` at displacements ``u [V, d]`` along ``w [V, d]``:
        implicit Euler's right-hand side. One pass for a linear model (``f(u + w)``); otherwise the
        forces and the product, sharing ``states`` (``[ops.linearize(g, u) for g in groups]``, the
        corotational rotations; computed here when None)."""
        self._check_positions("u", u)
        if self.is_linear:
            return self.displacement_forces(u + w)
        if states is None:
            states = [ops.linearize(group, u) for group in self.groups]
        total = None
        for group, state in zip(self.groups, states):
            f = ops.forces(group, u, state) + ops.dforces(group, u, w, state)
            total = f if total is None else total + f
        return total

    def stiffness_diagonal(self) -> torch.Tensor:
        """The diagonal ``[V, d]`` of the linear stiffness at rest (every group's
        :meth:`ElementGroup.stiffness_diagonal`), kept while the groups' tensors are unmodified
        (a cut edits them in place, and the next call sums again)."""
        tensors = tuple(t for group in self.groups for t in group.buffers())
        cache = self.__dict__.get("_stiffness_diagonal")
        if not library.unchanged(cache, tensors):
            total = sum(group.stiffness_diagonal() for group in self.groups)
            cache = self.__dict__["_stiffness_diagonal"] = (tensors, tuple(t._version for t in tensors), total)
        return cache[2]

    def stiffness_diagonal_blocks(self) -> torch.Tensor:
        """The diagonal blocks ``[V, d, d]`` of the linear stiffness at rest, K_ii = -sum_j K_ij
        over the edges of :meth:`rest_stiffness_edges` (what a block-Jacobi preconditioner
        inverts), kept while the groups' tensors are unmodified (a cut edits them in place)."""
        tensors = tuple(t for group in self.groups for t in group.buffers())
        cache = self.__dict__.get("_stiffness_blocks")
        if not library.unchanged(cache, tensors):
            edges, blocks = self.rest_stiffness_edges()
            flat = blocks.reshape(blocks.shape[0], -1)
            both = torch.cat([-flat, -blocks.transpose(1, 2).reshape(flat.shape)])
            nodes = torch.cat([edges[:, 0], edges[:, 1]])
            total = add_at(flat.new_zeros(self.num_nodes, flat.shape[1]), nodes, both)
            total = total.view(self.num_nodes, *blocks.shape[1:])
            cache = self.__dict__["_stiffness_blocks"] = (tensors, tuple(t._version for t in tensors), total)
        return cache[2]

    def rest_stiffness_edges(self):
        """Every group's :meth:`ElementGroup.rest_stiffness_edges` in one list ``(edges [E, 2],
        blocks [E, d, d])`` (an edge two groups share appears twice: its blocks add)."""
        parts = [group.rest_stiffness_edges() for group in self.groups]
        return torch.cat([e for e, _ in parts]), torch.cat([k for _, k in parts])

    def lumped_mass(self) -> torch.Tensor:
        """Lumped nodal masses ``[V]``."""
        return self.mass

    def buffer_bytes(self) -> int:
        """Bytes of precomputed data held (all groups, masses and rest positions)."""
        own = sum(b.numel() * b.element_size() for b in (self.rest, self.mass))
        return own + sum(g.buffer_bytes() for g in self.groups)
