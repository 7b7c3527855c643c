"""Bodies and the Simulator: many objects packed into one batch, stepped by implicit Euler."""
from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Callable, Dict, List, Optional, Sequence, Tuple

import torch

from ..errors import CapacityError, MeshError, SceneError, SolverError
from ..mesh.cutting import Blade, still_joined
from ..mesh.meshes import Mesh
from ..mesh.topology import boundary_faces
from ..ops import node_graph
from ..ops.cutting import cut_mesh, near_elements
from ..ops.segments import Segments
from ..ops.topology import upload
from ..physics.body_contact import Contact, SurfaceContact
from ..physics.constraints import node_mask
from ..physics.contact import Plane, Planes
from ..physics.materials import Material
from ..physics.tensor_mass import TensorMass, checked_element_ids
from ..physics.tools import Tool, ToolSet
from ..solver.guess import warm_start_mode
from ..solver.implicit_euler import (
    INTEGRATORS,
    DynamicsSystem,
    StepOptions,
    StepReport,
    auto_cg_max_iter,
    bdf2_step,
    implicit_euler_step,
    step_graphs_for,
)
from ..solver.preconditioner import PRECONDITIONERS
from ..solver.refine import PRECISIONS
from . import memory
from .captured_removal import CapturedRemovals
from .device_cut import DeviceCuts
from .diagnostics import ContactReport, InversionCheck, InversionReport, contact_report, interpenetration
from .scalpel import Scalpel

#: ``Simulator(check_inversion=...)`` values.
INVERSION_CHECKS = ("off", "warn", "error")
#: Deepest sub-stepping retry ``Simulator(substeps_on_failure=...)`` accepts (2^10 sub-steps).
MAX_SUBSTEP_DEPTH = 10


def _spare_rows(spare_nodes, count: int) -> List[int]:
    """``Simulator(spare_nodes=...)`` as one count per body (>= 0), or one SceneError."""
    values = [spare_nodes] * count if isinstance(spare_nodes, int) and not isinstance(spare_nodes, bool) \
        else list(spare_nodes) if isinstance(spare_nodes, (list, tuple)) else None
    if values is None or len(values) != count or any(isinstance(v, bool) or not isinstance(v, int) or v < 0
                                                      for v in values):
        raise SceneError(f"spare_nodes must be an integer >= 0 or one per body ({count}), got {spare_nodes!r}")
    return values


#: Spare node rows a cut that finds no room reserves per body: at least this many, at least
#: ``1 / SPARE_FRACTION`` of the body's nodes, at least twice what the cut needs.
MIN_SPARE_NODES = 256
SPARE_FRACTION = 8


class InvertedElementsWarning(RuntimeWarning):
    """A step left elements inverted (``Simulator(check_inversion="warn")``)."""


class Body:
    """One object of a scene: a mesh, its material, its constraints and initial velocity.

    Args:
        mesh: ``TetMesh`` or ``TriMesh`` (2-D triangle meshes are placed in the plane z = 0).
        material: :class:`Material`.
        fixed: nodes held at rest: bool mask ``[V]`` or indices ``[k]``.
        prescribed: nodes that follow ``motion``: bool mask ``[V]`` or indices ``[k]``.
        motion: ``motion(t) -> [k, 3]`` positions of the prescribed nodes (ascending node order) at
            time t.
        velocity: initial velocity ``[3]`` or ``[V, 3]``.
        name: a label for reports.
    """

    def __init__(self, mesh, material: Material, fixed=None, prescribed=None,
                 motion: Optional[Callable[[float], torch.Tensor]] = None, velocity=None, name: Optional[str] = None):
        if not isinstance(material, Material):
            raise SceneError(f"material must be a tm.Material, got {type(material).__name__}")
        self.mesh = mesh
        self.material = material
        self.name = name
        num_nodes = mesh.num_vertices
        device = mesh.vertices.device
        self.fixed = node_mask(fixed, num_nodes, "fixed", device)
        self.prescribed = node_mask(prescribed, num_nodes, "prescribed", device)
        if (motion is None) != (not bool(self.prescribed.any())):
            raise SceneError("prescribed nodes and motion go together: give both or neither")
        if bool((self.fixed & self.prescribed).any()):
            raise SceneError("a node cannot be both fixed and prescribed")
        self.motion = motion
        if bool((self.fixed | self.prescribed).all()):
            label = f"body {name} " if name else "the body "
            raise SceneError(f"every node of {label}is fixed or prescribed: nothing to simulate")
        used = torch.zeros(num_nodes, dtype=torch.bool, device=device)
        used[mesh.elements.reshape(-1)] = True
        massless = ~used & ~self.fixed & ~self.prescribed
        if bool(massless.any()):
            ids = torch.nonzero(massless).flatten()[:10].tolist()
            raise SceneError(f"vertices {ids} belong to no element: they would have no mass; fix them or remove them")
        self.velocity = velocity

    @classmethod
    def _trusted(cls, mesh, material: Material, fixed: torch.Tensor, prescribed: torch.Tensor, motion, name) -> "Body":
        """A body of data known to be valid (a valid body's cut: masks ``[V]`` on the mesh's
        device, motion with prescribed nodes), built with no check (no device read)."""
        body = cls.__new__(cls)
        body.mesh, body.material, body.name = mesh, material, name
        body.fixed, body.prescribed, body.motion, body.velocity = fixed, prescribed, motion, None
        return body


class Simulator:
    """Implicit Euler simulation of several bodies as one packed batch.

    All bodies share one set of kernels launches: nodes and elements are concatenated with
    global ids, and the conjugate gradient keeps per-object scalars and convergence.

    Args:
        bodies: list of :class:`Body`.
        dt: time step (> 0).
        gravity: ``[3]`` acceleration.
        rayleigh_mass, rayleigh_stiffness: Rayleigh damping r_M, r_K (>= 0).
        planes: list of :class:`Plane` (penalty contact).
        tools: list of rigid tools (:func:`tm.Sphere`, :func:`tm.Capsule`, :func:`tm.Box`): penalties
            on the signed distance, their stiffness in the implicit system, each tool where its
            path puts it at the end of the step; their reactions in ``StepReport.contact``.
        contact: a :class:`tm.Contact` (thickness, stiffness, self-contact) for contact between the
            surfaces of the tetrahedral bodies, or None (default: bodies pass through each other).
            Pairs are found at the start of each step; bodies they join are solved together; its
            steps run eagerly (not chained). Counts and penetrations in ``StepReport.contact``.
        integrator: ``"backward_euler"`` (default: numerical damping that grows with dt, the most
            robust), ``"newmark"`` (Newmark's average acceleration, the trapezoidal rule: no
            numerical damping) or ``"bdf2"`` (second order, its damping falling as dt^3; each
            step uses the state one step before, so the first step, a step after ``sim.x`` or
            ``sim.v`` were set, and sub-steps are backward Euler's and steps are not chained);
            all at backward Euler's cost per step (see ``solver.implicit_euler``).
        cg_tol, cg_max_iter, require_convergence, newton_iters, check_every, cuda_graphs,
            preconditioner, warm_start, paired_blocks, precision: see ``StepOptions``. With ``warm_start=True`` (or
            ``"extrapolate"``) each step's CG starts from the extrapolation of the two steps
            before (2 dv_1 - dv_2; dv_1 after one step; zeros after a state set by hand, a cut
            that made room, sub-steps or a chain of steps, which keep no history); with
            ``"project"``, from the projection of its solution on the last steps' solutions
            (``solver.guess``: any state, steps one at a time, no chains; best where the step's
            matrix is constant, as hooke's without contact). ``cg_max_iter=None`` (default) caps CG at
            ``auto_cg_max_iter`` of the largest object's free degrees of freedom, so a
            converging solve is never cut short; the value used is ``sim.options.cg_max_iter``.
        form: element force form, ``"auto" | "stress" | "tensor"``.
        device, dtype: where and in what precision to simulate (default: the meshes').
        check_inversion: inverted elements after each step: ``"off"`` (no check, no cost),
            ``"warn"`` (counts per object in ``StepReport.inverted``, details in
            ``last_inversion``, an ``InvertedElementsWarning`` when an object's elements start
            to invert) or ``"error"``
            (a step that inverts an element raises ``SolverError`` naming the objects and
            elements; the state is kept).
        substeps_on_failure: when a step fails (``SolverError``), retry it as 2, 4, ..., 2^k
            sub-steps of dt / 2^k, k up to this depth (0: no retry); ``StepReport.substeps`` says
            how many were used. The state is kept if every retry fails.
        spare_nodes: node rows reserved after each body's nodes (an int for every body, or one
            per body) for the nodes cuts add: while they last (and the plans' slots do) a cut
            runs in place, keeping the solver's caches and captured CUDA graphs. 0 (default):
            the first cut builds the simulator again with room (see :meth:`cut`). Spare rows
            are part of ``x``, ``v`` (held, no mass); ``positions(i)`` and the other per-body
            views show a body's nodes only.
        check_memory: on a CUDA device, estimate the scene's peak memory before building it
            (``tm.estimate_memory``) and raise ``SceneError`` at once, with the estimate, the
            free memory and about how many elements would fit, where it cannot fit (nothing is
            allocated). False: build anyway (an estimate: docs/scale.md says how close).
    """

    def __init__(self, bodies: Sequence[Body], dt: float = 0.01, gravity=(0.0, 0.0, -9.81),
                 rayleigh_mass: float = 0.0, rayleigh_stiffness: float = 0.0, planes: Sequence[Plane] = (),
                 cg_tol: float = 1e-6, cg_max_iter: Optional[int] = None, require_convergence: bool = True,
                 newton_iters: int = 1, check_every: int = 8, form: str = "auto", device=None, dtype=None,
                 cuda_graphs: bool = True, check_inversion: str = "off", substeps_on_failure: int = 0,
                 spare_nodes=0, tools: Sequence[Tool] = (), contact: Optional[Contact] = None,
                 preconditioner: str = "auto", integrator: str = "backward_euler", warm_start=False,
                 check_memory: bool = True, cut_on_device: bool = False, paired_blocks: bool = True,
                 precision: str = "full"):
        bodies = list(bodies)
        if not hasattr(self, "initial_bodies"):  # (a rebuild for a cut runs __init__ again: kept)
            #: the bodies this simulator was first built with (:meth:`rebuilt`)
            self.initial_bodies = list(bodies)
            self._initial_spare = spare_nodes
        # what a topology change that rebuilds the simulator (cut) builds it again with
        self._init_args = dict(dt=dt, gravity=gravity, rayleigh_mass=rayleigh_mass,
                               rayleigh_stiffness=rayleigh_stiffness, planes=planes, cg_tol=cg_tol,
                               cg_max_iter=cg_max_iter, require_convergence=require_convergence,
                               newton_iters=newton_iters, check_every=check_every, form=form, device=device,
                               dtype=dtype, cuda_graphs=cuda_graphs, check_inversion=check_inversion,
                               substeps_on_failure=substeps_on_failure, tools=tools, contact=contact,
                               preconditioner=preconditioner, integrator=integrator, warm_start=warm_start,
                               cut_on_device=cut_on_device, paired_blocks=paired_blocks, precision=precision)
        spare = _spare_rows(spare_nodes, len(bodies))
        if not bodies:
            raise SceneError("a simulator needs at least one body")
        for i, b in enumerate(bodies):
            if not isinstance(b, Body):
                raise SceneError(f"bodies[{i}] is a {type(b).__name__}, not a tm.Body")
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and dt > 0):
            raise SceneError(f"dt must be a positive finite number, got {dt!r}")
        for name, value in (("rayleigh_mass", rayleigh_mass), ("rayleigh_stiffness", rayleigh_stiffness)):
            if not (math.isfinite(value) and value >= 0):
                raise SceneError(f"{name} must be >= 0 and finite, got {value!r}")
        if cg_max_iter is not None and (isinstance(cg_max_iter, bool) or not isinstance(cg_max_iter, int)
                                        or cg_max_iter < 1):
            raise SceneError(f"cg_max_iter must be a positive integer or None (automatic), got {cg_max_iter!r}")
        if not (isinstance(cg_tol, (int, float)) and not isinstance(cg_tol, bool) and math.isfinite(cg_tol)
                and cg_tol >= 0):
            raise SceneError(f"cg_tol must be a finite number >= 0, got {cg_tol!r}")
        if newton_iters < 1:
            raise SceneError(f"newton_iters must be >= 1, got {newton_iters}")
        if preconditioner not in PRECONDITIONERS:
            raise SceneError(f"preconditioner must be one of {', '.join(map(repr, PRECONDITIONERS))}, "
                             f"got {preconditioner!r}")
        if integrator not in INTEGRATORS:
            raise SceneError(f"integrator must be one of {', '.join(map(repr, INTEGRATORS))}, got {integrator!r}")
        if INTEGRATORS[integrator] != 1.0 and newton_iters != 1:
            raise SceneError(f"newton_iters={newton_iters} needs integrator='backward_euler' or 'bdf2' (the "
                             f"{integrator!r} step is one linearisation)")
        if not isinstance(paired_blocks, bool):
            raise SceneError(f"paired_blocks must be True or False, got {paired_blocks!r}")
        try:
            warm_start_mode(warm_start)
        except ValueError as exc:
            raise SceneError(str(exc)) from None
        if check_inversion not in INVERSION_CHECKS:
            raise SceneError(f"check_inversion must be one of {', '.join(map(repr, INVERSION_CHECKS))}, "
                             f"got {check_inversion!r}")
        if isinstance(substeps_on_failure, bool) or not isinstance(substeps_on_failure, int) \
                or not 0 <= substeps_on_failure <= MAX_SUBSTEP_DEPTH:
            raise SceneError(f"substeps_on_failure must be an integer in [0, {MAX_SUBSTEP_DEPTH}] "
                             f"(retries at dt / 2^k), got {substeps_on_failure!r}")
        devices = {b.mesh.vertices.device for b in bodies}
        if device is None and len(devices) > 1:
            raise SceneError(f"bodies live on mixed devices {sorted(map(str, devices))}; pass device=")
        dtypes = {b.mesh.vertices.dtype for b in bodies}
        if dtype is None and len(dtypes) > 1:
            raise SceneError(f"bodies have mixed dtypes {sorted(map(str, dtypes))}; pass dtype=")
        self.device = torch.device(device) if device is not None else devices.pop()
        self.dtype = dtype if dtype is not None else dtypes.pop()
        _check_precision(precision, self.dtype, preconditioner, contact)
        if not isinstance(check_memory, bool):
            raise SceneError(f"check_memory must be True or False, got {check_memory!r}")
        if not isinstance(cut_on_device, bool):
            raise SceneError(f"cut_on_device must be True or False, got {cut_on_device!r}")
        #: whether the scene's memory was checked against the device's before it was built
        self.check_memory = check_memory
        if check_memory:  # before anything is allocated on the device
            memory.check_fits(bodies, self.dtype, self.device, form, warm_start, precision)
        gravity = torch.as_tensor(gravity, dtype=self.dtype, device=self.device)
        if gravity.shape != (3,) or not bool(torch.isfinite(gravity).all()):
            raise SceneError(f"gravity must be 3 finite numbers, got {gravity.tolist()}")

        self._bodies = bodies
        #: whether scalpels cut on the device where they can (``sim.device_cut.DeviceCuts``)
        self.cut_on_device = cut_on_device
        self._device_cuts = None  # the DeviceCuts of body 0, made at the first scalpel's cut
        self._captured_removals = None  # the CapturedRemovals, made at the first removal on CUDA
        self._device_cut_blades: list = []  # the blades cut on the device since the last settle
        # each scalpel's strip for the next step {(scalpel, t0, t1): corners} (scalpels keyed by
        # identity), made while the device runs this step's cut (see _apply_scalpels)
        self._next_strips: dict = {}
        self._views_stale = False  # the bodies' meshes lag behind cuts made on the device
        if cg_max_iter is None:
            free_dofs = [3 * int((~(b.fixed | b.prescribed)).sum()) for b in bodies]
            cg_max_iter = auto_cg_max_iter(max(free_dofs))
        self.options = StepOptions(dt=float(dt), rayleigh_mass=float(rayleigh_mass),
                                   rayleigh_stiffness=float(rayleigh_stiffness), cg_tol=cg_tol,
                                   cg_max_iter=cg_max_iter, require_convergence=require_convergence,
                                   newton_iters=newton_iters, check_every=check_every,
                                   cuda_graphs=bool(cuda_graphs), preconditioner=preconditioner,
                                   integrator=integrator, warm_start=warm_start,
                                   paired_blocks=bool(paired_blocks), precision=precision)
        rest_parts, parts, fixed, prescribed, velocities = [], [], [], [], []
        # bodies on the host are packed on the host and moved once (a batch of many small bodies
        # would otherwise cost a dozen small copies and a synchronisation a body)
        staging = torch.device("cpu") if all(b.mesh.vertices.device.type == "cpu" for b in bodies) else self.device
        offset = 0
        for b, room in zip(bodies, spare):
            verts = b.mesh.vertices.to(device=staging, dtype=self.dtype)
            if verts.shape[1] == 2:
                verts = torch.cat([verts, verts.new_zeros(verts.shape[0], 1)], dim=1)
            no = torch.zeros(room, dtype=torch.bool, device=staging)
            # spare rows: copies of the body's first node (no element: no mass, held)
            rest_parts.append(torch.cat([verts, verts[:1].expand(room, -1)]))
            parts.append((b.mesh.elements.to(staging) + offset, b.material, b.mesh.kind))
            fixed.append(torch.cat([b.fixed.to(staging), no]))
            prescribed.append(torch.cat([b.prescribed.to(staging), no]))
            vel = torch.zeros_like(verts) if b.velocity is None else \
                torch.as_tensor(b.velocity, dtype=self.dtype, device=staging).expand_as(verts).clone()
            vel[b.fixed.to(staging)] = 0.0
            velocities.append(torch.cat([vel, vel.new_zeros(room, 3)]))
            offset += verts.shape[0] + room
        rest = torch.cat(rest_parts).to(self.device)
        self.ptr = [0]
        for r in rest_parts:
            self.ptr.append(self.ptr[-1] + r.shape[0])
        #: each body's node count (its first rows; the spare rows follow, up to the next ``ptr``)
        self.used_nodes = [b.mesh.num_vertices for b in bodies]
        self.model = TensorMass.packed(rest, parts, form=form)
        if any(spare):
            self.model.reserve_slots(spare_nodes=sum(spare))
        self.fixed = torch.cat(fixed).to(self.device)
        self.prescribed = torch.cat(prescribed).to(self.device)
        self._has_prescribed = any(b.motion is not None for b in bodies)  # known once: no sync per step
        #: nodes held where a caller puts them (:meth:`hold_nodes`): packed ids ``[k]`` and their
        #: targets ``[k, 3]``, or None
        self._held = None
        self.segments = Segments.from_lengths([r.shape[0] for r in rest_parts], self.device)
        #: each body's first element in the model's numbering, and the element count ``[B + 1]``
        self.element_ptr = [0]
        for b in bodies:
            self.element_ptr.append(self.element_ptr[-1] + b.mesh.elements.shape[0])
        self.gravity = gravity
        self.planes = Planes(planes, self.dtype, self.device) if planes else None
        #: the rigid tools (``physics.tools.ToolSet``) or None
        self.tools = ToolSet(list(tools), self.dtype, self.device) if tools else None
        if contact is not None and not isinstance(contact, Contact):
            raise SceneError(f"contact must be a tm.Contact or None, got {type(contact).__name__}")
        self.contact = contact
        #: contact between the bodies' surfaces (``physics.body_contact.SurfaceContact``) or None
        self.body_contact = None
        #: the mass each body has lost to element removals ``[B]`` (float64, on the CPU: summed from
        #: the host's copy of the element masses, so that a removal launches nothing for it)
        self.removed_mass = torch.zeros(len(bodies), dtype=torch.float64)
        self._make_system()
        self._surfaces_changed()
        self.x = rest.clone()
        self.v = torch.cat(velocities).to(self.device)
        self.time = 0.0
        self.steps_done = 0
        self.last_report: Optional[StepReport] = None
        # the state one step before and the state committed after it (BDF2's history: valid while
        # sim.x, sim.v are still those committed tensors)
        self._history = None
        # the solutions of the last steps' first solves, newest first, and the state committed
        # after the newest (warm_start's history: valid while sim.x, sim.v are those tensors)
        self._solutions = None
        self.check_inversion = check_inversion
        self.substeps_on_failure = substeps_on_failure
        # Built only when asked for: "off" costs nothing (no buffers, no work per step).
        self._inversion = InversionCheck.for_simulator(self) if check_inversion != "off" else None
        self.last_inversion: Optional[InversionReport] = None
        self._inverted_before: Optional[List[bool]] = None  # objects with inverted elements ("warn")
        #: the scalpels that cut before each step (:meth:`add_scalpel`)
        self.scalpels: List[Scalpel] = []
        # per body, the element pairs cuts parted that still share their face (``cutting.cut``'s slit)
        self._slits: List[Optional[torch.Tensor]] = [None] * len(bodies)
        self._host_meshes: dict = {}  # body -> (its mesh's elements on the device, a host copy)

    @property
    def num_bodies(self) -> int:
        return len(self._bodies)

    @property
    def device_cuts_active(self) -> bool:
        """Whether the scalpels' cuts run on the device (``cut_on_device`` asked for it and
        ``sim.device_cut.DeviceCuts`` serves this simulator, from its first cut in spare rows)."""
        return self._device_cuts is not None

    @property
    def bodies(self) -> List[Body]:
        """The bodies as they are now (their meshes with the nodes cuts added)."""
        if self._views_stale:
            self._refresh_views()
        return self._bodies

    @bodies.setter
    def bodies(self, bodies) -> None:
        self._bodies = list(bodies)

    def _make_system(self):
        """The integrator's view of the model (masses, gravity, constraints; its solver caches
        and CUDA graphs start afresh). A node without mass (a vertex no element uses, or one whose
        last element was removed) has no stiffness either: it leaves the system, held in place.
        Once elements have been removed the system keeps a constraint mask even when nothing is
        constrained, so that later removals update it in place."""
        mass = self.model.lumped_mass()
        constrained = self.fixed | self.prescribed | (mass == 0)
        if self._held is not None:
            constrained = constrained.clone()
            constrained[self._held[0]] = True
        keep_mask = ("removed" in self.model._buffers or self.ptr[-1] > sum(self.used_nodes)
                     or getattr(self, "_held_ever", False))
        self.system = DynamicsSystem(self.model, mass, mass.unsqueeze(-1) * self.gravity, self.segments,
                                     constrained, self.planes, keep_mask=keep_mask, tools=self.tools,
                                     body_contact=self.body_contact)

    def _surfaces_changed(self):
        """The body contact's surfaces from the bodies' remaining tetrahedra (after a cut or a
        removal the surfaces change), into the system; nothing without ``contact``."""
        if self.contact is None:
            return
        triangles = self.surface_triangles()
        if not triangles:
            raise SceneError("contact is between the surfaces of tetrahedral bodies; this simulator has none")
        self.body_contact = SurfaceContact(torch.cat(list(triangles.values())), self.segments.node_object,
                                           self.model.rest, self.contact)
        self.system.body_contact = self.body_contact

    def _masses_changed(self):
        """After the model lost elements in place: gravity follows the masses and nodes left with
        no element leave the system (held, velocity 0), all in place (the solver's caches and
        captured CUDA graphs read this storage), but for the first removal from a system built
        without a constraint mask."""
        isolated = self.model.isolated_nodes()
        with torch.no_grad():
            self.v.masked_fill_(isolated[:, None], 0.0)
        if self.system.free is None:
            self._make_system()
            return
        self._loads_follow_masses(isolated)

    def _loads_follow_masses(self, isolated: torch.Tensor) -> None:
        """Gravity from the masses as they are and the nodes ``isolated [V]`` (bool: on no element)
        out of the system, in place: the storage the solver's caches and captured graphs read (the
        captured removals replay this too)."""
        torch.mul(self.model.lumped_mass()[:, None], self.gravity, out=self.system.external)
        self.system.free.masked_fill_(isolated[:, None], 0.0)

    def _body_index(self, body) -> int:
        """The index of ``body``: an index, a ``Body`` of this simulator or a body's name. (Reads
        the bodies as they are, not as cuts on the device left their meshes: a name or a ``Body``
        does not change with a cut, and a scalpel looks its body up before every step.)"""
        if isinstance(body, Body):
            for i, b in enumerate(self._bodies):
                if b is body:
                    return i
            raise SceneError("this Body is not one of the simulator's bodies")
        if isinstance(body, str):
            names = [b.name for b in self._bodies]
            if names.count(body) != 1:
                raise SceneError(f"no body named {body!r}" if body not in names else f"two bodies are named {body!r}")
            return names.index(body)
        if isinstance(body, bool) or not isinstance(body, int) or not -self.num_bodies <= body < self.num_bodies:
            raise SceneError(f"body must be a body index in [0, {self.num_bodies}), a tm.Body of this simulator or "
                             f"a body name, got {body!r}")
        return body % self.num_bodies

    def remove_elements(self, body, ids) -> float:
        """Remove elements of one body between steps (carving), in place: the model drops them
        the Tensor-Mass way (``TensorMass.remove_elements``), the masses and gravity follow, and a
        node left with no element leaves the system (its velocity zeroed, held in place). The
        next step is that of a simulator built from the remaining elements at the same state.
        Nothing is rebuilt: the solver's caches and captured CUDA graphs stay valid (after the
        first removal, which gives a system without constraints a constraint mask).

        Args:
            body: a body index, a ``tm.Body`` of this simulator, or a body's name.
            ids: element ids of that body's mesh (the original numbering: ids stay valid after
                earlier removals).

        Returns:
            the mass removed (added to ``removed_mass[body]``).

        Raises:
            SceneError / MeshError: a bad body, an id out of range, given twice or already
            removed; nothing is changed.
        """
        i = self._body_index(body)
        self._settle_topology()
        first, end = self.element_ptr[i], self.element_ptr[i + 1]
        removed = self.model.removed_host()
        ids = checked_element_ids(ids, None if removed is None else removed[first:end], end - first,
                                  f"body {i}")  # the body's ids in messages
        if ids.numel() == 0:
            return 0.0
        ids = ids + first  # checked once, as the body's ids
        self.model._prepare_removals()
        if CapturedRemovals.unavailable(self) is None:  # (on CUDA: replayed from a graph)
            if self._captured_removals is None:
                self._captured_removals = CapturedRemovals(self)
            self._captured_removals.remove(ids)
            lost = self.model._removed_on_host(ids)
        else:
            lost = self.model._remove_checked(ids)  # counted from the host's copy: no device read
            self._masses_changed()
        self.removed_mass[i] += lost
        self._surfaces_changed()
        if self._inversion is not None:
            self._inversion = InversionCheck.for_simulator(self)
        return lost

    def hold_nodes(self, body, nodes, positions) -> None:
        """Hold nodes of a body at ``positions`` from the next step on, as prescribed nodes are
        held on their path (a grab: a viewer's dragged node, a gripper): each step ends with them
        there, the rest of the body following implicitly. ``nodes``: ids of the body's mesh
        ``[k]`` (or a bool mask); ``positions [k, 3]``. Holding again replaces every held node
        of the simulator; :meth:`release_nodes` lets them go. Raises ``SceneError`` naming a bad
        body, node (out of range, fixed or prescribed) or position; nothing changes then."""
        i = self._body_index(body)
        local = torch.nonzero(node_mask(nodes, self.used_nodes[i], "hold_nodes: nodes", self.device)).flatten()
        ids = local + self.ptr[i]
        targets = torch.as_tensor(positions, dtype=self.dtype, device=self.device)
        if targets.numel() == 3 * ids.numel():
            targets = targets.reshape(-1, 3)
        if targets.shape != (ids.numel(), 3) or not bool(torch.isfinite(targets).all()):
            raise SceneError(f"hold_nodes: positions must be [{ids.numel()}, 3] finite numbers, got shape "
                             f"{tuple(targets.shape)}")
        if bool((self.fixed | self.prescribed)[ids].any()):
            raise SceneError("hold_nodes: fixed and prescribed nodes are held already; hold free nodes")
        self.release_nodes()
        if ids.numel() == 0:
            return
        self._held = (ids, targets.clone())
        if self.system.free is None:  # a system built without constraints: one with a mask, once
            self._held_ever = True
            self._make_system()
        else:
            self.system.free[ids] = 0.0

    def release_nodes(self) -> None:
        """Let the nodes :meth:`hold_nodes` holds go (they move freely from the next step on)."""
        if self._held is None:
            return
        ids = self._held[0]
        self._held = None
        free = ~(self.fixed | self.prescribed)[ids] & (self.model.lumped_mass()[ids] > 0)
        self.system.free[ids] = free.to(self.system.free.dtype)[:, None]

    def _imposed_velocity(self, x: torch.Tensor, t_next: float, h: float):
        """End-of-step velocities ``[V, 3]`` taking the prescribed nodes from ``x [V, 3]`` to
        ``motion(t_next)`` and the held ones to where they are held over a step of length h
        (zero on fixed nodes), or None."""
        if not self._has_prescribed and self._held is None:
            return None
        target_v = torch.zeros_like(self.v)
        if self._held is not None:
            ids, goal = self._held
            target_v[ids] = (goal - x[ids]) / h
        for i, b in enumerate(self.bodies):
            if b.motion is None:
                continue
            nodes = torch.nonzero(b.prescribed.to(self.device)).flatten() + self.ptr[i]
            goal = torch.as_tensor(b.motion(t_next), dtype=self.dtype, device=self.device)
            if goal.shape != (nodes.numel(), 3):
                raise SceneError(f"body {i}: motion(t) returned shape {tuple(goal.shape)}; "
                                 f"expected [{nodes.numel()}, 3]")
            target_v[nodes] = (goal - x[nodes]) / h
        return target_v

    def _check_inversion(self, x: torch.Tensor, t: float, report: StepReport):
        """Measure inverted elements at ``x [V, 3]`` (time t) into ``report`` (``check_inversion``
        on); "error" raises SolverError when any element is inverted."""
        inversion = self._inversion(x)
        report.inverted = inversion.inverted
        if self.check_inversion == "error" and bool((inversion.inverted > 0).any()):
            status = ["inverted" if c else "ok" for c in inversion.inverted.tolist()]
            raise SolverError(f"the step to t = {t:.6g} inverts elements ({inversion.describe(self._names())}); "
                              "the state was not changed", status, report)
        return inversion

    def _names(self):
        return [b.name for b in self._bodies]

    def _warn_new_inversions(self, inversion: InversionReport):
        """Warn when an object that had no inverted element has some now (once per episode, not
        at every step of it)."""
        now = [c > 0 for c in inversion.inverted.tolist()]
        before = self._inverted_before or [False] * len(now)
        self._inverted_before = now
        if any(n and not b for n, b in zip(now, before)):
            warnings.warn(f"inverted elements at t = {self.time:.6g}: {inversion.describe(self._names())}",
                          InvertedElementsWarning, stacklevel=3)

    def _substep(self, x, v, t_end: float, opts: StepOptions, previous=None, guess=None):
        """One implicit step of length ``opts.dt`` from ``x, v [V, 3]``, ending at time t_end
        (nothing committed): (x, v, report, inversion report or None). ``previous``: BDF2's
        state one step before (None: its start, a backward Euler step); ``guess``: the first
        solve's initial guess (``warm_start``) or None."""
        if self.tools is not None:  # the tools where they are at the step's end
            self.tools.set_time(t_end, opts.dt)
        if opts.integrator == "bdf2":
            if previous is None:
                imposed = self._imposed_velocity(x, t_end, opts.dt)
            else:  # the prescribed nodes reach their target from BDF2's extrapolated start over 2 dt / 3
                imposed = self._imposed_velocity((4.0 * x - previous[0]) / 3.0, t_end, 2.0 * opts.dt / 3.0)
            x_new, v_new, report = bdf2_step(self.system, x, v, previous, opts, imposed, guess)
        else:
            imposed = self._imposed_velocity(x, t_end, opts.dt)
            x_new, v_new, report = implicit_euler_step(self.system, x, v, opts, imposed, guess)
        inversion = self._check_inversion(x_new, t_end, report) if self._inversion is not None else None
        return x_new, v_new, report, inversion

    def _substeps(self, count: int):
        """The step from the current state as ``count`` sub-steps of dt / count (nothing
        committed): (x, v, report, inversion report or None)."""
        opts = self.options if count == 1 else dataclasses.replace(self.options, dt=self.options.dt / count)
        x, v = self.x, self.v
        reports, inversion = [], None
        for j in range(count):
            # prescribed motions at the sub-step times; the last one ends exactly at time + dt
            t_end = self.time + self.options.dt * ((j + 1) / count)
            one = count == 1
            x, v, report, inversion = self._substep(x, v, t_end, opts, self._previous_state() if one else None,
                                                    self._guess() if one else None)
            reports.append(report)
        if count == 1:
            return x, v, reports[0], inversion
        merged = StepReport(cg=[r for rep in reports for r in rep.cg], inverted=reports[-1].inverted,
                            substeps=count)
        return x, v, merged, inversion

    def _advance(self):
        """One step of dt; on a failed solve, retried with the classic CG where the pipelined one
        ran (:meth:`_classic_cg_may_solve`), then in sub-steps up to ``substeps_on_failure`` halvings."""
        try:
            return self._substeps(1)
        except SolverError as first:
            failure = first
        if self._classic_cg_may_solve(failure):
            self.options = dataclasses.replace(self.options, pipelined=False)
            try:
                return self._substeps(1)  # the classic CG stays for the steps that follow
            except SolverError as exc:  # a real failure: the classic CG fails it too
                self.options = dataclasses.replace(self.options, pipelined=True)
                failure = exc
        if self.substeps_on_failure == 0:
            raise failure
        for depth in range(1, self.substeps_on_failure + 1):
            try:
                return self._substeps(2 ** depth)
            except SolverError as exc:
                failure = exc
        raise SolverError(f"step at t = {self.time:.6g} failed at dt = {self.options.dt:g} and in 2 to "
                          f"{2 ** self.substeps_on_failure} sub-steps; last: {failure}", failure.status,
                          failure.report) from failure

    def _classic_cg_may_solve(self, failure: SolverError) -> bool:
        """Whether a step whose solve failed is worth retrying with the classic CG: a solve's
        failure on a CUDA device while the pipelined CG is chosen. In float32 its recurrences lose
        accuracy on an ill-conditioned system (nearly incompressible rubber at a large step): it
        takes more iterations and can meet a false breakdown where the classic CG converges.
        (Where the pipelined CG did not serve the system, the retry fails as the step did.)"""
        return bool(self.options.pipelined and self.device.type == "cuda" and failure.status
                    and any(s in ("not converged", "breakdown", "non-finite") for s in failure.status))

    def step(self, n: int = 1) -> StepReport:
        """Advance ``n`` implicit Euler steps; returns the last step's report.

        A failed step (after its sub-step retries, if any) raises ``SolverError`` and leaves
        positions, velocities and time as they were before that step. The scalpels
        (:meth:`add_scalpel`) cut before each step.

        On a CUDA device, when a whole step runs without a host decision (every CG iteration
        inside the captured step: the whole CG is one op that stops on the device, as for the
        hooke tensor form, or ``cg_max_iter <= check_every``, or with ``precision="mixed"`` one
        round of refinement; no prescribed motion; no inversion check), consecutive steps are
        chained: up to 64 run back to back with ONE host
        synchronisation, then every step's outcome is checked in order. Should one have failed, the
        steps before it are committed (run again: the kernels are deterministic) and it is run on
        its own, which raises (or retries in sub-steps) exactly as above.
        """
        left = int(n)
        while left > 0:
            if self.scalpels:
                self._apply_scalpels()
            chain = self._chain_graphs() if left > 1 and not self.scalpels else None
            if chain is not None:
                count = min(left, chain.max_chain)
                done = self._run_chain(chain, count)
                left -= done
                if done == count:
                    continue
            # One step on its own: the path that raises, retries in sub-steps and checks
            # inversions (after a chained step failed, it runs that step again and fails the same).
            try:
                x, v, report, inversion = self._advance()
            except SolverError:
                if self._device_cuts is not None:  # the state stays the cut's; not its buffers
                    self._replace_state(self.x.clone(), self.v.clone())
                raise
            if self._device_cuts is not None and self._device_cuts.pending and not self._settle_device_cuts():
                x, v, report, inversion = self._advance()  # built again with room: the step again
            self._commit(x, v, 1, report, inversion)
            if self.check_inversion == "warn":
                self._warn_new_inversions(inversion)
            left -= 1
        return self.last_report

    def _previous_state(self):
        """BDF2's state one step of dt before the current one ``(x, v)``, or None where there is
        none: the first step, a chain or sub-steps before, ``sim.x`` / ``sim.v`` set since,
        the node count changed (a cut that made room)."""
        if self._history is None:
            return None
        previous, committed = self._history
        if committed[0] is not self.x or committed[1] is not self.v or previous[0].shape != self.x.shape:
            return None
        return previous

    def _guess(self):
        """``warm_start``'s guess of the next step's first solve ``[V, 3]``: 2 dv_1 - dv_2 from the
        two steps before, dv_1 from one, None without history (see ``_commit``)."""
        solutions = self._solutions_before()
        if self.options.warm_start != "extrapolate" or not solutions:
            return None
        return solutions[0] if len(solutions) == 1 else 2.0 * solutions[0] - solutions[1]

    def _solutions_before(self) -> list:
        """The kept solutions (newest first) while the state is the one committed after them."""
        if self._solutions is None:
            return []
        solutions, committed = self._solutions
        if committed[0] is not self.x or committed[1] is not self.v or solutions[0].shape != self.x.shape:
            return []
        return solutions

    def _replace_state(self, x: torch.Tensor, v: torch.Tensor) -> None:
        """The state ``x, v [V', d]`` moved into other tensors, unchanged but for rows no element
        held before (a cut on the device writes its new nodes' rows there): what was kept with the
        state (warm start's solutions, BDF2's state before) stays the current state's."""
        committed = (self.x, self.v)
        if self._solutions is not None and self._solutions[1][0] is committed[0] \
                and self._solutions[1][1] is committed[1]:
            self._solutions = (self._solutions[0], (x, v))
        if self._history is not None and self._history[1][0] is committed[0] and self._history[1][1] is committed[1]:
            self._history = (self._history[0], (x, v))
        self.x, self.v = x, v

    def _commit(self, x, v, steps: int, report: StepReport, inversion):
        single = steps == 1 and report.substeps == 1
        one_step = single and self.options.integrator == "bdf2"
        self._history = ((self.x, self.v), (x, v)) if one_step else None
        if self.options.warm_start == "extrapolate":
            kept = self._solutions_before()[:1]
            self._solutions = ([report.cg[0].solution] + kept, (x, v)) if single and report.cg else None
        self.x, self.v = x, v
        for _ in range(steps):  # the same float sum as one step at a time
            self.time += self.options.dt
        self.steps_done += steps
        if self.tools is not None or self.body_contact is not None:
            report.contact = contact_report(self, x)
        self.last_report = report
        self.last_inversion = inversion

    def add_scalpel(self, scalpel: Scalpel) -> None:
        """Cut with ``scalpel`` from now on: before each step from t to t + dt, its body is cut
        along the surface its edge sweeps from t - dt to t + dt (``Scalpel.blade``; strips that
        overlap, ``sim.scalpel``; a sweep that crosses no face of the body cuts nothing). Steps
        are then run one by one (no chaining).

        Raises:
            SceneError: not a ``tm.Scalpel``, or its body is not one of this simulator's 3-D bodies.
        """
        if not isinstance(scalpel, Scalpel):
            raise SceneError(f"add_scalpel takes a tm.Scalpel, got {type(scalpel).__name__}")
        i = self._body_index(scalpel.body)
        if self.bodies[i].mesh.vertices.shape[1] != 3:
            raise SceneError(f"body {i} is 2-D: cutting needs a 3-D body (tetrahedra or membranes)")
        self.scalpels.append(scalpel)

    def _apply_scalpels(self) -> None:
        """The scalpels' cuts for the step from ``time`` to ``time + dt`` (sweeps from ``time - dt``:
        strips that overlap, see ``sim.scalpel``): on the device where ``cut_on_device`` and
        :class:`DeviceCuts` serve this simulator, else on the host (:meth:`cut`)."""
        dt = self.options.dt
        on_device = False
        for scalpel in self.scalpels:
            t0, t1 = self.time - dt, self.time + dt
            key = (scalpel, t0, t1)
            corners = self._next_strips[key] if key in self._next_strips else scalpel.strip(t0, t1)
            if corners is None:
                continue
            cuts = self._device_cutter(scalpel.body)
            if cuts is None:
                self.cut(scalpel.body, Blade.strip(corners), missing_ok=True)
            else:
                cuts.cut(corners)
                self._device_cut_blades.append(corners)
                on_device = True
        # the next step's strips (its time as _commit will add it), made on the host while the
        # device runs these cuts rather than before the next ones while it waits
        following = self.time + dt
        t0, t1 = following - dt, following + dt
        self._next_strips = {(s, t0, t1): s.strip(t0, t1) for s in self.scalpels} if on_device else {}

    def _device_cutter(self, body) -> Optional[DeviceCuts]:
        """The device cut of ``body`` where ``cut_on_device`` asks for it and it serves this
        simulator (made at the first call), else None."""
        if not self.cut_on_device or self._body_index(body) != 0:
            return None
        if self._device_cuts is None:
            if DeviceCuts.unavailable(self) is not None:
                return None
            self._device_cuts = DeviceCuts(self)
        return self._device_cuts

    def _settle_device_cuts(self) -> bool:
        """After a step that followed cuts on the device (its host synchronisation done): the nodes
        they added join body 0 (``used_nodes``; its mesh made again when read: ``bodies``). False
        where a cut did not fit: the simulator is then built again from the cut mesh with room and
        the cuts that were not made are made on the host; the caller runs the step again."""
        cuts = self._device_cuts
        added, fitted = cuts.settle()
        blades, self._device_cut_blades = self._device_cut_blades, []
        if added:
            self.used_nodes[0] += added
            self._views_stale = True
            self._history = None  # (BDF2's state before has no rows for the new nodes)
        if fitted:
            return True
        self._rebuild_from_device(blades)
        return False

    def _settle_topology(self) -> None:
        """Before a change of topology on the host (a cut, a removal): where cuts were made on the
        device, the model's other tables (edges, plans, host copies) lag behind them, so the
        simulator is built again from the cut mesh first (with room for the cuts to come); where
        none split a node yet, the cut on the device is only made again at its next cut."""
        if self._device_cuts is not None and self._device_cuts.pending:  # (settle() waits for the report)
            self._settle_device_cuts()
        if self._device_cuts is None:  # (none, or a cut that did not fit built the simulator again)
            return
        if self._device_cuts.added:
            self._rebuild_from_device(())
        else:
            # no node split yet: the model's tables are current, but the cut's own (the alive
            # elements, the system's buffers it captured) are made again at the next cut, and the
            # faces it parted stay parted as the body's slit
            self._refresh_views()
            self._device_cuts = None

    def _refresh_views(self) -> None:
        """Body 0 as the cuts on the device left it: its mesh (rest positions and elements of its
        used rows, read back), constraints and slit (the parted faces whose elements still share
        them), the host's copies of its elements dropped."""
        self._views_stale = False
        cuts = self._device_cuts
        old = self._bodies[0]
        used = self.used_nodes[0]
        # copies: the cuts to come write the model's elements and rest positions in place
        elements = cuts.group.elements.to(device=old.mesh.elements.device, dtype=old.mesh.elements.dtype, copy=True)
        vertices = self.model.rest[:used].to(device=old.mesh.vertices.device, dtype=old.mesh.vertices.dtype,
                                             copy=True)
        mesh = type(old.mesh)._trusted(vertices, elements)
        self._bodies[0] = Body._trusted(mesh, old.material, self.fixed[:used].to(old.fixed.device),
                                        self.prescribed[:used].to(old.prescribed.device), None, old.name)
        face_elements, _, parted = cuts.faces
        pairs = face_elements[parted].long()
        self._slits[0] = pairs[still_joined(cuts.group.elements.long(), pairs)].to("cpu")
        self._host_meshes.pop(0, None)

    def _rebuild_from_device(self, blades) -> None:
        """The simulator built again around body 0 as the cuts on the device left it, with room;
        then the cuts of ``blades`` (a scalpel's strips, ``Scalpel.strip``) made on the host (those
        a cut on the device could not make)."""
        self._refresh_views()
        self._rebuild_with_room(0, None)
        for corners in blades:
            self.cut(0, Blade.strip(corners), missing_ok=True)

    def cut(self, body, blade: Blade, missing_ok: bool = False) -> int:
        """Cut one body along ``blade`` between steps, where the body is now: the faces the blade
        crosses part and their nodes split (``mesh.cutting``), so that the sides move apart; a
        cut through the whole section leaves pieces that fall on their own. The body's mesh gets
        the new nodes (copies of their parents: rest position, state, fixed or prescribed).

        In place where there is room (the body's spare rows, ``Simulator(spare_nodes=)``, and
        its plans' slots): the model re-points the elements (``TensorMass.repoint_elements``) and
        the solver's caches and captured CUDA graphs stay (but for a stress-form body, whose
        tangent graph is built again). Otherwise the simulator is built again around the cut
        body with spare rows for the cuts to come (``MIN_SPARE_NODES``, ``SPARE_FRACTION``;
        removed elements stay removed; positions, velocities, time carried over).

        Args:
            body: a body index, a ``tm.Body`` of this simulator, or a body's name (3-D bodies).
            blade: a ``tm.Blade`` (e.g. ``tm.Blade.swept(a0, b0, a1, b1)``: a scalpel's edge
                between two poses).

            missing_ok: a blade that crosses no interior face of the body cuts nothing and
                returns 0 (a scalpel in the air) instead of raising.

        Returns:
            the number of nodes the cut added.

        Raises:
            MeshError: the blade crosses no interior face of the body (nothing changed), unless
                ``missing_ok``.
        """
        i = self._body_index(body)
        if not isinstance(blade, Blade):
            raise SceneError(f"blade must be a tm.Blade, got {type(blade).__name__}")
        self._settle_topology()
        old = self.bodies[i]
        if old.mesh.vertices.shape[1] != 3:
            raise SceneError(f"body {i} is 2-D: cutting needs a 3-D body (tetrahedra or membranes)")
        # the cut is found on the host: the body's elements and removed flags kept there, its
        # positions read once; on an accelerator the elements it looks at are picked there first
        # (a superset: near_elements), so that the host pass skips the others
        elements = self._host_elements(i)
        first, end = self.element_ptr[i], self.element_ptr[i + 1]
        removed = self.model.removed_host()
        removed = None if removed is None else removed[first:end]
        alive = None
        if self.device.type != "cpu":
            alive = near_elements(old.mesh.elements, self.positions(i), blade, self._slits[i])
            if "removed" in self.model._buffers:
                alive &= ~self.model.removed[first:end]
        try:
            result = cut_mesh(elements, old.mesh.num_vertices, self.positions(i).to("cpu"), blade, removed,
                              self._slits[i], alive=None if alive is None else alive.to("cpu"))
        except MeshError:
            if missing_ok:
                return 0
            raise
        if not self._cut_in_place(i, elements, result):
            self._rebuild_with_room(i, result)
        self._slits[i] = result.slit
        return result.new_nodes

    def _host_elements(self, i: int) -> torch.Tensor:
        """Body i's elements ``[N_i, n]`` on the host: its mesh's, or a copy kept with the mesh."""
        elements = self.bodies[i].mesh.elements
        if elements.device.type == "cpu":
            return elements
        kept = self._host_meshes.get(i)
        if kept is None or kept[0] is not elements:
            kept = self._host_meshes[i] = (elements, elements.to("cpu"))
        return kept[1]

    @staticmethod
    def _cut_body(old: Body, result, changed: Optional[torch.Tensor] = None) -> Body:
        """Body ``old`` after the cut ``result``: its mesh with the new nodes (copies of their
        parents: rest position, fixed or prescribed; the prescribed copies follow their parents).
        ``changed``: the ids of the elements the cut re-pointed (host), or None: any."""
        device = old.mesh.vertices.device
        new_parents = result.parents[result.num_old_nodes:].to(device)
        vertices = torch.cat([old.mesh.vertices, old.mesh.vertices[new_parents]])
        if changed is None or device.type == "cpu":
            elements = result.elements.to(device)
        else:  # the rows that changed written into a copy on the device
            elements = old.mesh.elements.clone()
            elements[changed.to(device)] = result.elements[changed].to(device, elements.dtype)
        mesh = type(old.mesh)._trusted(vertices, elements)
        fixed = torch.cat([old.fixed, old.fixed[new_parents]])
        prescribed = torch.cat([old.prescribed, old.prescribed[new_parents]])
        motion = None
        if old.motion is not None:  # the prescribed nodes' copies follow their parents
            mesh_parents = result.parents.to(device)
            old_ids = torch.nonzero(old.prescribed).flatten()
            new_ids = torch.nonzero(prescribed).flatten()
            pick = torch.searchsorted(old_ids, mesh_parents[new_ids])

            def motion(t, follow=old.motion, pick=pick):
                goal = torch.as_tensor(follow(t))
                return goal[pick.to(goal.device)]
        return Body._trusted(mesh, old.material, fixed, prescribed, motion, old.name)

    def _cut_in_place(self, i: int, elements: torch.Tensor, result) -> bool:
        """The cut ``result`` of body i (its elements before: ``elements``, like the result's on
        the host) done in place, in the body's spare rows: the model re-points the elements
        (``TensorMass.repoint_elements``), the new nodes take their parents' state and
        constraints, masses and gravity follow. False, having changed nothing, where there is no
        room (spare rows, a plan's slots)."""
        used, first = self.used_nodes[i], self.ptr[i]
        added = result.new_nodes
        if used + added > self.ptr[i + 1] - first:
            return False
        changed = self._changed_rows(i, elements, result)
        if changed.numel() == 0:  # faces parted along a slit's front, no node split yet
            return True
        new_nodes = torch.arange(first + used, first + used + added)
        parents = result.parents[used:] + first
        edges = [g.edges for g in self.model.groups if g.form == "tensor" and g.model == "hooke"]
        try:
            stale = self.model.repoint_elements(changed + self.element_ptr[i], result.elements[changed] + first,
                                                new_nodes, parents)
        except CapacityError:
            return False
        # a cut that adds edges moves a hooke tensor-form group's edge arrays (edges, edge_k, the
        # plan's native copies): captured launches that read them must be captured again
        moved = any(g.edges is not e for g, e in zip([g for g in self.model.groups if g.form == "tensor"
                                                      and g.model == "hooke"], edges))
        stale = stale or (moved and self._captures_read_edges())
        sent = upload({"new_nodes": new_nodes, "parents": parents}, self.device)
        new_nodes, parents = sent["new_nodes"], sent["parents"]
        with torch.no_grad():
            self.x[new_nodes] = self.x[parents]
            self.v[new_nodes] = self.v[parents]
        self._history = None  # (BDF2's state before has no rows for the new nodes: its next step starts again)
        self.fixed[new_nodes] = self.fixed[parents]
        self.prescribed[new_nodes] = self.prescribed[parents]
        self.bodies[i] = self._cut_body(self.bodies[i], result, changed)
        if i in self._host_meshes:  # the cut's elements are the new mesh's on the host
            self._host_meshes[i] = (self.bodies[i].mesh.elements, result.elements)
        self.used_nodes[i] = used + added
        if stale:  # a new integrator view: its CUDA graphs captured again
            self._make_system()
            self._surfaces_changed()
        else:
            torch.mul(self.model.lumped_mass()[:, None], self.gravity, out=self.system.external)
            free = ~(self.fixed | self.prescribed)[new_nodes]
            self.system.free[new_nodes] = free.to(self.system.free.dtype)[:, None]
            self._surfaces_changed()
        if self._inversion is not None:
            self._inversion = InversionCheck.for_simulator(self)
        return True

    def _changed_rows(self, i: int, elements: torch.Tensor, result) -> torch.Tensor:
        """The ids ``[M]`` (body i's, ascending, host) of the elements the cut ``result`` re-pointed
        (``elements``: the body's before, on the host). Only elements that held a split node can
        change: they are read from the model's incidence lists of the new nodes' parents (the
        host's ``node_slots``), not found by comparing every element."""
        parents = result.parents[result.num_old_nodes:]
        if parents.numel() == 0:
            return torch.zeros(0, dtype=torch.int64)
        self.model._prepare_removals()
        node_slots = self.model._cut_tables()["node_slots"]
        listed = node_slots[:, parents + self.ptr[i]].reshape(-1)
        ids = torch.unique(listed[listed >= 0].long()) - self.element_ptr[i]
        ids = ids[(ids >= 0) & (ids < elements.shape[0])]
        return ids[(result.elements[ids] != elements[ids]).any(1)]

    def _captures_read_edges(self) -> bool:
        """Whether the integrator's captured launches may read a hooke tensor-form group's edge
        arrays: unless the model is one such group whose step and products all run over its node
        graph (written in place by a cut), as on a GPU with the default kernels."""
        groups, variants = self.model.groups, self.options.variants
        return not (len(groups) == 1 and variants.hooke_matvec == "node"
                    and node_graph.step_rhs_serves(groups[0], (), variants))

    def _rebuild_with_room(self, i: int, result) -> None:
        """The simulator built again around body i cut (``result``; None: body i as it is), with
        spare rows for the cuts to come (removed elements stay removed; positions, velocities, time
        carried over)."""
        bodies = list(self.bodies)
        if result is not None:
            bodies[i] = self._cut_body(bodies[i], result)
        removed = [torch.nonzero(~self.alive_elements(k)).flatten() for k in range(self.num_bodies)]
        states = [(self.positions(k), self.velocities(k)) for k in range(self.num_bodies)]
        if result is not None:
            states[i] = (states[i][0][result.parents], states[i][1][result.parents])
        spare = [self.ptr[k + 1] - self.ptr[k] - self.used_nodes[k] for k in range(self.num_bodies)]
        spare[i] = max(MIN_SPARE_NODES, bodies[i].mesh.num_vertices // SPARE_FRACTION,
                       2 * (0 if result is None else result.new_nodes), 2 * spare[i])
        kept = (self.time, self.steps_done, self.removed_mass.clone(), self.last_report, self.last_inversion,
                self.scalpels, self._slits)
        self.__init__(bodies, **self._init_args, spare_nodes=spare)
        for k, ids in enumerate(removed):
            if ids.numel():
                self.model.remove_elements(ids + self.element_ptr[k])
        self._make_system()
        self._surfaces_changed()
        if self._inversion is not None:
            self._inversion = InversionCheck.for_simulator(self)
        with torch.no_grad():
            for k, (x, v) in enumerate(states):
                self.x[self._range(k)] = x
                self.v[self._range(k)] = v
        (self.time, self.steps_done, self.removed_mass, self.last_report, self.last_inversion, self.scalpels,
         self._slits) = kept

    def mesh(self, i) -> Mesh:
        """Body i's mesh as it is now (its rest shape): the elements that remain after removals,
        over its nodes (those cuts added included; a node left with no element stays, unused).
        ``i``: a body index, a ``tm.Body`` of this simulator or a body's name."""
        i = self._body_index(i)
        mesh = self.bodies[i].mesh
        alive = self.alive_elements(i).to(mesh.elements.device)
        return mesh if bool(alive.all()) else type(mesh)(mesh.vertices, mesh.elements[alive], check=False)

    def alive_elements(self, i: int) -> torch.Tensor:
        """``[N_i]`` bool: which elements of body i's mesh remain (``remove_elements``)."""
        i = self._body_index(i)
        return self.model.alive_elements()[self.element_ptr[i]:self.element_ptr[i + 1]]

    def _chain_graphs(self):
        """The step graphs that run several steps with one host synchronisation (CUDA, every CG
        iteration inside the captured step, no prescribed motion, no inversion check), or None."""
        if (self._has_prescribed or self._held is not None or self._inversion is not None
                or (self.tools is not None and self.tools.moves)):
            return None
        graphs = step_graphs_for(self.system, self.options, imposed=False)
        return graphs if graphs is not None and graphs.chainable else None

    def _run_chain(self, graphs, count: int) -> int:
        """Up to ``count`` steps chained on the device; commits the steps before the first failed
        one (if any) and returns how many were committed."""
        summaries = graphs.run_steps(self.x, self.v, count)
        ok = graphs.first_failure(summaries)
        if ok < count:  # (the solution space as the chain found it)
            graphs.rewind()
        if 0 < ok < count:  # the state before the failed step: the good steps again (deterministic)
            summaries = graphs.run_steps(self.x, self.v, ok)
        if ok:
            self._commit(graphs.x.clone(), graphs.v.clone(), ok, graphs.report_of(summaries[ok - 1]), None)
        return ok

    def rebuilt(self, bodies=None, **changes) -> "Simulator":
        """A new simulator with this one's constructor settings, ``changes`` applied (the
        constructor's keyword arguments: ``dt=``, ``cg_max_iter=``, ``tools=``...), over
        ``bodies`` (default: :attr:`initial_bodies`, as first built, before any cut), at the
        bodies' initial state and time 0 (a reset; another material: new bodies). Raises
        ``SceneError`` naming an argument the constructor does not take."""
        known = set(self._init_args) | {"spare_nodes"}
        unknown = sorted(set(changes) - known)
        if unknown:
            raise SceneError(f"rebuilt: unknown settings {unknown}; known: {sorted(known)}")
        args = {**self._init_args, "spare_nodes": self._initial_spare, **changes}
        return Simulator(list(self.initial_bodies if bodies is None else bodies), **args)

    def move_tool(self, tool, position) -> None:
        """Hold a tool at the origin ``position`` ``[3]`` from the next step on, in place of its
        path (a tool driven live, by a viewer's gizmo or a device); its velocity over the next
        step is its move over that step (friction against it follows). ``tool``: its index in
        ``tools`` or its name. Raises ``SceneError`` naming a missing tool or a bad position
        (nothing changes). Steps are not chained while a tool is held."""
        if self.tools is None:
            raise SceneError("move_tool: this simulator has no tools")
        names = [t.name for t in self.tools.tools]
        if isinstance(tool, str):
            if tool not in names:
                raise SceneError(f"move_tool: no tool named {tool!r}; tools: {names}")
            tool = names.index(tool)
        self.tools.hold(tool, position)

    def _range(self, i: int) -> slice:
        if not -self.num_bodies <= i < self.num_bodies:
            raise IndexError(f"body index {i} out of range for {self.num_bodies} bodies")
        i = i % self.num_bodies
        return slice(self.ptr[i], self.ptr[i] + self.used_nodes[i])

    def positions(self, i: int) -> torch.Tensor:
        """Current positions of body i ``[V_i, 3]`` (a view of the packed state)."""
        return self.x[self._range(i)]

    def velocities(self, i: int) -> torch.Tensor:
        """Current velocities of body i ``[V_i, 3]``."""
        return self.v[self._range(i)]

    def displacements(self, i: int) -> torch.Tensor:
        """Current displacements of body i from its rest shape ``[V_i, 3]``."""
        s = self._range(i)
        return self.x[s] - self.model.rest[s]

    def contact_report(self) -> ContactReport:
        """The tools' reactions (force and torque ``[T, 3]``), and per body the nodes in contact
        with a tool or plane and the deepest penetration ``[B]``, at the current state (device
        tensors; ``StepReport.contact`` holds the same at each step's end when there are tools)."""
        return contact_report(self)

    def surface_triangles(self) -> Dict[int, torch.Tensor]:
        """The surface of each tetrahedral body as it is now (cuts and removals included): body
        index -> its boundary triangles ``[F_i, 3]``, outward-wound, in packed node ids (each
        body's in the order of its own ``boundary_faces``)."""
        triangles, body = self.surfaces()
        sizes = torch.bincount(body, minlength=self.num_bodies).tolist()
        parts = torch.split(triangles, sizes)
        return {i: parts[i] for i, b in enumerate(self.bodies) if b.mesh.kind == "tet"}

    def surfaces(self) -> Tuple[torch.Tensor, torch.Tensor]:
        """Every tetrahedral body's surface as it is now, packed: the boundary triangles ``[F, 3]``
        (outward-wound, packed node ids, body after body) and each one's body ``[F]`` (int64). One
        ``boundary_faces`` over all the bodies' elements: the bodies' node ranges are disjoint, so
        a face is on the boundary of the union where it is on its body's."""
        tet = [i for i, b in enumerate(self.bodies) if b.mesh.kind == "tet"]
        if not tet:
            return (torch.zeros(0, 3, dtype=torch.int64, device=self.device),
                    torch.zeros(0, dtype=torch.int64, device=self.device))
        elements = torch.cat([self.mesh(i).elements.to(self.device).long() + self.ptr[i] for i in tet])
        triangles = boundary_faces(elements)
        return triangles, self.segments.node_object[triangles[:, 0]]

    def interpenetration(self) -> torch.Tensor:
        """Per body ``[B]``, how deep its surface is inside other bodies now, measured exactly
        whatever the contact settings (``diagnostics.interpenetration``: for checks that no
        body passed through another; all bodies in one batched distance query)."""
        return interpenetration(self)

    def kinetic_energy(self) -> torch.Tensor:
        """Kinetic energy per body ``[B]``."""
        return 0.5 * self.segments.sum(self.system.mass * self.v * self.v)


def _check_precision(precision, dtype, preconditioner, contact) -> None:
    """Raise SceneError where ``precision`` is unknown or ``"mixed"`` (float64 residuals, float32
    corrections: ``solver.refine``) cannot serve the scene."""
    if precision not in PRECISIONS:
        raise SceneError(f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}")
    if precision != "mixed":
        return
    if dtype != torch.float64:
        raise SceneError(f"precision='mixed' keeps a float64 state and iterates in float32: it needs "
                         f"dtype=torch.float64, got {dtype} (a float32 simulator already iterates in float32)")
    if preconditioner not in ("auto", "none"):
        raise SceneError(f"precision='mixed' runs unpreconditioned float32 corrections: preconditioner must be "
                         f"'auto' or 'none', got {preconditioner!r}")
    if contact is not None:
        raise SceneError("precision='mixed' does not take contact between bodies (yet): use precision='full'")
