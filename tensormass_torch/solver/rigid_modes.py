"""A coarse correction over each body's rigid motions, beside block Jacobi (``preconditioner="rigid"``).

Why: contact pairs join bodies by penalties far stiffer than a body's nodes (``docs/contact.md``).
Block Jacobi brings each stiff row back to the others' scale, but not the motions those rows
do not resist: a stack of blocks moving together, each block turning on the one below. There the
scaled matrix is near singular, and CG spends its iterations finding them one contact at a time.
These motions are close to rigid per body, six per body: a space small enough to solve directly.

The coarse space: Z ``[V d, 6 B]``, each body's three translations and three rotations about its
centre of mass (the rotations' lever arms divided by the body's radius of gyration, so that the
six columns have comparable norms), zero on fixed nodes. Its matrix

    E = Z^T A Z = c_M Z^T M Z + c_K Z^T N Z + sum over pairs (J Z)^T M_p (J Z)

(M the masses, N the planes' and tools' node stiffness, M_p a pair's a u u^T + b P_t, J its
vertex-minus-closest-point operator) leaves out the bodies' elastic stiffness: a rigid motion
does not strain a body, so Z^T K Z is zero at rest (tested) and small when it is deformed, and
leaving it out saves six products of the elastic operator a load.

The preconditioner, the additive two-level form: block Jacobi (B, each node's diagonal block)
plus the coarse solve, weighted by w = 1/2 (the two overlap on the coarse space;
``docs/preconditioners.md``):

    z = M^-1 r = B^-1 r + w Z E^-1 Z^T r.

It is symmetric positive definite when E is, and E is a Galerkin product of the step's matrix.
The CG applies B^-1 inside its update (``preconditioner.BlockJacobi``) and :meth:`correct` adds
the coarse part; its stopping rule stays on r.B^-1 r. Loaded on a ``JacobiScaling`` instead, it
is the same preconditioner of the scaled system A' = S^T A S (S = L^-T per node, B = L L^T) that
the CG then runs on: with Z' = S^-1 Z (so that Z'^T A' Z' = E), M'^-1 = I + w Z' E^-1 Z'^T,
and S M'^-1 S^T = M^-1: the same iterates in exact arithmetic (x = S y).

E is not solved whole. The bodies are ordered and taken in groups of ``group_bodies``; E is
replaced by its principal blocks over the groups (each one symmetric positive definite, as
principal blocks of E are): the pairs between two groups keep their diagonal terms and drop their
coupling. The order (``grouping``) puts the bodies the step's pairs join most next to each other
(``"contact"``: clusters by heavy-edge matching on the bodies' contact graph, along a Morton curve
of their centres), or follows the Morton curve alone (``"morton"``): a stack of blocks is one
cluster, where the curve's groups, small cubes of a pile, cut it into three or four and the
correction misses its blocks' motions against each other. Each group's block is inverted once per
load, in float64.

An iteration applies the coarse part as three ops of the multigrid family: the restriction Z^T
(a body's sum over its nodes), the groups' inverses (a block-sparse product, a block row a body)
and the prolongation Z, which also adds what z holds (in the step's CG, on a ``BlockJacobi``, the
prolongation is no pass of its own: the CG's direction p = z + w Z y + beta p adds it at each node,
``cg_direction``'s coarse term, and r.z = r.B^-1 r + w (Z^T r) . y comes from the coarse vectors,
``cg_coarse_beta``: :meth:`coarse_terms`). Z_i = N_i [I | -[a_i]x] is formed at each
node from N (the identity on free nodes, zero on fixed ones: one value a node; on a
``JacobiScaling``, its inverse S^-1, 3 x 3) and the lever arm a, 4 or 12 values a node where a
stored basis reads 18.
Fixed shapes, no host synchronisation, deterministic sums: a CUDA graph replays it with each
load's values, in the buffers kept here. Whether the iterations it saves pay for it is measured,
not assumed: ``"auto"`` takes it for the solves body contact pairs join, where it was measured
faster than block Jacobi alone at rest, over a pile's run and even on a tumbling pile, and not
elsewhere (``docs/preconditioners.md``, "Measured 2026-12-03").
"""
from __future__ import annotations

from typing import Optional

import torch

from ..mesh.topology import add_at
from ..ops.cg import CoarseTerm
from ..ops.multigrid import BsrMatrix, bsr_gemv, match_clusters, rigid_prolong, rigid_restrict
from ..ops.segments import Segments

#: Bodies per group of the coarse solve (its matrices are 6 x this on a side).
GROUP_BODIES = 32
#: The coarse correction's weight w (z = r + w Z' E^-1 Z'^T r).
WEIGHT = 0.5
#: Loads of new products between two computations of the bodies' part (their modes, groups and
#: own blocks; 1: every load). In between it is lagged: the scaling is the load's, the bodies'
#: part the last one computed, and the pairs' part the last load's too where the correction is
#: made with ``lag_pairs`` (its coarse inverses kept whole; see :meth:`RigidModeCorrection.load`).
#: The step lags it only while the bodies' contacts hold still (``solver.implicit_euler._rigid``),
#: so the lag costs no iterations where they change and saves the coarse solve's load at rest.
REFRESH = 16
#: The most the number of contact pairs may change (relative) for the bodies' part to stay lagged:
#: the groups follow the pairs (a pile that was found without pairs, then lands, is grouped again).
LAG_PAIRS_CHANGE = 0.1
#: Nodes a lane group of the restriction sums (a body's nodes are taken in runs of this many, then
#: the runs' sums added per body): enough lanes for the GPU where a group a body left it idle.
RESTRICTION_RUN = 64
#: Morton code bits per axis of the bodies' order.
_MORTON_BITS = 10
#: How the bodies are taken into the coarse solve's groups: along the Morton curve of their centres,
#: or with the bodies the step's pairs join most together first (:func:`contact_groups`).
GROUPINGS = ("contact", "morton")


class BodySums:
    """Per-body sums of per-node values in float64: one ``segment_reduce`` over the bodies' node
    ranges (``segments``), each body summed in node order (deterministic), with no host
    synchronisation (a load runs between a step's captured iterations without draining the
    device's queue; the ranges are checked against the nodes once, here)."""

    def __init__(self, segments: Segments, like: torch.Tensor):
        lengths = segments.lengths.to(like.device)
        if int(lengths.sum()) != like.shape[0]:
            raise ValueError(f"the bodies' segments hold {int(lengths.sum())} nodes, the positions {like.shape[0]}")
        self.segments = segments
        self.lengths = lengths
        self.num_nodes = like.shape[0]
        self.device = like.device

    def sums(self, values: torch.Tensor) -> torch.Tensor:
        """Each body's sums ``[B, n]`` float64 of per-node ``values [V, n]``."""
        return torch.segment_reduce(values.to(torch.float64), "sum", lengths=self.lengths, unsafe=True)


def lever_arms(x: torch.Tensor, mass: torch.Tensor, sums: BodySums) -> tuple:
    """(arms ``[V, 3]``, centres ``[B, 3]``): each node's lever arm about its body's centre of mass
    divided by the body's radius of gyration (so that the rotations' modes and the translations'
    have comparable norms), and the centres. A massless body turns about its nodes' mean."""
    index = sums.segments.node_object.to(x.device)
    tiny = torch.finfo(torch.float64).tiny
    per_body = sums.sums(torch.cat([mass[:, None], mass[:, None] * x, x], 1))  # [B, 7]
    body_mass = per_body[:, 0]
    counts = sums.lengths.clamp(min=1).to(torch.float64)
    centres = torch.where(body_mass[:, None] > 0, per_body[:, 1:4] / body_mass.clamp(min=tiny)[:, None],
                          per_body[:, 4:7] / counts[:, None]).to(x.dtype)
    arm = x - centres[index]
    spread = sums.sums((mass * (arm * arm).sum(-1))[:, None])[:, 0]
    gyration = torch.sqrt(spread / body_mass.clamp(min=tiny))
    gyration = torch.where(gyration > tiny, gyration, torch.ones_like(gyration)).to(x.dtype)
    return arm / gyration[index, None], centres


def modes_of(arms: torch.Tensor) -> torch.Tensor:
    """The six modes ``[6, V, 3]`` at nodes of lever ``arms [V, 3]``: the translations, then
    e_x x a, e_y x a, e_z x a (Z_i = [I | -[a_i]x]), one stack of 18 per-node components."""
    ax, ay, az = arms.unbind(-1)
    zero, one = torch.zeros_like(ax), torch.ones_like(ax)
    return torch.stack([one, zero, zero, zero, one, zero, zero, zero, one,
                        zero, -az, ay, az, zero, -ax, -ay, ax, zero]).view(6, 3, -1).transpose(1, 2)


def rigid_modes(x: torch.Tensor, mass: torch.Tensor, sums: BodySums) -> tuple:
    """(modes ``[6, V, 3]``, centres ``[B, 3]``): at each node its body's three translations and
    three rotations about the body's centre of mass (:func:`lever_arms`, :func:`modes_of`).
    ``sums``: the bodies' :class:`BodySums`."""
    arms, centres = lever_arms(x, mass, sums)
    return modes_of(arms), centres


def _morton_codes(centres: torch.Tensor) -> torch.Tensor:
    """``[B]`` int64: each of ``centres [B, dim]``'s cell on a grid of 2^10 a side over their box,
    its bits interleaved (the position along a Morton curve)."""
    dim = centres.shape[1]
    low = centres.amin(0)
    span = (centres.amax(0) - low).amax().clamp(min=torch.finfo(centres.dtype).tiny)
    top = (1 << _MORTON_BITS) - 1
    cells = ((centres - low) / span * top).round().to(torch.int64).clamp(0, top)  # [B, dim]
    bits = torch.arange(_MORTON_BITS, device=centres.device)
    axes = torch.arange(dim, device=centres.device)
    return (((cells[:, :, None] >> bits) & 1) << (dim * bits + axes[:, None])).sum((1, 2))


def _groups_of(order: torch.Tensor, group_bodies: int) -> tuple:
    """(group ``[B]``, slot ``[B]``, groups) of the bodies taken ``group_bodies`` at a time in
    ``order [B]`` (body ids)."""
    count = order.numel()
    rank = torch.empty_like(order)
    rank[order] = torch.arange(count, device=order.device)
    return rank // group_bodies, rank % group_bodies, -(-count // group_bodies)


def morton_groups(centres: torch.Tensor, group_bodies: int) -> tuple:
    """(each body's group ``[B]``, its slot in the group ``[B]``, the number of groups): the
    bodies in the order of a Morton curve through their ``centres [B, 3]`` (ties by index), taken
    ``group_bodies`` at a time."""
    return _groups_of(torch.argsort(_morton_codes(centres), stable=True), group_bodies)


def _edge_keys(u: torch.Tensor, v: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``[E]`` int64, distinct and >= 0: the matching's priority of the edges (u, v) ``[E]`` each:
    their ``weight`` (saturating at 2^16 - 1), then a hash of their two ends, then their index.
    The hash (an integer mix of 32 bits, no int64 overflow) breaks a path of equal weights into
    local maxima about every third edge, where an order by index would match one edge a round."""
    x = (u * 40503 + v) & 0xFFFFFFFF
    x = (((x >> 16) ^ x) * 0x45D9F3B) & 0xFFFFFFFF
    x = (((x >> 16) ^ x) * 0x45D9F3B) & 0xFFFFFFFF
    x = (x >> 16) ^ x
    index = torch.arange(u.numel(), device=u.device)
    return (weight.clamp(max=(1 << 16) - 1) << 47) | ((x & 0xFFFF) << 31) | index


def contact_clusters(pair_objects: torch.Tensor, bodies: int, most: int, rounds: Optional[int] = None) -> torch.Tensor:
    """``[B]`` int64: a label for each of ``bodies`` bodies (its cluster's smallest body), the
    bodies that the contact pairs join most (``pair_objects [P, 2]``: each pair's two bodies; an
    edge's weight is the number of pairs between its two bodies) in clusters of at most ``most``
    bodies. Heavy-edge matching, as graph partitioners coarsen (``ops.multigrid.match_clusters``):
    ``rounds`` times, each cluster offers its heaviest edge to a cluster that fits beside it (ties
    by :func:`_edge_keys`' hash), and two clusters that offer each other one edge merge (None:
    2 log2(most) + 2 rounds, enough for clusters to double up to ``most`` where a round matches a
    third of a chain's links). No host synchronisation: the edges are a pair long (one a run of
    equal pairs, the others loops that never join)."""
    if rounds is None:
        rounds = 2 * max(1, (most - 1).bit_length()) + 2
    device = pair_objects.device
    if pair_objects.numel() == 0 or most < 2:
        return torch.arange(bodies, device=device)
    # the edges, without a host read of their number: the pairs' codes sorted, an edge at the first
    # pair of each run, its weight the run's length; every other slot (and a pair within one
    # body, self-contact) a loop (0, 0), which never joins
    lo, hi = pair_objects.amin(1), pair_objects.amax(1)
    none = bodies * bodies
    codes = torch.sort(torch.where(lo != hi, lo * bodies + hi, none)).values  # [P]
    count = codes.numel()
    index = torch.arange(count, device=device)
    first = torch.cat([codes.new_ones(1, dtype=torch.bool), codes[1:] != codes[:-1]])
    later = torch.cummin(torch.where(first, index, count).flip(0), 0).values.flip(0)  # the next run's start, from p on
    weight = torch.cat([later[1:], later.new_full((1,), count)]) - index
    real = first & (codes != none)
    u, v = torch.where(real, codes // bodies, 0), torch.where(real, codes % bodies, 0)
    return match_clusters(_edge_keys(u, v, weight), torch.stack([u, v], 1), bodies, most, rounds)


def contact_groups(centres: torch.Tensor, pair_objects: torch.Tensor, group_bodies: int) -> tuple:
    """As :func:`morton_groups`, with the bodies that the contact pairs (``pair_objects [P, 2]``)
    join most next to each other: :func:`contact_clusters` of at most ``group_bodies`` bodies,
    ordered along the Morton curve by their first body, each cluster's bodies along it. A cluster
    may still straddle two groups (its coupling there is dropped, as the Morton groups drop theirs);
    on stacks of blocks the Morton groups cut every stack, these one stack in three or four."""
    count = centres.shape[0]
    code = _morton_codes(centres)
    label = contact_clusters(pair_objects, count, group_bodies)
    first = torch.full_like(code, torch.iinfo(torch.int64).max).scatter_reduce(0, label, code, "amin")
    by_body = torch.argsort(code, stable=True)
    cluster_key = first[label] * count + label  # (the codes have 30 bits, the labels < B)
    order = by_body[torch.argsort(cluster_key[by_body], stable=True)]
    return _groups_of(order, group_bodies)


def _gram(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a^T b ``[N, 6, 6]`` for ``a, b [N, 3, 6]``, elementwise (batched GEMMs of such small
    matrices run far below the memory's speed on the GPU)."""
    return (a[:, :, :, None] * b[:, :, None, :]).sum(1)


def own_blocks(arms: torch.Tensor, node_weights: torch.Tensor, sums: BodySums,
               free: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Each body's own block of the coarse matrix without pairs, Z_b^T W Z_b ``[B, 6, 6]`` float64
    (Z_i = [I | -A_i] at nodes of lever ``arms [V, 3]`` (:func:`lever_arms`; A_i = [a_i]x), zero
    where ``free [V, 1]`` is 0; ``node_weights [V, 3, 3]``: W = c_M m_i I + c_K N_i, symmetric).
    A node's block [[W, -W A], [A W, -A W A]] from two cross products a row (W A's rows are W's
    rows x a; -A W A's columns are W A's columns x a), summed per body in one reduction (in the
    dtype of the nodes: a body's few thousand terms)."""
    weights = node_weights if free is None else node_weights * free[:, :, None]
    lever = arms[:, None, :].expand_as(weights)
    wa = torch.linalg.cross(weights, lever, dim=-1)  # W A [V, 3, 3]
    awa = torch.linalg.cross(wa.transpose(1, 2), lever, dim=-1).transpose(1, 2)  # -A W A
    per_node = torch.cat([torch.cat([weights, -wa], 2), torch.cat([-wa.transpose(1, 2), awa], 2)], 1)  # [V, 6, 6]
    lengths = sums.lengths
    return torch.segment_reduce(per_node.reshape(-1, 36), "sum", lengths=lengths, unsafe=True).view(-1, 6, 6).to(
        torch.float64)


def group_matrices(own: torch.Tensor, arms: torch.Tensor, group: torch.Tensor, slot: torch.Tensor, groups: int,
                   size: int, pairs=None, pair_matrices: Optional[torch.Tensor] = None,
                   free: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The coarse matrix E = Z^T A Z without the elastic part, as its principal blocks over the
    groups ``[groups, 6 size, 6 size]`` float64 (body b in block ``group[b]`` at ``slot[b]``; slots
    without a body are zero).

    ``own [B, 6, 6]``: the bodies' own blocks without pairs (:func:`own_blocks`); ``arms [V, 3]``
    and ``free [V, 1]`` (or None): Z (:func:`modes_of`, zero on fixed nodes), formed at the pairs'
    nodes only; ``pairs``: ``ContactPairs`` (or None) with ``pair_matrices [P, 3, 3]`` their M_p. A pair
    between two groups adds its terms on each body's own block and drops its coupling; a pair
    within one body (self-contact) adds its coupling to the body's own block."""
    place = group * size * size + slot * size + slot  # each body's own block (one a body)
    matrices = own.new_zeros(groups * size * size, 6, 6).index_copy_(0, place, own)
    if pairs is not None and len(pairs):
        nodes = pairs.nodes
        modes = modes_of(arms[nodes.reshape(-1)])  # [6, 4 P, 3]
        if free is not None:
            modes = modes * free[nodes.reshape(-1)]
        modes = modes.view(6, -1, 4, 3)  # the pair's vertex and its triangle's corners
        coefficients = pairs._coefficients().to(modes.dtype)  # [P, 4]: 1, -w
        vertex = modes[:, :, 0].permute(1, 2, 0)  # [P, 3, 6]
        triangle = sum(coefficients[:, i, None, None] * modes[:, :, i].permute(1, 2, 0) for i in (1, 2, 3))
        mp = pair_matrices.to(modes.dtype)

        def weighted(g):
            return (mp[:, :, :, None] * g[:, None, :, :]).sum(2)  # M_p g [P, 3, 6]

        mv, mt = weighted(vertex), weighted(triangle)
        bv, bt = pairs.objects[:, 0], pairs.objects[:, 1]
        inside = (group[bv] == group[bt])[:, None, None]
        vt = torch.where(inside, _gram(vertex, mt), 0.0)
        cross_vt = group[bv] * size * size + slot[bv] * size + slot[bt]
        cross_tv = group[bv] * size * size + slot[bt] * size + slot[bv]
        index = torch.cat([place[bv], place[bt], cross_vt, cross_tv])
        blocks = torch.cat([_gram(vertex, mv), _gram(triangle, mt), vt, vt.transpose(1, 2)])
        matrices = add_at(matrices, index, blocks.to(torch.float64))
    return matrices.view(groups, size, size, 6, 6).transpose(2, 3).reshape(groups, 6 * size, 6 * size)


class RigidModeCorrection:
    """The coarse correction w Z E^-1 Z^T r ``[V, 3]`` beside block Jacobi (see the module) as three
    ops and a sum: the restriction Z^T r (``ops.multigrid.rigid_restrict`` over runs of a body's
    nodes, the runs then summed per body), the groups' inverses (``ops.multigrid.bsr_gemv``: a
    block row a body, a 6 x 6 block for each body of its group) and the prolongation adding to z
    (``ops.multigrid.rigid_prolong``: a node an item). Z_i = N_i [I | -[a_i]x] is formed at each
    node from N (zero on fixed nodes) and the lever arm a, never stored. Loaded on a
    ``BlockJacobi`` (the step's) N is the identity and the CG takes :attr:`inverse_blocks` and
    :meth:`correct`; on a ``JacobiScaling``, N = S^-1 and :meth:`__call__` is the scaled system's
    preconditioner. Its buffers keep their storage from load to load while the shapes do (a CUDA
    graph captured over the iterations replays with each load's values). ``group_bodies``,
    ``grouping``, ``weight``: the coarse solve's (module); ``refresh``: :data:`REFRESH`'s;
    ``lag_pairs``: where a load lags the bodies' part, keep the last load's coarse inverses whole
    (False: their pairs' part made again at every load)."""

    def __init__(self, group_bodies: int = GROUP_BODIES, weight: float = WEIGHT, grouping: str = "contact",
                 refresh: int = REFRESH, lag_pairs: bool = True):
        if group_bodies < 1:
            raise ValueError(f"group_bodies must be at least 1, got {group_bodies}")
        if refresh < 1:
            raise ValueError(f"refresh must be at least 1, got {refresh}")
        if not weight > 0:
            raise ValueError(f"weight must be positive, got {weight}")
        if grouping not in GROUPINGS:
            raise ValueError(f"grouping must be one of {GROUPINGS}, got {grouping!r}")
        self.group_bodies = int(group_bodies)
        self.weight = float(weight)
        self.grouping = grouping
        self.refresh = int(refresh)
        self.lag_pairs = bool(lag_pairs)
        self._age = 0  # loads of new products since the bodies' part was computed
        self._lag = None  # the ``lag`` key it was computed under
        self._lag_pairs = 0  # the number of pairs it was computed with
        self.node_inverse: Optional[torch.Tensor] = None  # N = S^-1 [V, 3, 3] or the free mask [V] (N = I)
        self.arms: Optional[torch.Tensor] = None  # a [V, 3]
        self.inverses: Optional[BsrMatrix] = None  # the groups' E^-1 [6 B, 6 B]
        self._run_ptr: Optional[torch.Tensor] = None  # [R + 1] int32: the restriction's runs of nodes
        self._runs: Optional[torch.Tensor] = None  # [B] each body's runs
        self._node_body: Optional[torch.Tensor] = None  # [V] int32
        self._body_ptr: Optional[torch.Tensor] = None  # [B + 1] int64
        self._sums: Optional[BodySums] = None
        self._kept = None  # (key, arms, free, group, slot, groups, own blocks, filled, columns) of load's ``kept``
        self._blocks: Optional[torch.Tensor] = None  # a BlockJacobi's B^-1 [V, 3, 3] (None: a JacobiScaling's)
        self._scaling = None  # the BlockJacobi or JacobiScaling it was loaded on

    def load(self, x: torch.Tensor, mass: torch.Tensor, segments: Segments, free: Optional[torch.Tensor],
             node_weights, scaling, pairs=None, pair_matrices: Optional[torch.Tensor] = None,
             kept=None, lag=None, renew: bool = False) -> "RigidModeCorrection":
        """Build the correction at positions ``x [V, 3]`` for the bodies of ``segments`` with node
        masses ``mass [V]``, free-node mask ``free [V, 1]`` (or None), ``node_weights [V, 3, 3]``
        (c_M m_i I + c_K N_i, or a function that returns them: called only where the bodies' part
        is computed), block Jacobi loaded (``scaling``: a ``BlockJacobi``, N = I and the CG
        applies B^-1; or a ``JacobiScaling``, Z' = S^-1 Z) and the ``pairs`` with their
        ``pair_matrices [P, 3, 3]`` (c_K k u u^T + damping, or None).
        ``kept``: a key that promises x, mass, free and the node weights are those of the last
        load with the same key (a step's contact rounds: only the pairs and the scaling change),
        whose modes, groups and own blocks are then reused; None: computed afresh. ``lag``: a key
        that promises the node weights' parts that do not change from step to step (the step's
        coefficients); under the same key the bodies' part of the last computation is reused for
        up to ``refresh`` - 1 loads of new products, while the number of pairs stays within
        ``LAG_PAIRS_CHANGE`` of the one it was computed with, and with ``lag_pairs`` the last
        load's coarse inverses whole, its pairs' part too (the correction stays symmetric
        positive definite with any modes and any positive definite coarse blocks: lagged, they
        only match the bodies' present rigid motions, node weights and pairs less exactly). None:
        never lagged. ``renew``: compute the bodies' part afresh at this load whatever the lag (later
        loads under the same ``lag`` key may then lag it). No host synchronisation (but where the
        bodies' node ranges are checked, the first load)."""
        if self._sums is None or self._sums.segments is not segments or self._sums.device != x.device \
                or self._sums.num_nodes != x.shape[0]:
            self._sums, self.node_inverse, self._kept = BodySums(segments, x), None, None
        size, bodies = self.group_bodies, segments.num_objects
        fresh = kept is None or self._kept is None or self._kept[0] != kept
        count = len(pairs) if pairs is not None else 0
        lagged = False
        if fresh and not renew and lag is not None and self._kept is not None and lag == self._lag \
                and self._age + 1 < self.refresh \
                and abs(count - self._lag_pairs) <= LAG_PAIRS_CHANGE * max(self._lag_pairs, 1):
            self._age += 1
            self._kept = (kept, *self._kept[1:])
            fresh, lagged = False, True
        elif fresh:
            self._age, self._lag, self._lag_pairs = 0, lag, count
            arms, centres = lever_arms(x, mass, self._sums)
            if self.grouping == "contact" and pairs is not None and len(pairs):
                group, slot, groups = contact_groups(centres, pairs.objects, size)
            else:
                group, slot, groups = morton_groups(centres, size)
            own = own_blocks(arms, node_weights() if callable(node_weights) else node_weights, self._sums, free)
            # each body's row of its group's inverse takes a block for each slot of the group, its
            # columns the slots' bodies; the ranks group * c + slot are 0 .. B - 1, so the slots
            # past them are the empty ones (their blocks zero: the inverse keeps the padding's
            # identity apart)
            members = torch.zeros(groups * size, dtype=torch.int64, device=x.device)
            members[group * size + slot] = torch.arange(bodies, device=x.device)
            filled = (torch.arange(groups * size, device=x.device).view(groups, size) < bodies)[group]  # [B, c]
            columns = members.view(groups, size)[group].to(torch.int32).reshape(-1)  # [B c]
            self._kept = (kept, arms, free, group, slot, groups, own, filled[:, :, None, None], columns)
        _, arms, kept_free, group, slot, groups, own, filled, columns = self._kept
        node_inverse = self._take_scaling(scaling, x, free)
        if lagged and self.lag_pairs and self.node_inverse is not None \
                and self.node_inverse.shape == node_inverse.shape and self.node_inverse.dtype == x.dtype:
            # the last load's coarse inverses kept whole, its pairs' part too: E = Z^T A Z does not
            # depend on the scaling, and what it lags is the pairs' change since that load (their
            # number within LAG_PAIRS_CHANGE, over contacts that held still)
            self.node_inverse.copy_(node_inverse)
            return self
        matrices = group_matrices(own, arms, group, slot, groups, size, pairs, pair_matrices, kept_free)
        # slots past the last body, and coarse unknowns no free node carries: the identity there
        # (a rigid motion of fixed nodes is no motion); a relative 1e-10 on the diagonal keeps
        # the factor finite where a body's free nodes leave a motion nearly unresisted
        entries = torch.diagonal(matrices, dim1=-2, dim2=-1)
        scale = entries.amax(-1, keepdim=True).clamp(min=torch.finfo(torch.float64).tiny)
        empty = entries <= 1e-12 * scale
        matrices = matrices + torch.diag_embed(empty.to(matrices.dtype) + 1e-10 * scale)
        # E^-1 = L^-T L^-1 by triangular solves (torch's cholesky_inverse synchronises with the
        # host; the loads must not)
        factor, _ = torch.linalg.cholesky_ex(matrices)
        eye = torch.eye(6 * size, dtype=matrices.dtype, device=matrices.device).expand_as(matrices)
        lower_inverse = torch.linalg.solve_triangular(factor, eye, upper=False)
        inverses = lower_inverse.transpose(1, 2) @ lower_inverse  # [G, 6 c, 6 c]
        rows = inverses.view(groups, size, 6, size, 6).transpose(2, 3)[group, slot]  # [B, c, 6, 6]
        blocks = torch.where(filled, rows, 0.0).to(x.dtype).reshape(-1, 6, 6)
        if self.node_inverse is None or self.inverses.values.shape != blocks.shape \
                or self.node_inverse.shape != node_inverse.shape or self.node_inverse.dtype != x.dtype \
                or self.node_inverse.device != x.device:
            self._build(node_inverse, arms, blocks, columns, segments)
        else:
            self.node_inverse.copy_(node_inverse)
            self.inverses.values.copy_(blocks)
            if fresh:  # (a kept load's arms and groups are the last load's)
                self.arms.copy_(arms)
                self.inverses.block_cols.copy_(columns)
        return self

    def _take_scaling(self, scaling, x: torch.Tensor, free: Optional[torch.Tensor]) -> torch.Tensor:
        """Take block Jacobi loaded as ``scaling`` for this load (:attr:`inverse_blocks` and
        :attr:`paired` read it) and return N at each node: on a ``BlockJacobi`` the free mask
        ``[V]`` (N = I, Z in the system's own unknowns), on a ``JacobiScaling`` its S^-1
        ``[V, 3, 3]``; zero on fixed nodes."""
        self._blocks = getattr(scaling, "inverse_blocks", None)
        self._scaling = scaling
        if self._blocks is not None:
            return free[:, 0].to(x.dtype) if free is not None else x.new_ones(x.shape[0])
        node_inverse = scaling.inverse if scaling.inverse.dim() == 3 else torch.diag_embed(scaling.inverse)
        return node_inverse if free is None else node_inverse * free[:, :, None]

    def _build(self, node_inverse: torch.Tensor, arms: torch.Tensor, rows: torch.Tensor, columns: torch.Tensor,
               segments: Segments):
        """The buffers, new: ``node_inverse [V, 3, 3] or [V]``, ``arms [V, 3]``, the inverses' blocks
        ``rows [B c, 6, 6]`` and their block columns ``[B c]`` int32, the bodies' node ranges."""
        bodies, device = segments.num_objects, arms.device
        per_row = rows.shape[0] // bodies
        self.node_inverse = node_inverse.contiguous().clone()
        self.arms = arms.contiguous().clone()
        # the restriction sums runs of at most RESTRICTION_RUN nodes within a body, then each
        # body's runs in order (deterministic): the runs' ranges and each body's count of them
        lengths = segments.lengths.to(device)
        self._runs = (lengths + RESTRICTION_RUN - 1) // RESTRICTION_RUN  # [B]
        run_body = torch.repeat_interleave(torch.arange(bodies, device=device), self._runs)
        first_run = torch.cumsum(self._runs, 0) - self._runs
        starts = segments.ptr.to(device)[run_body] + RESTRICTION_RUN * (torch.arange(run_body.numel(), device=device)
                                                                        - first_run[run_body])
        self._run_ptr = torch.cat([starts, starts.new_full((1,), arms.shape[0])]).to(torch.int32)
        self._node_body = segments.node_object.to(device=device, dtype=torch.int32)
        self._body_ptr = segments.ptr.to(device=device, dtype=torch.int64)
        self.inverses = BsrMatrix(rows.contiguous(), columns.clone(),  # (its own: later loads write it)
                                  torch.arange(bodies + 1, dtype=torch.int32, device=device) * per_row,
                                  torch.arange(bodies, device=device).repeat_interleave(per_row),
                                  (6 * bodies, 6 * bodies))

    @property
    def key(self) -> tuple:
        """What a graph captured over :meth:`__call__` depends on: its buffers' storage."""
        return ("rigid", self.node_inverse.data_ptr(), self.arms.data_ptr(), self.inverses.values.data_ptr(),
                self.inverses.block_cols.data_ptr())

    def basis(self) -> torch.Tensor:
        """Z' ``[V, 3, 6]`` as the ops form it at each node (N [I | -[a]x]), for tests and inspection."""
        modes = modes_of(self.arms).permute(1, 2, 0)  # [V, 3, 6]
        if self.node_inverse.dim() == 1:  # N = n_i I
            return self.node_inverse[:, None, None] * modes
        return (self.node_inverse[:, :, :, None] * modes[:, None, :, :]).sum(2)

    def _coarse_solution(self, r: torch.Tensor) -> torch.Tensor:
        """E^-1 Z'^T r ``[6 B]`` (the groups' blocks) for a residual ``r [V, 3]``."""
        return self.coarse_terms(r)[1].reshape(-1)

    def coarse_terms(self, r: torch.Tensor) -> tuple:
        """(g = Z'^T r, y = E^-1 g), ``[B, 6]`` each, for a residual ``r [V, 3]``: what the CG's
        iteration takes where z = B^-1 r + w Z' y is applied in its own ops (``CGSolver``: r.z =
        r.B^-1 r + w g . y by ``cg_ops.coarse_beta``, and w Z' y added in ``cg_direction``)."""
        per_run = rigid_restrict(self.node_inverse, self.arms, self._run_ptr, r.reshape(-1)).view(-1, 6)
        restricted = torch.segment_reduce(per_run, "sum", lengths=self._runs, unsafe=True)  # [B, 6]
        return restricted, bsr_gemv(self.inverses, restricted.reshape(-1)).view(-1, 6)

    def direction_term(self, solution: torch.Tensor) -> CoarseTerm:
        """w Z' y as ``cg_direction``'s coarse term, for the coarse solution ``y [B, 6]``."""
        return CoarseTerm(self.node_inverse, self.arms, self._node_body, solution.reshape(-1), self.weight)

    @property
    def body_ptr(self) -> torch.Tensor:
        """``[B + 1]`` int64 on the device: the bodies' node ranges (the coarse vectors' items)."""
        return self._body_ptr

    def coarse(self, r: torch.Tensor) -> torch.Tensor:
        """Z' E^-1 Z'^T r ``[V, 3]`` for a residual ``r [V, 3]`` of the scaled system (unweighted)."""
        return rigid_prolong(self.node_inverse, self.arms, self._node_body, self._coarse_solution(r)).view_as(r)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """z = r + w Z' E^-1 Z'^T r ``[V, 3]`` of the scaled system (loaded on a JacobiScaling):
        three ops, the last adding r; on a BlockJacobi, z = B^-1 r + w Z E^-1 Z^T r."""
        if self._blocks is not None:  # (the BlockJacobi's own z: its paired blocks too)
            return self.correct(r, self._scaling(r))
        return rigid_prolong(self.node_inverse, self.arms, self._node_body, self._coarse_solution(r), r.reshape(-1),
                             self.weight).view_as(r)

    @property
    def inverse_blocks(self) -> Optional[torch.Tensor]:
        """Loaded on a ``BlockJacobi``: its B^-1 ``[V, 3, 3]``, which the CG applies inside its
        update before :meth:`correct` adds the coarse part (``CGSolver``); else None."""
        return self._blocks

    @property
    def paired(self):
        """Loaded on a ``BlockJacobi``: its paired blocks (``preconditioner.PairedBlocks``, which
        the CG adds to z before the coarse part), or None."""
        return getattr(self._scaling, "paired", None) if self._blocks is not None else None

    def correct(self, r: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """z += w Z E^-1 Z^T r ``[V, 3]`` in place (loaded on a ``BlockJacobi``: Z in the system's
        own unknowns): with z = B^-1 r, the preconditioner's z = M^-1 r. Returns z."""
        rigid_prolong(self.node_inverse, self.arms, self._node_body, self._coarse_solution(r), z.reshape(-1),
                      self.weight, out=z.reshape(-1))
        return z


__all__ = ["GROUPINGS", "GROUP_BODIES", "WEIGHT", "BodySums", "RigidModeCorrection", "contact_clusters",
           "contact_groups", "group_matrices", "lever_arms", "modes_of", "morton_groups", "own_blocks", "rigid_modes"]
