"""The solve op family (``csrc/solve/``): whole CG solves over the node graph in one op.

    hooke_node_cg         the start (with rhs) and up to ``count`` iterations of the classic CG
                          with hooke_node_system's product: one persistent kernel on the GPU,
                          bitwise the op-by-op solve
    hooke_node_solve      a whole solve from x0 = 0 (or from the iterate a start left: a warm
                          start) by the pipelined CG (Chronopoulos-Gear: one
                          reduction and one grid barrier an iteration); GPU only: raises
                          NotImplementedError, having done nothing, where it does not fit one
                          wave, or on the CPU
    hooke_node_solve_step the same solve, then euler_update with its solution as dv
    hooke_node_steps      ``steps`` implicit Euler steps in one kernel: each hooke_node_step_rhs,
                          then hooke_node_solve_step

Each op's pure-torch reference (composed from the node-graph and cg families' references: CG's
iterates in exact arithmetic), fake kernel and example, and the group-level wrappers the solver
calls (:func:`system_cg`, :func:`system_solve`). The ops write into their arguments and return
nothing (traceable by torch's functionalization). They take their many tensors packed in lists by
what they are (``system``, ``plan``, ``cg``, ``buffers``, ``step``, ...; the members: :data:`SYSTEM`,
:data:`PLAN`, ...); ``library.pack(name, **named)`` builds a call from the members' names.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import torch

from . import cg as cg_family
from . import library
from .cg import ACTIVE, CGState
from .library import OpDef, contiguous, plan_indices, unchanged
from .node_graph import (
    _ref_hooke_node_step_rhs,
    _ref_hooke_node_system,
    node_graph_of,
    planes_serve,
    row_nodes_of,
    step_rhs_serves,
)
from .segments import ChunkPlan
from .variants import DEFAULT, KernelVariants

__all__ = ["system_cg", "system_cg_serves", "system_solve", "solve_plan", "chunk_slots", "persistent_cg_fits",
           "StepEnd", "StepRhs", "steps_serve", "SOLVE_CHUNK_NODES", "STREAM_CHUNK_NODES"]

# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _ref_start(rhs, free, tol_sq, plan, s, max_iter):
    """CG's start from x0 = 0 on the state ``s`` (as ``CGSolver.start``)."""
    b = rhs if free is None else rhs * free[:, None]
    s.x.zero_()
    s.rhs_sq.copy_(cg_family._object_sums(b * b, plan).to(s.rhs_sq.dtype))
    s.threshold.copy_(s.rhs_sq * tol_sq)
    _ref_begin(b, plan, s, max_iter)


def _ref_from_iterate(rhs, free, plan, s, max_iter):
    """CG's start from the iterate a start left in ``s`` (x0 = s.x kept, r0 = ``rhs`` projected:
    b - A x0; threshold and rhs_sq kept), as ``CGSolver.start`` with x0 leaves it."""
    _ref_begin(rhs if free is None else rhs * free[:, None], plan, s, max_iter)


def _ref_begin(r, plan, s, max_iter):
    """The start's residual ``r`` into ``s``: r.r, the statuses against ``s.threshold``, p = r."""
    s.r.copy_(r)
    s.rr.copy_(cg_family._object_sums(r * r, plan).to(s.rr.dtype))
    s.status.copy_(cg_family._ref_statuses(s.rr, s.threshold, max_iter))
    s.iterations.zero_()
    s.alpha.zero_()
    s.beta.zero_()
    s.p.copy_(s.r)


def _ref_iterations(graph, mass, free, c_mass, c_stiff, node_stiffness, plan, s, max_iter, count):
    """Up to ``count`` CG iterations with hooke_node_system's product, stopping once no object is
    active."""
    for _ in range(int(count)):
        if not bool((s.status == ACTIVE).any()):
            break
        ap, p_dot_ap = _ref_hooke_node_system(s.p, *graph, mass, free, c_mass, c_stiff, node_stiffness)
        cg_family._ref_alpha(p_dot_ap, plan, s)
        cg_family._ref_update(ap, plan, s, max_iter)
        cg_family._ref_direction(plan, s)


#: The values each list argument of the solve ops packs, in order (csrc/solve/schema.cpp).
SYSTEM = ("neighbor", "node_k", "incidences", "row_node", "mass", "free")
PLAN = ("chunk_start", "chunk_object", "object_chunk")
CG = CGState.PACKED
CG_BUFFERS = ("ap", "rr_swap", "work", "sums")
SOLVE_BUFFERS = ("exchange", "sums", "counters")
STEP = ("state_x", "state_v", "x_new", "v_new", "norms", "summary", "end_sums", "end_counter")
LOADS = ("rest", "external", "plane_normals", "plane_offsets", "plane_stiffness")
RHS_OUT = ("u", "rhs")
STEP_COEFS = ("h", "w_coef", "rayleigh_mass", "h_old")


def _state(cg):
    return cg_family._op_state(**dict(zip(CG, cg)))


def _ref_hooke_node_cg(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, max_iter, count, cg, buffers,
                       flags=3):
    *graph, mass, free = system
    chunk_plan = ChunkPlan.from_tensors(*plan)
    s = _state(cg)
    if rhs is not None:
        _ref_start(rhs, free, tol_sq, chunk_plan, s, max_iter)
    _ref_iterations(graph, mass, free, c_mass, c_stiff, node_stiffness, chunk_plan, s, max_iter, count)


def _ref_solve(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, max_iter, cg, from_iterate=False):
    *graph, mass, free = system
    chunk_plan = ChunkPlan.from_tensors(*plan)
    s = _state(cg)
    if from_iterate:
        _ref_from_iterate(rhs, free, chunk_plan, s, max_iter)
    else:
        _ref_start(rhs, free, tol_sq, chunk_plan, s, max_iter)
    _ref_iterations(graph, mass, free, c_mass, c_stiff, node_stiffness, chunk_plan, s, max_iter, max_iter)
    return s


def _ref_hooke_node_solve(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, chunk_nodes, chunk_slots,
                          max_iter, cg, buffers, flags=3, cache_slots=-1, from_iterate=False):
    _ref_solve(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, max_iter, cg, from_iterate)


def _ref_hooke_node_solve_step(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, chunk_nodes, chunk_slots,
                               max_iter, cg, buffers, step, dv_imposed, h, ring, ring_pos, carry, flags=3,
                               cache_slots=-1, h_old=0.0):
    s = _ref_solve(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, max_iter, cg)
    state_x, state_v, x_new, v_new, norms, summary, end_sums, end_counter = step
    cg_family._ref_euler_update(state_x, state_v, s.x, dv_imposed, h, x_new, v_new, *plan, s.status, s.iterations,
                                s.rr, s.rhs_sq, norms, summary, end_sums, end_counter, ring, ring_pos, carry, h_old)


def _ref_hooke_node_steps(system, c_mass, c_stiff, node_stiffness, loads, rhs_out, tol_sq, plan, chunk_nodes,
                          chunk_slots, max_iter, cg, buffers, step, step_coefs, ring, ring_pos, carry, steps, flags=3,
                          cache_slots=-1):
    *graph, mass, _ = system
    rest, external, *planes = loads
    u, rhs = rhs_out
    h, w_coef, rayleigh_mass, *rest_coefs = step_coefs
    h_old = rest_coefs[0] if rest_coefs else 0.0
    state_x, state_v = step[0], step[1]
    for _ in range(int(steps)):
        _ref_hooke_node_step_rhs(state_x, state_v, rest, *graph, mass, external, *planes, h, w_coef, rayleigh_mass, u,
                                 rhs, node_stiffness)
        _ref_hooke_node_solve_step(system, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan, chunk_nodes,
                                   chunk_slots, max_iter, cg, buffers, step, None, h, ring, ring_pos, carry,
                                   h_old=h_old)


def _example(name):
    def example(device, dtype):
        ex = library.Example(device, dtype)
        from .node_graph import OPS as graph_ops

        system_args, _ = graph_ops[0].example(device, dtype)  # hooke_node_system's
        p, *graph, mass, free, c_mass, c_stiff, node_stiffness = system_args
        system = [*graph, mass, free]
        # one object (the example mesh is connected: CG's objects never share an edge), three chunks
        plan = ChunkPlan.from_segments(cg_family.Segments.from_lengths([ex.num_nodes], device=device), 2)
        s = cg_family.CGState.empty(plan, tuple(p.shape), dtype, device)
        rhs = ex.du
        b = plan.segments.num_objects
        if name == "hooke_node_cg":
            return (system, c_mass, c_stiff, node_stiffness, rhs, 1e-8, plan.tensors(), 20, 20, s.packed(),
                    [torch.zeros_like(p), s.rr_swap, s.work, s.sums]), {}
        buffers = [torch.zeros((2, p.shape[0], 4 * p.shape[1]), dtype=dtype, device=device),
                   torch.zeros(4 * plan.num_chunks, dtype=torch.float64, device=device),
                   torch.zeros(3, dtype=torch.int32, device=device)]
        solve = (1e-8, plan.tensors(), SOLVE_CHUNK_NODES, 16, 20, s.packed(), buffers)
        if name == "hooke_node_solve":
            return (system, c_mass, c_stiff, node_stiffness, rhs, *solve), {}
        state_x, state_v = ex.rest + ex.u, 0.1 * ex.du
        step = [state_x, state_v, torch.empty_like(p), torch.empty_like(p), torch.zeros(b, dtype=dtype, device=device),
                torch.zeros((5, b), dtype=torch.float64, device=device),
                torch.zeros(plan.num_chunks, dtype=torch.float64, device=device),
                torch.zeros(b + 1, dtype=torch.int32, device=device)]
        if name == "hooke_node_solve_step":
            return (system, c_mass, c_stiff, node_stiffness, rhs, *solve, step, None, 0.01, None, None, True), {}
        loads = [ex.rest, 9.8 * ex.du, None, None, None]
        rhs_out = [torch.empty_like(p), torch.empty_like(p)]
        return (system, c_mass, c_stiff, None, loads, rhs_out, *solve, step, [0.01, 0.02, 0.1, 0.005], None, None, True,
                2), {}

    return example


#: The pipelined solves' work buffers, and what Chronopoulos-Gear's recurrences hold otherwise
#: than the classic CG of the references (p, alpha, beta): x, r, the statuses, iterations and
#: residual norms are compared.
_PIPELINED_SCRATCH = ("exchange", "sums", "counters", "end_sums", "end_counter", "p", "alpha", "beta")
_SOLVE_MEMBERS = dict(system=SYSTEM, plan=PLAN, cg=CG, buffers=SOLVE_BUFFERS)

OPS = (
    OpDef("hooke_node_cg", _ref_hooke_node_cg, None, differentiable=False, mutates=True,
          example=_example("hooke_node_cg"), scratch=CG_BUFFERS,
          members=dict(system=SYSTEM, plan=PLAN, cg=CG, buffers=CG_BUFFERS)),
    OpDef("hooke_node_solve", _ref_hooke_node_solve, None, differentiable=False, mutates=True,
          example=_example("hooke_node_solve"), scratch=_PIPELINED_SCRATCH, members=_SOLVE_MEMBERS,
          devices=("cuda",)),
    OpDef("hooke_node_solve_step", _ref_hooke_node_solve_step, None, differentiable=False, mutates=True,
          example=_example("hooke_node_solve_step"), scratch=_PIPELINED_SCRATCH,
          members=dict(_SOLVE_MEMBERS, step=STEP), devices=("cuda",)),
    OpDef("hooke_node_steps", _ref_hooke_node_steps, None, differentiable=False, mutates=True,
          example=_example("hooke_node_steps"), scratch=_PIPELINED_SCRATCH,
          members=dict(_SOLVE_MEMBERS, loads=LOADS, rhs_out=RHS_OUT, step=STEP, step_coefs=STEP_COEFS),
          devices=("cuda",)),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Group-level calls: the solver's whole solves
# ---------------------------------------------------------------------------------------------


#: Blocks of the persistent CG kernel resident on each multiprocessor (``kPersistentBlocksPerSM``
#: of csrc/solve/cg_persistent.cuh: its launch bounds guarantee them).
PERSISTENT_BLOCKS_PER_SM = 2


def persistent_cg_fits(device: torch.device, num_chunks: int) -> bool:
    """Whether a CG over ``num_chunks`` chunks runs as one op on ``device``: always on the CPU; on a
    GPU when every chunk has its own resident block of the persistent kernel (one wave). Beyond
    that the blocks loop over chunks with 16 warps per SM, too few to stream memory as well as the
    per-iteration kernels on a full grid, whose launches cost nothing at that size
    (docs/performance-history.md)."""
    if device.type != "cuda":
        return True
    sms = torch.cuda.get_device_properties(device).multi_processor_count
    return num_chunks <= PERSISTENT_BLOCKS_PER_SM * sms


def system_cg_serves(group, inputs=(), num_chunks: int = 0, node_k: Optional[torch.Tensor] = None,
                     variants: KernelVariants = DEFAULT) -> bool:
    """Whether :func:`system_cg` solves ``group``'s systems in one op: over a node graph (the hooke
    tensor form's with ``variants.hooke_matvec`` "node", or a stress-form group's tangent graph
    with ``node_k`` given), ``hooke_node_cg`` compiled, no gradient wanted through ``inputs``, and
    a plan of ``num_chunks`` chunks that fits (:func:`persistent_cg_fits`) on the device of
    ``inputs[0]``."""
    inputs = tuple(inputs)
    return (node_graph_of(group, variants, inputs, "hooke_node_cg", node_k) is not None
            and (not inputs or persistent_cg_fits(inputs[0].device, num_chunks)))


def system_cg(group, mass: torch.Tensor, free: Optional[torch.Tensor], c_mass: float,
              c_stiff: float, node_stiffness: Optional[torch.Tensor], ap: torch.Tensor, rhs: Optional[torch.Tensor],
              tol: float, plan_tensors, cg_state, max_iter: int, count: int,
              node_k: Optional[torch.Tensor] = None, variants: KernelVariants = DEFAULT) -> bool:
    """A whole CG solve of the system of :func:`system_matvec` in one op (``hooke_node_cg``: one
    persistent kernel on the GPU) on ``cg_state`` (``CGState``; its direction ``p`` is the
    product's input): with ``rhs [V, d]`` the start from x0 = 0 (rhs projected on
    ``free``, relative tolerance ``tol``), then up to ``count`` iterations, stopping once no
    object is active;
    ``ap [V, d]``: the product's buffer. Bitwise the op-by-op solve. Only for the hooke tensor form
    over the node graph (``variants.hooke_matvec`` "node") or a tangent graph; returns False, having done nothing,
    for any other group, where the op is missing or a gradient is wanted."""
    ops_ns = torch.ops.tensormass
    s = cg_state
    if not system_cg_serves(group, (s.p, mass, free, node_stiffness, rhs), s.scratch.numel(), node_k, variants):
        return False
    mass, free, node_stiffness, rhs = contiguous(mass, free, node_stiffness, rhs)
    graph = node_graph_of(group, variants, (), "hooke_node_cg", node_k)
    ops_ns.hooke_node_cg([*graph, mass, free], float(c_mass), float(c_stiff), node_stiffness, rhs, float(tol) ** 2,
                         list(plan_tensors), int(max_iter), int(count), s.packed(), [ap, s.rr_swap, s.work, s.sums],
                         variants.solve_flags)
    return True


#: Nodes per chunk of the pipelined solve's plan in each layout (csrc/solve/cg_pipelined.cuh
#: kSolveChunkNodes: two threads a node; kStreamChunkNodes: one).
SOLVE_CHUNK_NODES = 128
STREAM_CHUNK_NODES = 256
_LAYOUT_CHUNK_NODES = {"shared": SOLVE_CHUNK_NODES, "streamed": STREAM_CHUNK_NODES}


def solve_plan(plan, layout: str = "shared"):
    """The chunk plan of :func:`system_solve` in ``layout`` (see ``variants.PIPELINED_LAYOUTS``) for the
    objects of ``plan`` (a ``ChunkPlan``): chunks of at most :data:`SOLVE_CHUNK_NODES` ("shared")
    or :data:`STREAM_CHUNK_NODES` ("streamed") nodes, one GPU block each. Cached on ``plan``."""
    if layout not in _LAYOUT_CHUNK_NODES:
        raise ValueError(f"layout must be one of {sorted(_LAYOUT_CHUNK_NODES)}, got {layout!r}")
    plans = plan.__dict__.setdefault("_solve_plans", {})
    if layout not in plans:
        plans[layout] = type(plan).from_segments(plan.segments, _LAYOUT_CHUNK_NODES[layout])
    return plans[layout]


def chunk_slots(group, plan, incidences: Optional[torch.Tensor] = None) -> int:
    """The most slots of any chunk of ``plan`` (the sum of the node graph's incidences over its
    nodes): the shared memory a block of the pipelined solve needs. ``incidences``: the node
    graph's ``[V]`` (that of the group's plan when None: the hooke tensor form). A host
    synchronisation the first time; cached on the group while the plan and its incidences are the
    same. A group with slots reserved for cuts (``group.reserved_slots``) gets a quarter more, so
    that the chunks a cut fills (its new nodes in spare rows, the nodes next to it) seldom
    outgrow what captured launches were given (:func:`chunk_slots_grew`)."""
    if incidences is None:
        _, _, incidences = plan_indices(group.plan)
    cache = group.__dict__.get("_solve_chunk_slots")
    if cache is not None and cache[0] is plan and unchanged(cache[1], (incidences,)):
        return cache[2]
    value = _chunk_need(plan, incidences)
    if getattr(group, "reserved_slots", 0):
        value += value // 4
    group.__dict__["_solve_chunk_slots"] = (plan, ((incidences,), (incidences._version,), None), value)
    return value


def most_chunk_slots(incidences: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
    """``[]`` int64 on incidences' device: the most slots of a chunk (the sum of ``incidences [V]``
    over its nodes; ``starts``: the chunks' first nodes and the end, ``[C + 1]``, on that device),
    with no host read."""
    prefix = torch.zeros(incidences.numel() + 1, dtype=torch.int64, device=incidences.device)
    torch.cumsum(incidences.long(), 0, out=prefix[1:])
    return (prefix[starts[1:]] - prefix[starts[:-1]]).amax()


def _chunk_need(plan, incidences: torch.Tensor, starts: Optional[torch.Tensor] = None) -> int:
    """The most slots of a chunk of ``plan`` (:func:`most_chunk_slots`; ``starts``: the plan's
    ``chunk_start`` on the device of ``incidences``, when the caller has it); a host read where
    ``incidences`` is on the device."""
    starts = plan.chunk_start.to(incidences.device) if starts is None else starts
    return int(most_chunk_slots(incidences, starts)) if plan.num_chunks else 0


def captured_chunk_slots(group):
    """``(chunk_start, slots)`` of the plan whose chunk slots :func:`chunk_slots` cached for
    ``group`` (the value its captured launches hold), or None where no solve asked yet."""
    cache = group.__dict__.get("_solve_chunk_slots")
    return None if cache is None else (cache[0].chunk_start, cache[2])


def chunk_slots_grew(group, incidences: Optional[torch.Tensor] = None) -> bool:
    """After the node graph of ``group`` gained slots in place (a cut): whether some chunk of the
    plan :func:`chunk_slots` cached now holds more slots than the value cached, a launch
    parameter that captured CUDA graphs hold (they must then be captured again; the value is then
    computed again at the next solve). ``incidences``: the node graph's ``[V]`` now, on the host
    (no device read; the plan's chunk starts read once and kept), or None: the cached device
    tensor, read (a host synchronisation). False where nothing was cached."""
    cache = group.__dict__.get("_solve_chunk_slots")
    if cache is None:
        return False
    plan, ((cached,), _, _), before = cache
    starts = None
    if incidences is not None:  # in node order: in the rows' order where the graph is by rows
        kept = group.__dict__.get("_solve_chunk_starts")
        if kept is None or kept[0] is not plan or kept[1] is not cached:
            rows = row_nodes_of(group, cached)
            kept = (plan, cached, plan.chunk_start.to(incidences.device),
                    None if rows is None else rows.to(incidences.device, torch.int64))
            group.__dict__["_solve_chunk_starts"] = kept
        starts = kept[2]
        incidences = incidences if kept[3] is None else incidences[kept[3]]
    if _chunk_need(plan, cached if incidences is None else incidences, starts) > before:
        group.__dict__.pop("_solve_chunk_slots")  # computed again at the next solve
        return True
    group.__dict__["_solve_chunk_slots"] = (plan, ((cached,), (cached._version,), None), before)
    return False


@dataclasses.dataclass
class StepEnd:
    """The end of an implicit Euler step for the solve that computes its ``dv`` to do in its own
    kernel (:func:`system_solve`: ``hooke_node_solve_step``), as ``euler_update`` does it:
    ``v_new = v + dv (+ dv_imposed)``, ``x_new = x + h v_new`` (``h_old`` not 0: ``x + h_old v +
    (h - h_old) v_new``, the trapezoidal rule's) (all ``[V, d]``; ``carry``: also
    into ``x, v``), each object's ``|v_new|^2`` into ``norms [B]``, the step's summary into
    ``summary [5, B]`` float64 and, with a ``ring [R, 5, B]``, its row ``ring_pos [1]`` (then
    advanced). ``done``: set by the solve that did it (else the caller runs ``euler_update``)."""

    x: torch.Tensor
    v: torch.Tensor
    dv_imposed: Optional[torch.Tensor]
    h: float
    x_new: torch.Tensor
    v_new: torch.Tensor
    norms: torch.Tensor
    summary: torch.Tensor
    ring: Optional[torch.Tensor] = None
    ring_pos: Optional[torch.Tensor] = None
    carry: bool = False
    done: bool = False
    #: the step's right-hand side for the solve to compute first (``StepRhs``; the solve's rhs is
    #: then its output), ``steps`` steps back to back (needs ``carry`` beyond one): one kernel
    #: for all of them (``hooke_node_steps``) where it serves, else nothing is done
    rhs: Optional["StepRhs"] = None
    steps: int = 1
    h_old: float = 0.0


@dataclasses.dataclass
class StepRhs:
    """What the solve needs to compute implicit Euler's right-hand side itself, at the state
    ``StepEnd.x, StepEnd.v`` (``hooke_node_steps``), as :func:`step_rhs` does:
    ``rhs = h (f((x - rest) + w_coef v) + external + contact(x) - Kc(x) (w_coef v) - r_M mass v)``,
    ``u = x - rest`` into ``u [V, d]`` (``rest, external [V, d]``) and, with ``planes`` (a
    ``contact.Planes``), Kc into the solve's ``node_stiffness [V, 3, 3]``, which its products
    then read."""

    rest: torch.Tensor
    external: torch.Tensor
    w_coef: float
    rayleigh_mass: float
    u: torch.Tensor
    planes: Optional[object] = None


class _SolveWork:
    """The pipelined solve's work on one CG state, for one plan, graph (its ``incidences``), and
    ``key`` (the right-hand side's shape and dtype, the layouts to try): the
    exchange rows ``[2, V, 4d]``, the counters, the chunk sums of each layout tried, and what the
    tries found (``layout``: the one that ran; ``misfits``: those that did not fit, not tried
    again: each try is a launch attempt, on every step)."""

    def __init__(self, plan, incidences: torch.Tensor, key, rhs: torch.Tensor):
        self.plan, self.incidences, self.key = plan, incidences, key
        self.exchange = torch.zeros((2, rhs.shape[0], 4 * rhs.shape[1]), dtype=rhs.dtype, device=rhs.device)
        self.counters = torch.zeros(3, dtype=torch.int32, device=rhs.device)
        self.sums = {}
        self.end_work = {}
        self.layout = None
        self.misfits = set()

    def sums_of(self, layout: str, plan) -> torch.Tensor:
        if layout not in self.sums:
            self.sums[layout] = torch.zeros(4 * plan.num_chunks, dtype=torch.float64, device=self.exchange.device)
        return self.sums[layout]

    def end_work_of(self, layout: str, plan):
        """The step end's chunk sums ``[K]`` float64 and object counters ``[B + 1]`` int32 (zero
        between calls) in ``layout``."""
        if layout not in self.end_work:
            device = self.exchange.device
            self.end_work[layout] = (torch.zeros(plan.num_chunks, dtype=torch.float64, device=device),
                                     torch.zeros(plan.object_chunk.numel(), dtype=torch.int32, device=device))
        return self.end_work[layout]


def system_solve(group, mass: torch.Tensor, free: Optional[torch.Tensor], c_mass: float, c_stiff: float,
                 node_stiffness: Optional[torch.Tensor], rhs: torch.Tensor, tol: float, plan, cg_state,
                 max_iter: int, node_k: Optional[torch.Tensor] = None, step_end: Optional[StepEnd] = None,
                 variants: KernelVariants = DEFAULT, from_iterate: bool = False) -> bool:
    """A whole CG solve from x0 = 0 of :func:`system_matvec`'s system (rhs ``[V, d]`` projected on
    ``free``; relative tolerance ``tol``; at most ``max_iter`` iterations) by the pipelined CG
    (``hooke_node_solve``: Chronopoulos-Gear, one reduction and one grid barrier an iteration, one
    persistent kernel) into ``cg_state`` (a ``CGState`` over ``plan``: x, r, p, the per-object
    scalars and statuses), in the first of ``variants.pipelined_layouts`` that fits. CG's iterates
    in exact arithmetic, rounded differently from :func:`system_cg`'s. Returns False, having done
    nothing, where it does not serve: not a CUDA tensor, no node graph
    (``node_k``: as in :func:`system_matvec`), a gradient wanted, or a system too large for one
    wave of the kernel in every layout. ``step_end``: the implicit Euler step's end, done in the
    same kernel (``hooke_node_solve_step``; its ``done`` set) where ``variants.fused_step_end``; with
    its ``rhs`` (a :class:`StepRhs`), ``rhs`` is this solve's output: its ``steps`` steps, each
    its right-hand side, solve and end, in one kernel (``hooke_node_steps``) where
    :func:`steps_serve`, else nothing is done. ``from_iterate``: the solve goes on from the
    iterate a start left in ``cg_state`` (``CGSolver.start`` from a guess x0: ``rhs`` is its
    residual b - A x0, ``cg_state.r``; its threshold, relative to b, is kept and ``tol`` unused):
    CG from x0, a warm start; no ``step_end``."""
    if from_iterate and step_end is not None:
        raise ValueError("system_solve: a solve from the iterate (from_iterate) takes no step_end")
    s = cg_state
    if not rhs.is_cuda:
        return False
    if step_end is not None and step_end.rhs is not None and not steps_serve(group, node_stiffness, node_k, step_end,
                                                                               variants):
        return False
    graph = node_graph_of(group, variants, (s.p, mass, free, node_stiffness, rhs), "hooke_node_solve", node_k)
    if graph is None:
        return False
    layouts = variants.pipelined_layouts
    key = (tuple(rhs.shape), rhs.dtype, layouts)
    work = s.__dict__.get("_solve_work")
    if work is None or work.plan is not plan or work.incidences is not graph[2] or work.key != key:
        work = s.__dict__["_solve_work"] = _SolveWork(plan, graph[2], key, rhs)
    mass, free, node_stiffness, rhs = contiguous(mass, free, node_stiffness, rhs)
    for layout in ((work.layout,) if work.layout is not None else layouts):
        if layout in work.misfits:
            continue
        layout_plan = solve_plan(plan, layout)
        slots = chunk_slots(group, layout_plan, graph[2]) if layout == "shared" else 0
        system = ([*graph, mass, free], float(c_mass), float(c_stiff))
        solve = (float(tol) ** 2, layout_plan.tensors(), _LAYOUT_CHUNK_NODES[layout], slots, int(max_iter),
                 s.packed(), [work.exchange, work.sums_of(layout, layout_plan), work.counters])
        kernel = (variants.solve_flags, variants.stream_cache_slots)
        try:
            if step_end is not None and step_end.rhs is not None:
                e, in_solve = step_end, step_end.rhs
                planes = [None] * 3 if in_solve.planes is None else list(contiguous(
                    in_solve.planes.normals, in_solve.planes.offsets, in_solve.planes.stiffness))
                torch.ops.tensormass.hooke_node_steps(
                    *system, node_stiffness, [in_solve.rest, in_solve.external, *planes], [in_solve.u, rhs], *solve,
                    _step_list(e, work.end_work_of(layout, layout_plan)),
                    [float(e.h), float(in_solve.w_coef), float(in_solve.rayleigh_mass), float(e.h_old)], e.ring,
                    e.ring_pos,
                    bool(e.carry), int(e.steps), *kernel)
                e.done = True
            elif step_end is not None and variants.fused_step_end:
                e = step_end
                torch.ops.tensormass.hooke_node_solve_step(
                    *system, node_stiffness, rhs, *solve, _step_list(e, work.end_work_of(layout, layout_plan)),
                    e.dv_imposed, float(e.h), e.ring, e.ring_pos, bool(e.carry), *kernel, float(e.h_old))
                e.done = True
            else:
                torch.ops.tensormass.hooke_node_solve(*system, node_stiffness, rhs, *solve, *kernel, bool(from_iterate))
            ran = True
        except NotImplementedError:  # does not fit one wave in this layout: nothing was changed
            ran = False
        if ran:
            work.layout = layout
            return True
        work.layout = None
        work.misfits.add(layout)
    return False


def _step_list(e: StepEnd, end_work):
    """The solve ops' ``step`` list of ``e`` with its work (end sums, end counter)."""
    return [e.x, e.v, e.x_new, e.v_new, e.norms, e.summary, *end_work]


def steps_serve(group, node_stiffness: Optional[torch.Tensor], node_k: Optional[torch.Tensor],
                step_end: StepEnd, variants: KernelVariants = DEFAULT) -> bool:
    """Whether ``hooke_node_steps`` serves these steps: ``variants.solve_step_rhs`` and
    ``variants.fused_step_end`` (its solve ends each step), the hooke tensor
    form's own node graph (``node_k`` None; :func:`step_rhs_serves`), a contact stiffness buffer
    exactly where there are planes (3-D, of the state's dtype and device), no imposed velocity,
    and ``carry`` where the steps are more than one. (The solve may still not fit the device:
    :func:`system_solve` says.)"""
    e = step_end
    if (e.rhs.planes is None) != (node_stiffness is None) or not planes_serve(e.rhs.planes, e.x, node_stiffness):
        return False
    return (variants.solve_step_rhs and variants.fused_step_end and hasattr(torch.ops.tensormass, "hooke_node_steps")
            and node_k is None and e.dv_imposed is None and (e.carry or e.steps == 1) and e.steps >= 1
            and step_rhs_serves(group, (e.x, e.v, e.rhs.rest, e.rhs.external), variants))
