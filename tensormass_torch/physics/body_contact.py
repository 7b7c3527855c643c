"""Contact between the surfaces of bodies: vertex-triangle penalties with a contact thickness,
found by a spatial hash each step, their stiffness in the implicit system.

Every surface vertex p of a body meets the surface triangles (a, b, c) of the other bodies (and,
with ``self_contact``, the far parts of its own surface). For a pair, the closest point of the
triangle is ``q = w_a a + w_b b + w_c c`` (barycentric weights w on the triangle), at distance
``d = |p - q|``; its sign is the side of the triangle's outward normal ``n_t`` that p is on, so
``s = sign(n_t . (p - q)) d`` is negative once p is inside the other body. With the thickness
delta the gap is ``g = s - delta`` and, while g < 0, the pair's penalty energy and forces are

    E = k/2 g^2       f_p = -k g u        f_a = k g w_a u,  f_b = k g w_b u,  f_c = k g w_c u

with ``u = sign (p - q) / d`` (= n_t where q is inside the triangle). These forces are minus the
energy's gradient: d is the minimum of |p - sum w_i x_i| over the triangle, so by the envelope
theorem its gradient is u on p and -w_i u on the triangle's nodes (the minimising w does not
move to first order). They sum to zero (the w sum to 1) and their torque about any point is zero
(p - q is along u): contact conserves linear and angular momentum.

The stiffness the implicit step uses is, by default (``tangent="projected"``), k J^T J with
J = (u, -w_a u, -w_b u, -w_c u): the energy's Hessian without its curvature term k g d2s/dx2,
positive semi-definite (the same choice as the tools'; docs/contact.md). ``tangent="exact"``
keeps that term (each pair's 12 x 12 Hessian by automatic differentiation of its energy: for
tests and small scenes; it can make the step's matrix indefinite).

Which pairs: for each surface vertex and each other body, the nearest triangle of that body
within ``thickness + search`` (the spatial hash's reach), with ``swept`` (the default) plus,
at a step's start, what the pair may close over the step (the broad phase sweeps the
triangles' and the vertices' boxes over the step in their bodies' moving frames: a vertex
arriving faster than the search per step is found before it is inside); the pair is in
contact while its gap is negative. A vertex that went deeper than ``search`` into a body is
lost to it (the step was too long for the contact: shorten dt, stiffen the contact or widen
``search``). For self-contact the triangles within the same reach of the vertex at rest (its
neighbourhood) are left out.

Pairs are found at the start of a step (where the step linearises) and kept for its solve. A
pair counts from the step whose end it would reach in contact at the current velocities (its
gap plus dt times its closing speed negative), not from the step after: its linearised force
-k (g + J dx) u then acts on the gap at the end of the step, as an implicit step's forces do,
and a body arriving at speed v stops within about the penalty's own depth instead of v dt inside
the other. (At the step's start such a pair's force -k g u, g > 0, pulls: it is the linear
model's value there, the solve's result is the push at the end.) The pairs couple the bodies
they join: the step solves such bodies together (one CG over the run of objects that contact
joins, ``coupled_ranges``).

The starting velocities only predict the end of the step: the solve changes them (another
pair's push, the floor stopping the body below, a bounce), and a pair left out of the solve has
no force, however deep the solution puts its vertex. So the step checks its solution against
every nearby pair (:meth:`SurfaceContact.nearby`: each vertex's nearest triangle of each other
body within reach, whatever its gap) and solves again with those whose linear end gap
g + u . J dx came out negative; and, since that linear model keeps the triangle, the closest
point and the direction of the step's start, with the pairs found at the solution's end where
a vertex is deeper there than its model says (:meth:`SurfaceContact.relinearise`: a vertex
sliding over a crease of the other surface or across a turning triangle), linearised there
(``solver.implicit_euler.implicit_euler_step``).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field
from typing import List, Optional

import torch

from ..errors import SceneError
from ..mesh.distance import closest_point, closest_weights  # noqa: F401  (closest_weights: re-exported)
from ..mesh.topology import add_at
from ..ops import contact as contact_ops
from .contact import check_friction, coulomb_damping, tangential_part

#: Bodies tested against all the others at a time by the swept broad phase (memory: BODY_ROWS x B).
BODY_ROWS = 2048

#: After a settled test that failed (:meth:`SurfaceContact.settled_if_due`), the next one waits
#: 1, 2, 4, ... steps, by default at most this many (``SurfaceContact.settled_wait``): a pile
#: still creeping fails it step after step (each a detection's worth of reductions and a host
#: read), and a step that leaves it out runs the check it would have skipped, so the wait changes
#: no result.
SETTLED_WAIT = 8

#: the stiffness a body contact gives the implicit step (``Contact.tangent``)
TANGENTS = ("projected", "exact")


@dataclass(frozen=True)
class Contact:
    """Settings of contact between bodies (the scene file's ``[contact]`` table).

    Attributes:
        stiffness: penalty k (N/m per vertex in contact).
        thickness: contact distance delta: surfaces are pushed apart once closer than this (a
            layer that takes the penalty's compression, so the surfaces themselves need not
            interpenetrate; 0: they meet at the surfaces).
        search: how far past the thickness pairs are looked for, and how deep a vertex may go into
            another body and still be pushed out; None: the mean edge length of the bodies'
            surfaces.
        self_contact: a body's surface also meets its own far parts (those beyond ``thickness +
            search`` of a vertex at rest).
        swept: find each step's pairs over the step's motion (``SurfaceContact.candidates``,
            in each body's moving frame): a body closing on another faster than the search per
            step is found before it is inside (default). False: within the search of where the
            step starts only (a little cheaper for a few small bodies).
        tangent: ``"projected"`` (default; positive semi-definite) or ``"exact"`` (see the module).
        friction: Coulomb coefficient mu between the bodies (0: frictionless, the default).
        friction_velocity: eps_v (m/s), the slip speed below which friction is viscous instead
            of Coulomb (the regularisation: a sticking contact creeps at less than this).
        rounds: how many more solves a step may take to check its contact set against its
            solution (``solver.implicit_euler.implicit_euler_step``: pairs the solution drives
            into contact join the set, pairs it slides over a crease are linearised again; a step
            that misses nothing is solved once). 0: the pairs found at the step's start only,
            one solve a step; fewer rounds are faster and leave deeper transient
            interpenetration (docs/contact.md measures the trade; at scale a falling pile's
            steps take every round they may, so each costs about one more solve).
        tolerance: how much deeper than its pair's linear model (or, with no pair, than the
            surface) a vertex may end a step before the step takes a round; None: 1/400 of the
            search, 0.25 % of the mean surface edge by default (``SurfaceContact.tolerance``). A
            larger tolerance leaves shallow misses to the next step, which finds them in contact.
        recheck_tolerance: the same for the solves of the rounds (the step's first solve takes
            ``tolerance``): a round's solve is checked again, and one more round taken, only for a
            vertex that ends deeper than this past its model; None: 1/100 of the search (the 1 %
            of an edge the contact holds interpenetration to), and at least ``tolerance``. At rest
            a round's solve leaves shallow misses of its own (vibrating vertices at the rim of
            a contact patch), which the next step finds in contact; a fast body's are deep
            (docs/contact.md).
        check_tol: the relative residual at which a solve whose end positions a round's check
            reads pauses; None: every solve to ``cg_tol``. A check needs the end positions to
            about the tolerance, not the velocities to cg_tol (docs/contact.md measures the
            saving). Where the check finds nothing to add, the paused solve goes on to the
            simulator's ``cg_tol``, else the round solves again from it; the step's last solve
            always reaches ``cg_tol``. A pair
            re-linearised where a paused solve ended depends on that solve, so ``tm.rollout``
            (``exact=True``, its default) solves every solve to ``cg_tol``; with ``exact=False``
            its gradient through that dependence is approximate.
        skin: keep the broad phase's candidates and reuse them (m; None: 1/10 of the search; 0:
            every detection finds its own). The candidates are found for triangles grown by
            twice the skin past the reach, and a detection takes them where, since they were
            found, no surface vertex has moved by more than the skin less what its query needs for
            the step's motion (a swept one: the most any vertex moves apart from its body, plus
            half the most two bodies close on each other; a contact-set check: nothing). Those
            candidates then hold every pair a fresh broad phase would find
            (``SurfaceContact.candidates``), so every pair within the reach is the fresh
            detection's; beyond the reach, where a swept detection keeps pairs only outside, a
            pair may take a nearer triangle. A larger skin is reused longer and gives the narrow
            phase more candidates (docs/contact.md measures the trade).
        check_margin: how far (m) a body's surface may end a solve from where the step's starting
            velocities put it, for the step's contact-set checks to take its pairs' candidates
            from the step's own broad phase (whose triangles then grow by twice the margin); a
            body past it has its pairs searched again among the bodies near it. None: 1/16 of
            the search; 0: every check searches on its own. The pairs are the same either way
            (``SurfaceContact._step_candidates``); a larger margin serves more bodies (a bounce,
            an impact) and gives the narrow phases more candidates. Used only with ``skin=0``: the
            kept candidates of a skin serve the checks by their own bound.
    """

    stiffness: float = 1e5
    thickness: float = 0.0
    search: Optional[float] = None
    self_contact: bool = False
    swept: bool = True
    tangent: str = "projected"
    friction: float = 0.0
    friction_velocity: float = 1e-3
    rounds: int = 2
    tolerance: Optional[float] = None
    recheck_tolerance: Optional[float] = None
    check_tol: Optional[float] = 1e-2
    skin: Optional[float] = None
    check_margin: Optional[float] = None

    def __post_init__(self):
        def number(value):
            return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

        if not number(self.stiffness) or self.stiffness <= 0:
            raise SceneError(f"contact stiffness must be a positive finite number, got {self.stiffness!r}")
        if not number(self.thickness) or self.thickness < 0:
            raise SceneError(f"contact thickness must be a non-negative finite number, got {self.thickness!r}")
        if self.search is not None and (not number(self.search) or self.search <= 0):
            raise SceneError(f"contact search must be a positive finite number or None, got {self.search!r}")
        if not isinstance(self.self_contact, bool):
            raise SceneError(f"contact self_contact must be true or false, got {self.self_contact!r}")
        if not isinstance(self.swept, bool):
            raise SceneError(f"contact swept must be true or false, got {self.swept!r}")
        check_friction(self.friction, self.friction_velocity, "contact")
        if not isinstance(self.rounds, int) or isinstance(self.rounds, bool) or self.rounds < 0:
            raise SceneError(f"contact rounds must be a non-negative integer, got {self.rounds!r}")
        if self.tolerance is not None and (not number(self.tolerance) or self.tolerance <= 0):
            raise SceneError(f"contact tolerance must be a positive finite number or None, got {self.tolerance!r}")
        if self.recheck_tolerance is not None and (not number(self.recheck_tolerance) or self.recheck_tolerance <= 0):
            raise SceneError(f"contact recheck_tolerance must be a positive finite number or None, "
                             f"got {self.recheck_tolerance!r}")
        if self.check_tol is not None and (not number(self.check_tol) or not 0 < self.check_tol < 1):
            raise SceneError(f"contact check_tol must be a number in (0, 1) or None, got {self.check_tol!r}")
        if self.skin is not None and (not number(self.skin) or self.skin < 0):
            raise SceneError(f"contact skin must be a non-negative finite number or None, got {self.skin!r}")
        if self.check_margin is not None and (not number(self.check_margin) or self.check_margin < 0):
            raise SceneError(f"contact check_margin must be a non-negative finite number or None, "
                             f"got {self.check_margin!r}")
        if self.tangent not in TANGENTS:
            raise SceneError(f"contact tangent must be one of {', '.join(map(repr, TANGENTS))}, "
                             f"got {self.tangent!r}")


def _direction(diff: torch.Tensor, d: torch.Tensor, side: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """u = side (p - q) / d, the gradient of the signed distance at p; the normal where p is on
    the triangle (d ~ 0, where the direction of p - q means nothing)."""
    tiny = torch.finfo(d.dtype).eps * torch.clamp(d.amax() if d.numel() else d.new_ones(()), min=1.0)
    return torch.where((d > tiny)[..., None], side[..., None] * diff / torch.clamp(d, min=tiny)[..., None], normal)


def signed_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor, c: torch.Tensor):
    """The signed distance from p to the one triangle (a, b, c) (all ``[..., 3]``): (s ``[...]``,
    unit direction u ``[..., 3]`` (ds/dp), weights w ``[..., 3]``); s < 0 on the side opposite
    the triangle's normal. (On a closed surface, where the closest point is on an edge or a
    corner several triangles share, the side is that of their normals' sum: ``SurfaceContact``.)"""
    w, diff, d, normal = closest_point(p, a, b, c)
    side = torch.where((normal * diff).sum(-1) >= 0, 1.0, -1.0).to(p.dtype)
    return side * d, _direction(diff, d, side, normal), w


def _sum_into(num_nodes: int, nodes: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``[V, k]`` zeros plus ``values [M, k]`` summed at ``nodes [M]``, in an order that does not
    depend on the run (``mesh.topology.add_at``)."""
    return add_at(values.new_zeros(num_nodes, values.shape[-1]), nodes, values)


def entry_runs(nodes: torch.Tensor, num_nodes: int):
    """(order ``[M]``, offsets ``[V + 1]``): the entries ``nodes [M]`` stably sorted by the node
    they go to, and where each node's run starts in that order (node i's entries are
    ``order[offsets[i]:offsets[i + 1]]``): what :func:`sum_runs` sums by."""
    targets, order = torch.sort(nodes, stable=True)
    return order, torch.searchsorted(targets, torch.arange(num_nodes + 1, device=nodes.device))


def sum_runs(values: torch.Tensor, order: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """``[V, k]``: ``values [M, k]`` summed over each node's run of :func:`entry_runs` (a gather and
    a segment sum, each run in entry order: deterministic, no sort, no atomics)."""
    return torch.segment_reduce(values[order], "sum", offsets=offsets, axis=0, unsafe=True)


def _relative(nodes: torch.Tensor, coefficients: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
    """``[P, 3]`` J dx per pair: sum_i coefficient_i dx[node_i] (``nodes, coefficients [P, 4]``)."""
    return (coefficients[:, :, None] * dx[nodes]).sum(1)


def _along_normals(pairs: "ContactPairs", coefficients: torch.Tensor, direction: torch.Tensor,
                   magnitude: torch.Tensor) -> torch.Tensor:
    """``[V, 3]``: each pair's force ``magnitude [P]`` along its direction u ``[P, 3]``, J^T (magnitude
    u): coefficient_i magnitude u on node i of ``pairs``' nodes, summed deterministically."""
    per_pair = magnitude[:, None, None] * coefficients[:, :, None] * direction[:, None, :]  # [P, 4, 3]
    return pairs.node_sums(per_pair.reshape(-1, 3))


def _pair_blocks(direction: torch.Tensor, normal, tangential: Optional[torch.Tensor]) -> torch.Tensor:
    """``[P, 3, 3]``: each pair's M = a u u^T + b (I - u u^T) for its direction u ``[P, 3]``, a =
    ``normal`` (a number, or ``[P]``) and b = ``tangential`` ``[P]`` (None: 0)."""
    along = direction[:, :, None] * direction[:, None, :]  # [P, 3, 3]
    normal = torch.as_tensor(normal, dtype=along.dtype, device=along.device)
    per_pair = (normal.reshape(-1, 1, 1) if normal.dim() else normal) * along
    if tangential is not None:
        eye = torch.eye(3, dtype=along.dtype, device=along.device)
        per_pair = per_pair + tangential[:, None, None] * (eye - along)
    return per_pair


def _entry_blocks(coefficients: torch.Tensor, per_pair: torch.Tensor) -> torch.Tensor:
    """``[4 P, 9]``: coefficient_i^2 M, each pair's diagonal block at its node i (``coefficients
    [P, 4]``, M ``[P, 3, 3]``), in the pairs' entry order."""
    return ((coefficients ** 2)[:, :, None, None] * per_pair[:, None]).reshape(-1, 9)


@dataclass
class ContactPairs:
    """The vertex-triangle pairs in contact at one state (what a step linearises).

    Attributes:
        nodes: ``[P, 4]`` the vertex, then the triangle's three nodes (packed node ids).
        weights: ``[P, 3]`` the closest point's barycentric weights on the triangle.
        direction: ``[P, 3]`` u, the unit gradient of the signed distance at the vertex.
        signed: ``[P]`` s, the signed distance (negative: the vertex is inside the other body).
        gap: ``[P]`` s - thickness (negative: in contact).
        objects: ``[P, 2]`` the vertex's body and the triangle's.
        stiffness: k.
        hessians: ``[P, 12, 12]`` each pair's exact energy Hessian (``tangent="exact"``), or None.
        num_nodes: V.
        friction: ``[P]`` each pair's friction damping c (N s/m) on its tangential relative
            velocity, mu k max(0, -g) / max(|v_t|, eps_v) at the velocities it was found with
            (lagged: fixed for the step), or None (no friction).
        shift: ``[P, 4, 3]`` the motions of its four nodes from the state the step linearises at
            to where the pair was found (:meth:`SurfaceContact.relinearise`: its direction,
            weights and gap are those at x + shift, its gap carried back to x), or None (every
            pair found at x).
        born: ``[P]`` int64, with ``shift``: the solve of the step whose motion the shift is
            (``relinearise``'s ``solution``; -1: the pair was found at x, its shift 0), or None.
    """

    nodes: torch.Tensor
    weights: torch.Tensor
    direction: torch.Tensor
    signed: torch.Tensor
    gap: torch.Tensor
    objects: torch.Tensor
    stiffness: float
    hessians: Optional[torch.Tensor]
    num_nodes: int
    friction: Optional[torch.Tensor] = None
    shift: Optional[torch.Tensor] = None
    born: Optional[torch.Tensor] = None
    #: (weights, their coefficients) once computed (a step asks for them about eight times)
    _coefficient_cache: Optional[tuple] = field(default=None, init=False, repr=False, compare=False)
    #: (nodes, entry_runs of them) once formed (a step sums at the nodes several times on CUDA,
    #: and the pair stiffness loads them)
    _runs_cache: Optional[tuple] = field(default=None, init=False, repr=False, compare=False)

    def __len__(self):
        return self.gap.numel()

    def select(self, index: torch.Tensor) -> "ContactPairs":
        """The pairs at ``index`` (indices ``[Q]`` or a mask ``[P]``), in that order."""
        if index.dtype == torch.bool:  # one host read for every field, not one each
            index = index.nonzero().squeeze(1)

        def take(t):
            return None if t is None else t[index]

        return ContactPairs(self.nodes[index], self.weights[index], self.direction[index], self.signed[index],
                            self.gap[index], self.objects[index], self.stiffness, take(self.hessians),
                            self.num_nodes, take(self.friction), take(self.shift), take(self.born))

    def end_gap(self, dx: torch.Tensor) -> torch.Tensor:
        """``[P]`` each pair's gap after node motions ``dx [V, 3]`` in the pair's linear model,
        g + u . J dx (the gap its linearised force -k (g + u . J dx) acts on)."""
        return self.gap + (self.relative(dx) * self.direction).sum(-1)

    def _coefficients(self) -> torch.Tensor:
        """``[P, 4]``: the vertex's 1 and the triangle's -w (J = coefficient x u per node); kept
        for these weights (not where they carry autograd history: each graph makes its own)."""
        cached = self._coefficient_cache
        if cached is not None and cached[0] is self.weights:
            return cached[1]
        coefficients = torch.cat([torch.ones_like(self.weights[:, :1]), -self.weights], dim=1)
        if not (self.weights.requires_grad and torch.is_grad_enabled()):
            self._coefficient_cache = (self.weights, coefficients)
        return coefficients

    def runs(self):
        """(order ``[4 P]``, offsets ``[V + 1]``): the pairs' entries (``nodes`` flattened) by the
        node they go to (:func:`entry_runs`), sorted once for these pairs."""
        cached = self._runs_cache
        if cached is None or cached[0] is not self.nodes:
            cached = (self.nodes, entry_runs(self.nodes.reshape(-1), self.num_nodes))
            self._runs_cache = cached
        return cached[1]

    def node_sums(self, per_entry: torch.Tensor, by_runs: Optional[bool] = None) -> torch.Tensor:
        """``[V, k]``: ``per_entry [4 P, k]`` (each pair's four entries in node order, the vertex
        first) summed at their nodes, in an order that does not change from run to run: on CUDA
        by the entries' runs (:meth:`runs`; a gather and a segment sum a call, where ``add_at``'s
        accumulation sorts at every call), elsewhere by ``add_at`` (``index_add_``). ``by_runs``:
        one way or the other whatever the device (None: by the device)."""
        if per_entry.is_cuda if by_runs is None else by_runs:
            return sum_runs(per_entry, *self.runs())
        return _sum_into(self.num_nodes, self.nodes.reshape(-1), per_entry)

    def forces(self) -> torch.Tensor:
        """The penalty forces ``[V, 3]``: -k g u on the vertex, k g w_i u on the triangle's nodes."""
        return _along_normals(self, self._coefficients(), self.direction, -self.stiffness * self.gap)

    def dforces(self, dx: torch.Tensor) -> torch.Tensor:
        """(df/dx) dx ``[V, 3]`` with the chosen stiffness (minus the projected or exact Hessian)."""
        if self.hessians is not None:
            local = dx[self.nodes].reshape(-1, 12)  # [P, 12]
            per_pair = -(self.hessians @ local[:, :, None])[:, :, 0].reshape(-1, 4, 3)
            return self.node_sums(per_pair.reshape(-1, 3))
        coefficients = self._coefficients()  # projected: -k (u . J dx) along each pair's normal
        along = (_relative(self.nodes, coefficients, dx) * self.direction).sum(-1)
        return _along_normals(self, coefficients, self.direction, -self.stiffness * along)

    def linear_forces(self, dx: torch.Tensor) -> torch.Tensor:
        """:meth:`forces` plus :meth:`dforces` of ``dx [V, 3]`` ``[V, 3]``, the pairs' forces
        linearised at x + dx: with the projected tangent J^T (-k (g + u . J dx) u), summed at the
        nodes once."""
        if self.hessians is not None:
            return self.forces() + self.dforces(dx)
        coefficients = self._coefficients()
        along = (_relative(self.nodes, coefficients, dx) * self.direction).sum(-1)
        return _along_normals(self, coefficients, self.direction, -self.stiffness * (self.gap + along))

    def relative(self, dx: torch.Tensor) -> torch.Tensor:
        """``[P, 3]`` J dx as a vector per pair: the vertex's motion less the closest point's,
        sum_i coef_i dx_i for node motions (or velocities) ``dx [V, 3]``."""
        return _relative(self.nodes, self._coefficients(), dx)

    def slip(self, v: torch.Tensor) -> torch.Tensor:
        """``[P, 3]`` each pair's tangential relative velocity P_t J v at velocities ``v [V, 3]``
        (the vertex's against the triangle's closest point, less its part along u)."""
        return tangential_part(self.relative(v), self.direction)

    def friction_forces(self, v: torch.Tensor) -> torch.Tensor:
        """The friction forces ``[V, 3]`` at velocities ``v [V, 3]``: each pair's -c P_t (J v) on
        the vertex and +c w_i P_t (J v) on the triangle's nodes (P_t = I - u u^T: the relative
        velocity's tangential part), zero without friction. Linear in v (c is fixed for the
        step), so it is also its own derivative: the implicit step's damping matrix times v."""
        if self.friction is None:
            return v.new_zeros(self.num_nodes, 3)
        per_pair = -(self.friction[:, None, None] * self._coefficients()[:, :, None]) * self.slip(v)[:, None, :]
        return self.node_sums(per_pair.reshape(-1, 3))

    def stiffness_diagonal(self, coefficient: float, damping: float = 0.0) -> torch.Tensor:
        """The diagonal ``[V, 3]`` of the pairs' part of the step's matrix, sum over pairs of
        J^T (a u u^T + b P_t) J with a = ``coefficient`` k, b = ``damping`` c_p (as
        :class:`PairStiffness`): coef_i^2 (a u_x^2 + b (1 - u_x^2)) at node i, axis x. The
        projected stiffness's also where the tangent is exact (its Hessians' diagonal need not be
        positive; this is for a preconditioner)."""
        along = self.direction * self.direction  # [P, 3]
        per_axis = (coefficient * self.stiffness) * along
        if self.friction is not None and damping:
            per_axis = per_axis + (damping * self.friction)[:, None] * (1.0 - along)
        per_entry = (self._coefficients() ** 2)[:, :, None] * per_axis[:, None, :]  # [P, 4, 3]
        return self.node_sums(per_entry.reshape(-1, 3))

    def _pair_matrices(self, coefficient: float, damping: float) -> torch.Tensor:
        """``[P, 3, 3]``: each pair's M = a u u^T + b (I - u u^T), a = ``coefficient`` k, b =
        ``damping`` c_p (its part of the step's matrix is J^T M J over its four nodes)."""
        return _pair_blocks(self.direction, coefficient * self.stiffness,
                            damping * self.friction if self.friction is not None and damping else None)

    def stiffness_row_l1(self, coefficient: float, damping: float = 0.0) -> torch.Tensor:
        """``[V, 3]``: a bound of the l1 norms of the rows of the pairs' part of the step's matrix
        (as :meth:`stiffness_diagonal`): each pair's rows summed exactly, |coef_i| (sum_j |coef_j|)
        sum_y |M_xy| at node i, axis x, M = a u u^T + b P_t, then over the pairs (the triangle
        inequality). A pair couples its four nodes: its diagonal alone does not bound its rows
        (the vertex's row is twice its diagonal, a triangle node's 2 / w of it), and an l1-Jacobi
        scaling built on the diagonal lets D^-1 A past 1 (``solver.multigrid``'s smoothers)."""
        coefficients = self._coefficients().abs()  # [P, 4]
        rows = self._pair_matrices(coefficient, damping).abs().sum(-1)  # [P, 3]
        per_entry = (coefficients * coefficients.sum(1, keepdim=True))[:, :, None] * rows[:, None]
        return self.node_sums(per_entry.reshape(-1, 3))

    def stiffness_blocks(self, coefficient: float, damping: float = 0.0) -> torch.Tensor:
        """The diagonal blocks ``[V, 3, 3]`` of the pairs' part of the step's matrix (as
        :meth:`stiffness_diagonal`, whose diagonals they hold): coef_i^2 (a u u^T + b (I - u u^T))
        at node i."""
        per_entry = _entry_blocks(self._coefficients(), self._pair_matrices(coefficient, damping))
        return self.node_sums(per_entry).view(-1, 3, 3)

    def energy(self) -> torch.Tensor:
        """The penalty energy (0-dim): sum over pairs of k/2 g^2."""
        return 0.5 * self.stiffness * (self.gap ** 2).sum()

    def penetration(self, num_objects: int, node_object: torch.Tensor):
        """Per body ``[B]``: its vertices in contact (gap < 0, int64: pairs kept only for their
        predicted gap do not count) and the deepest interpenetration of its surface into
        another's, max(0, -s) (0 with none: the thickness layer's compression is not penetration)."""
        vertex = self.nodes[:, 0]
        counts = torch.zeros(num_objects, dtype=torch.int64, device=vertex.device)
        # (integer sums: exact in any order, so atomics are deterministic here and need no sort)
        counts.scatter_add_(0, node_object[vertex], (self.gap < 0).to(torch.int64))
        deepest = self.signed.new_zeros(num_objects)
        deepest.scatter_reduce_(0, node_object[vertex], torch.clamp(-self.signed, min=0.0), "amax")
        return counts, deepest


class PairStiffness:
    """The pairs' part of the step's matrix as a product on buffers whose storage stays from step
    to step, so that a CUDA graph captured over a CG iteration replays with each step's pairs:

        dx -> sum over pairs of J^T (a u u^T + b P_t) J dx   [V, 3]

    with a = c_K k (the projected stiffness times the step's stiffness coefficient) and
    b = h c_p (the pair's friction damping times dt; 0 without friction), P_t = I - u u^T.

    The buffers hold ``capacity`` pairs (a power of two, at least 64, grown as needed, never
    shrunk); rows past the step's pairs are zero and add nothing. The product is a gather, a
    few products per pair and a deterministic scatter: the entries (4 per pair) are sorted by
    the node they go to once per load, so that each product only permutes them and sums each
    node's run in order (no sort per CG iteration; ``ops.contact.pair_product``: two kernels, a
    pair each, then a node each). The padding gathers node 0 and sorts past every node's run: no
    node receives it.
    """

    def __init__(self):
        self.capacity = 0
        self.nodes: Optional[torch.Tensor] = None  # [C, 4] gathered (padding: node 0)
        self.order: Optional[torch.Tensor] = None  # [4 C] the entries by the node they go to (padding last)
        self.offsets: Optional[torch.Tensor] = None  # [V + 1] node i's run: order[offsets[i]:offsets[i + 1]]
        self.coef: Optional[torch.Tensor] = None  # [C, 4] (1, -w_a, -w_b, -w_c)
        self.direction: Optional[torch.Tensor] = None  # [C, 3] u
        self.normal: Optional[torch.Tensor] = None  # [C] a
        self.friction: Optional[torch.Tensor] = None  # [C] b (zeros without friction)
        self.vector: Optional[torch.Tensor] = None  # [C, 3] the product's scratch
        self.rows: Optional[torch.Tensor] = None  # [V, 3] the product alone (rows_of), kept for the CG's graphs
        self.num_nodes = 0

    def load(self, pairs: "ContactPairs", coefficient: float, damping: float = 0.0) -> bool:
        """Take ``pairs`` (projected tangent) with a = ``coefficient`` k and b = ``damping`` times
        their friction; returns whether the buffers were reallocated (then graphs captured over
        the old ones must not be replayed)."""
        count = len(pairs)
        like = pairs.direction
        grew = (self.coef is None or count > self.capacity or self.coef.dtype != like.dtype
                or self.coef.device != like.device or pairs.num_nodes != self.num_nodes)
        if grew:
            self.capacity = max(64, 1 << max(count - 1, 1).bit_length(), self.capacity)
            self.nodes = torch.zeros(self.capacity, 4, dtype=torch.int64, device=like.device)
            self.order = torch.zeros(4 * self.capacity, dtype=torch.int64, device=like.device)
            self.offsets = torch.zeros(pairs.num_nodes + 1, dtype=torch.int64, device=like.device)
            self.coef = like.new_zeros(self.capacity, 4)
            self.direction = like.new_zeros(self.capacity, 3)
            self.normal = like.new_zeros(self.capacity)
            self.friction = like.new_zeros(self.capacity)
            self.vector = like.new_zeros(self.capacity, 3)
            self.rows = like.new_zeros(pairs.num_nodes, 3)
        self.num_nodes = pairs.num_nodes
        self.nodes[:count].copy_(pairs.nodes)
        self.nodes[count:].zero_()
        order, offsets = pairs.runs()  # (the pairs' own: their node sums in the step use them too)
        self.order[:4 * count].copy_(order)
        torch.arange(4 * count, 4 * self.capacity, out=self.order[4 * count:])
        self.offsets.copy_(offsets)
        self.coef[:count].copy_(pairs._coefficients())
        self.direction[:count].copy_(pairs.direction)
        self.normal[:count].fill_(coefficient * pairs.stiffness)
        if pairs.friction is None:
            self.friction[:count].zero_()
        else:
            torch.mul(pairs.friction, damping, out=self.friction[:count])
        for buffer in (self.coef, self.direction, self.normal, self.friction):
            buffer[count:].zero_()
        return grew

    def stiffness_blocks(self) -> torch.Tensor:
        """The diagonal blocks ``[V, 3, 3]`` of the loaded pairs' part of the step's matrix
        (``ContactPairs.stiffness_blocks`` with the load's coefficient and damping): coef_i^2 M at
        node i, M = a u u^T + b (I - u u^T), each node's entries summed in the order the load
        sorted them (one gather and one segment sum: no sort of its own; the padding's entries,
        zero, sort past every node's run)."""
        per_entry = _entry_blocks(self.coef, _pair_blocks(self.direction, self.normal, self.friction))
        return sum_runs(per_entry, self.order, self.offsets).view(-1, 3, 3)

    def pair_matrices(self) -> torch.Tensor:
        """``[C, 3, 3]``: each loaded pair's M = a u u^T + b (I - u u^T) (zero past the pairs)."""
        return _pair_blocks(self.direction, self.normal, self.friction)

    @property
    def key(self) -> tuple:
        """The buffers' storage (what a graph captured over them reads)."""
        return ("pair_stiffness", self.nodes.data_ptr(), self.coef.data_ptr(), self.direction.data_ptr(),
                self.normal.data_ptr(), self.friction.data_ptr())

    def __call__(self, dx: torch.Tensor, add_to: Optional[torch.Tensor] = None) -> torch.Tensor:
        """The product ``[V, 3]`` for ``dx [V, 3]`` (see the class; ``ops.contact.pair_product``),
        or ``add_to [V, 3]`` (another product, not ``dx``) plus it, in place."""
        return self._product(dx, add_to=add_to)

    def rows_of(self, dx: torch.Tensor) -> torch.Tensor:
        """The product ``[V, 3]`` for ``dx [V, 3]`` alone, written into :attr:`rows` (kept with the
        buffers: a CG iteration takes it every time with no allocation)."""
        return self._product(dx, out=self.rows)

    def _product(self, dx: torch.Tensor, **into) -> torch.Tensor:
        return contact_ops.pair_product(dx, self.nodes, self.coef, self.direction, self.normal, self.friction,
                                        self.order, self.offsets, self.vector, **into)


class HeldPairs:
    """A step's contact pairs as functions of the positions and of the contact's stiffness and
    thickness, what each pair is held to (its vertex and triangle, its side, and where it was
    linearised) kept as the step found it: the body contact's part of the step's residual that
    the adjoint step differentiates (``solver.adjoint``).

    At positions x, a pair of ``pairs`` (a :class:`ContactPairs`) has, at y = x[nodes] + shift
    (its node motions :attr:`ContactPairs.shift`; 0 where found at x), the closest point's
    weights w(y), direction u(y) and signed distance s(y) = side |y_p - q(y)|, and

        g(x, delta) = s(y) - delta - u(y) . J(y) shift        (the gap its linear model has at x)
        f = -k g J^T u        (df/dx) dw = -k J^T u (u . J dw)          (J = (1, -w_a, -w_b, -w_c))

    At the x and settings the step found them with, these are the pairs' forces and projected
    stiffness exactly (the same closest point, the same formulas). Their derivatives in x go
    through w(y) and u(y) (the surfaces' curvature), and in the shift likewise (an earlier
    solve's motion: the adjoint step carries its cotangent back to that solve).

    Args:
        pairs: the step's pairs (``tangent="projected"``: no Hessians).
        stiffness: k, a number or a 0-dim tensor.
        thickness: delta, a number or a 0-dim tensor.
        shift: ``[P, 4, 3]`` in place of the pairs' own (the same values, with a gradient), or None.
    """

    def __init__(self, pairs: ContactPairs, stiffness, thickness, shift: Optional[torch.Tensor] = None):
        self.pairs = pairs
        self.stiffness = stiffness
        self.thickness = thickness
        self.shift = pairs.shift if shift is None else shift
        self._at = None  # (x, its model (coefficients [P, 4], direction [P, 3], gap [P]))

    def _model(self, x: torch.Tensor):
        """(J's coefficients ``[P, 4]``, u ``[P, 3]``, g ``[P]``) at ``x [V, 3]``, formed once per x."""
        if self._at is not None and self._at[0] is x:
            return self._at[1]
        pairs = self.pairs
        y = x[pairs.nodes]  # [P, 4, 3]
        if self.shift is not None:
            y = y + self.shift
        w, diff, d, normal = closest_point(y[:, 0], y[:, 1], y[:, 2], y[:, 3])
        # the side the pair was found on: u . (p - q) = side d (where d is not ~0, which it is
        # only for a vertex on the triangle, where the side leaves s unchanged)
        side = torch.where((pairs.direction * diff.detach()).sum(-1) >= 0, 1.0, -1.0).to(d.dtype)
        direction = _direction(diff, d, side, normal)
        coefficients = torch.cat([torch.ones_like(w[:, :1]), -w], dim=1)
        gap = side * d - self.thickness
        if self.shift is not None:
            gap = gap - ((coefficients[:, :, None] * self.shift).sum(1) * direction).sum(-1)
        self._at = (x, (coefficients, direction, gap))
        return self._at[1]

    def forces(self, x: torch.Tensor) -> torch.Tensor:
        """The pairs' forces ``[V, 3]`` at ``x [V, 3]``."""
        coefficients, direction, gap = self._model(x)
        return _along_normals(self.pairs, coefficients, direction, -self.stiffness * gap)

    def dforces(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """The pairs' projected force differential ``[V, 3]`` at ``x [V, 3]`` along ``dx [V, 3]``."""
        coefficients, direction, _ = self._model(x)
        along = (_relative(self.pairs.nodes, coefficients, dx) * direction).sum(-1)
        return _along_normals(self.pairs, coefficients, direction, -self.stiffness * along)


def _pair_energy_hessians(x: torch.Tensor, nodes: torch.Tensor, side: torch.Tensor, stiffness: float,
                          thickness: float) -> torch.Tensor:
    """``[P, 12, 12]``: each pair's exact energy Hessian k/2 (side d - delta)^2 over its 12
    coordinates (``side [P]`` as found; automatic differentiation through the closest point: the
    pairs are independent, so 12 backward passes give every block)."""
    with torch.enable_grad():
        local = x[nodes].detach().reshape(-1, 12).requires_grad_(True)
        y = local.reshape(-1, 4, 3)
        _, _, d, _ = closest_point(y[:, 0], y[:, 1], y[:, 2], y[:, 3])
        energy = 0.5 * stiffness * ((side * d - thickness) ** 2).sum()
        (grad,) = torch.autograd.grad(energy, local, create_graph=True)
        rows = [torch.autograd.grad(grad[:, j].sum(), local, retain_graph=True)[0] for j in range(12)]
    return torch.stack(rows, dim=1).detach()


class SurfaceContact:
    """Contact between the surfaces of packed bodies (see the module).

    Args:
        triangles: ``[F, 3]`` the bodies' surface triangles (packed node ids, wound outward).
        node_object: ``[V]`` each node's body (int64).
        rest: ``[V, 3]`` rest positions (for self-contact's neighbourhoods and the default search).
        settings: :class:`Contact`.
    """

    def __init__(self, triangles: torch.Tensor, node_object: torch.Tensor, rest: torch.Tensor, settings: Contact):
        if not isinstance(settings, Contact):
            raise SceneError(f"contact must be a tm.Contact, got {type(settings).__name__}")
        self.settings = settings
        self.triangles = triangles.to(device=rest.device, dtype=torch.int64).reshape(-1, 3)
        self.node_object = node_object.to(rest.device)
        self.triangle_object = self.node_object[self.triangles[:, 0]]
        self.vertices = torch.unique(self.triangles)  # the surface vertices [S]
        self.vertex_object = self.node_object[self.vertices]
        self.num_nodes = rest.shape[0]
        self.num_objects = int(self.node_object.max()) + 1 if self.node_object.numel() else 0
        # nodes and surface vertices per body; where the bodies own contiguous node ranges (the
        # simulator packs them so), their per-body sums and extremes are segment reductions, in a
        # fixed order, with no sort (add_at's) or atomics (scatter_reduce's): a third of the time
        # on the 1,000-block pile (benchmarks/results/contact/contact_pile_1000_body_reductions.md)
        objects = max(self.num_objects, 1)
        self._node_counts = torch.bincount(self.node_object, minlength=objects)
        self._vertex_counts = torch.bincount(self.vertex_object, minlength=objects)
        self._contiguous = len(self.node_object) < 2 or bool((self.node_object[1:] >= self.node_object[:-1]).all())
        # where each body's triangles start, where they come in body order (the packed bodies' do):
        # the broad phase's ops then skip a vertex's own body in its walks (no output changes)
        in_order = len(self.triangle_object) < 2 or bool((self.triangle_object[1:] >= self.triangle_object[:-1]).all())
        self._triangle_first = self._first_triangles(self.triangle_object) if in_order else None
        if settings.search is not None:
            self.search = float(settings.search)
        else:
            edges = rest[self.triangles] - rest[self.triangles.roll(1, dims=1)]
            self.search = float(torch.linalg.vector_norm(edges, dim=-1).mean()) if len(self.triangles) else 1.0
        self.rest = rest
        self._last = None  # (x, its version, v, its version, dt, what at_state found there)
        self._static = None  # (x, its version, the pairs in contact there): see _pairs_at
        #: whether the last step's first contact-set check found pairs (implicit_euler_step then
        #: skips the next step's settled test: it decides nothing that the check would not)
        self.first_check_found = False
        #: the most steps a settled test waits after failures (settled_if_due; 0: never waits)
        self.settled_wait = SETTLED_WAIT
        self._settled_failures = 0  # settled tests failed in a row (settled_if_due)
        self._settled_left = 0  # steps the settled test still waits
        self._kept = None  # Contact.skin: (surface vertices' positions [S, 3], reach, the candidates)
        # Contact.check_margin: the step's start search, for its checks (nearby, relinearise):
        # (x, its version, where the step's velocities put the surface vertices [S, 3], the
        # margin, the candidates)
        self._step_search = None
        # the search of a step's first check among the bodies near those past the margin, for the
        # step's later checks (_step_candidates): (the step's start search it was made under, the
        # surface vertices' positions at that check [S, 3], the bodies past the margin there [B],
        # the candidates)
        self._check_search = None

    @property
    def reach(self) -> float:
        """Thickness plus search: the distance within which pairs are looked for."""
        return self.settings.thickness + self.search

    @property
    def skin(self) -> float:
        """``Contact.skin`` (m), by default 1/10 of :attr:`search`; 0: no kept candidates."""
        skin = self.settings.skin
        return self.search / 10.0 if skin is None else float(skin)

    @property
    def check_margin(self) -> float:
        """``Contact.check_margin``, by default 1/16 of :attr:`search`; 0 with a skin (:attr:`skin`)."""
        if self.skin > 0:
            return 0.0
        margin = self.settings.check_margin
        return self.search / 16.0 if margin is None else float(margin)

    def _bodies(self, x: torch.Tensor, rate: torch.Tensor, scale: float):
        """Each body's motion and box for a motion ``scale * rate [V, 3]`` from ``x [V, 3]``: (each
        node's motion apart from its body's mean ``[V, 3]``; each body's mean motion ``[B, 3]``;
        the most any of its surface vertices moves apart from that mean ``[B]``; its surface's
        box at ``x``, lower and upper corners ``[B, 3]``)."""
        if self._contiguous:
            total = torch.segment_reduce(rate, "sum", lengths=self._node_counts, unsafe=True)
        else:
            total = add_at(rate.new_zeros(max(self.num_objects, 1), 3), self.node_object, rate)
        body_step = scale * total / self._node_counts.clamp(min=1).to(rate.dtype)[:, None]
        deviation = scale * rate - body_step[self.node_object]
        most = self._per_body_max(torch.linalg.vector_norm(deviation[self.vertices], dim=-1))
        return (deviation, body_step, most, *self._body_boxes(x[self.vertices]))

    def _per_body_max(self, values: torch.Tensor) -> torch.Tensor:
        """``[B]`` the largest of the surface vertices' ``values [S]`` (>= 0) over each body (0 for a
        body without any)."""
        if self._contiguous:
            return torch.segment_reduce(values, "max", lengths=self._vertex_counts, unsafe=True, initial=0.0)
        return values.new_zeros(max(self.num_objects, 1)).scatter_reduce(0, self.vertex_object, values, "amax")

    def _body_boxes(self, points: torch.Tensor):
        """Each body's box of its surface vertices at ``points [S, 3]``: lower and upper corners
        ``[B, 3]`` (+inf and -inf for a body without any)."""
        if self._contiguous:
            return (torch.segment_reduce(points, "min", lengths=self._vertex_counts, unsafe=True, initial=math.inf),
                    torch.segment_reduce(points, "max", lengths=self._vertex_counts, unsafe=True, initial=-math.inf))
        objects, index = max(self.num_objects, 1), self.vertex_object[:, None].expand(-1, 3)
        lower = points.new_full((objects, 3), math.inf).scatter_reduce(0, index, points, "amin")
        upper = points.new_full((objects, 3), -math.inf).scatter_reduce(0, index, points, "amax")
        return lower, upper

    @staticmethod
    def _boxes_meet(lower: torch.Tensor, upper: torch.Tensor, rows: torch.Tensor, margin) -> torch.Tensor:
        """``[rows, B]`` whether body ``rows``' boxes come within ``margin`` (a number, or ``[rows,
        B]``) of each body's, per axis (boxes ``lower, upper [B, 3]``)."""
        margin = margin[..., None] if torch.is_tensor(margin) else margin
        return ((lower[rows, None] <= upper[None] + margin) & (lower[None] <= upper[rows, None] + margin)).all(-1)

    def _motion(self, x: torch.Tensor, v: torch.Tensor, dt: float, reach: Optional[float] = None):
        """The step's motion as the broad phase sweeps it: (each node's displacement apart from
        its body's mean, dt (v - V_body) ``[V, 3]``; each body's mean displacement dt V_body
        ``[B, 3]``; per body, the largest dt |V_a - V_b| over the bodies b whose boxes may meet
        its own over the step, triangles grown by ``reach`` (None: :attr:`reach`) ``[B]``).
        Bodies moving together (a pile in free fall) sweep little: only their own deformation
        and turning, and what they close on each other. (The bodies' pairwise test runs
        BODY_ROWS bodies against all at a time.)"""
        reach = self.reach if reach is None else reach
        objects = max(self.num_objects, 1)
        deviation, body_step, turn, lower, upper = self._bodies(x, v, dt)
        grow = []
        for rows in torch.arange(objects, device=x.device).split(BODY_ROWS):  # [rows, B] at a time
            closing = torch.linalg.vector_norm(body_step[rows, None] - body_step[None], dim=-1)
            meet = self._boxes_meet(lower, upper, rows, reach + turn[rows, None] + turn[None] + closing)
            grow.append(torch.where(meet, closing, torch.zeros_like(closing)).amax(1))
        return deviation, body_step, torch.cat(grow)

    def settled(self, x: torch.Tensor, dx: torch.Tensor, pairs: "ContactPairs", active: torch.Tensor) -> bool:
        """Whether the contact set's first check after a solve (``implicit_euler_step``: the
        missed pairs, then :meth:`relinearise` at ``x + dx``) can find nothing, so that its
        detection may be skipped, for :meth:`nearby`'s ``pairs`` at ``x [V, 3]`` (linearised
        there) and the ``active [P]`` ones the solve used, the solve having moved the nodes by
        ``dx [V, 3]``. Conservative, from the bodies' motion: relative to body b's surface, a
        vertex of body a moves by at most r = dev_a + dev_b + |D_a - D_b| (D: a body's mean
        displacement; dev: the most any of its surface vertices moves apart from it), so its
        signed distance to b's surface changes by at most r, and so does a pair's linear model
        g + u . J dx: they differ by at most 2 r. Settled where
        - every active pair has 2 r <= tolerance (no re-linearisation),
        - every other pair's linear end gap is at least 2 r - tolerance (none missed),
        - every two bodies (a body and itself with self-contact) are at least max(reach, the gap
          between their boxes) - r - thickness > 0 apart at the end, for the vertices no pair
          holds (each at least the reach from that body at ``x``).
        One host read; the same pairs as the full check would find, so the step is bit for bit
        the same."""
        objects = max(self.num_objects, 1)
        _, mean, dev, lower, upper = self._bodies(x, dx, 1.0)
        margins = []
        for rows in torch.arange(objects, device=x.device).split(BODY_ROWS):  # [rows, B] at a time
            box_gap = torch.linalg.vector_norm(torch.clamp(torch.maximum(lower[rows, None] - upper[None],
                                                                         lower[None] - upper[rows, None]), min=0.0),
                                               dim=-1)
            closing = dev[rows, None] + dev[None] + torch.linalg.vector_norm(mean[rows, None] - mean[None], dim=-1)
            margin = torch.clamp(box_gap, min=self.reach) - closing - self.settings.thickness
            if not self.settings.self_contact:  # a body's own surface does not count
                margin[torch.arange(len(rows), device=x.device), rows] = math.inf
            margins.append(margin.amin(1))
        checks = [(torch.cat(margins) > 0).all()]
        if len(pairs):
            a, b = pairs.objects[:, 0], pairs.objects[:, 1]
            twice = 2.0 * (dev[a] + dev[b] + torch.linalg.vector_norm(mean[a] - mean[b], dim=-1))
            checks.append(torch.where(active, twice <= self.tolerance,
                                      pairs.end_gap(dx) >= twice - self.tolerance).all())
        return bool(torch.stack(checks).all())

    def settled_if_due(self, x: torch.Tensor, dx: torch.Tensor, pairs: "ContactPairs", active: torch.Tensor) -> bool:
        """:meth:`settled`, where the test is due: after tests that failed in a row it waits
        1, 2, 4, ... steps (at most :attr:`settled_wait`, ``SETTLED_WAIT`` by default), answering
        False (not known settled) without testing; a test that passes makes the next one due at
        once. One call a step."""
        if self._settled_left > 0:
            self._settled_left -= 1
            return False
        if self.settled(x, dx, pairs, active):
            self._settled_failures = 0
            return True
        self._settled_failures += 1
        self._settled_left = min(1 << min(self._settled_failures - 1, self.settled_wait.bit_length()),
                                 self.settled_wait)
        return False

    def candidates(self, x: torch.Tensor, v: Optional[torch.Tensor] = None, dt: float = 0.0, motion=None):
        """Broad phase at positions ``x [V, 3]``: (surface vertex ids into :attr:`vertices` ``[C]``,
        triangle ids ``[C]``), every vertex-triangle pair of different bodies (or allowed
        self-contact) whose triangle's box, grown by :attr:`reach`, meets the vertex's box.
        Given velocities ``v [V, 3]`` and a step ``dt`` (with ``Contact.swept``), the boxes are
        swept over the step in their body's moving frame (:meth:`_motion`): a triangle's holds
        it at x and at x + dt (v - V_body), a vertex's its segment likewise, grown by the most
        that a body its body may meet closes on it, dt |V_a - V_b| (a vertex arriving faster
        than the reach per step is found before it is inside); otherwise a vertex's box is its
        point. ``motion``: :meth:`_motion` ``(x, v, dt)`` when the caller has it. With
        ``Contact.skin``, the kept candidates where they still hold these (:meth:`_kept_candidates`).

        A spatial hash of cell size c = the largest triangle box side at x + 2 reach (motion does
        not grow it: a still triangle covers at most 2 cells per axis, a moving one as many as
        its swept box does, and a vertex's segment likewise). A pair meets in every cell both
        boxes cover; it is kept in one, the cell of the low corner of the boxes' intersection
        (``ops.contact.candidate_pairs``: the walk over the cells' entries is an op)."""
        return self._candidates(x, v, dt, motion)[:2]

    def _candidates(self, x: torch.Tensor, v: Optional[torch.Tensor], dt: float, motion):
        """:meth:`candidates`, and whether they come in a point query's order (by vertex, then
        triangle): a search without motion's, as the kept ones are, where a swept search lists a
        vertex's candidates cell after cell."""
        if self.settings.swept and v is not None and dt > 0:
            motion = self._motion(x, v, dt) if motion is None else motion
        else:
            motion = None
        if self.skin > 0 and len(self.triangles):
            kept = self._kept_candidates(x, motion)
            if kept is not None:
                return (*kept, True)
        return (*self._search(x, motion, self.reach), motion is None)

    def _kept_candidates(self, x: torch.Tensor, motion):
        """``Contact.skin``'s candidates for a query at ``x [V, 3]`` (``motion``: a swept query's
        :meth:`_motion`, or None), or None where a fresh search must answer.

        Kept candidates, found at positions x_k for triangles grown by reach + 2 skin, hold
        every pair a query at x meets when M + D + G / 2 <= skin, M the most a surface vertex
        moved from x_k, D the most one moves apart from its body over the step and G the most
        two bodies close on each other (a check's query: D = G = 0). A pair the query meets
        has a point q in both boxes: q is within D + G of the vertex at x, so within M + D + G
        of it at x_k, and within reach + D of the triangle's box at x, so within reach + D + M
        of it at x_k; the vertex at x_k is then within reach + 2 (M + D) + G <= reach + 2 skin
        of the triangle's box at x_k, which the kept search tested. Where the kept ones do not
        hold them but the query's own motion fits the skin, the candidates are found again
        at x (and kept); else the query's own search answers. One host read."""
        skin = self.skin
        points = x[self.vertices]
        need = points.new_zeros(())
        if motion is not None:
            deviation, _, grow = motion
            need = torch.linalg.vector_norm(deviation[self.vertices], dim=-1).amax() + 0.5 * grow.amax()
        kept = self._kept
        usable = (kept is not None and kept[1] == self.reach and kept[0].shape == points.shape
                  and kept[0].device == points.device and kept[0].dtype == points.dtype)
        moved = torch.linalg.vector_norm(points - kept[0], dim=-1).amax() if usable else points.new_full((), math.inf)
        moved, need = torch.stack([moved + need, need]).tolist()
        if moved <= skin:
            return kept[2]
        if need > skin:
            return None
        found = self._search(x, None, self.reach + 2.0 * skin)
        self._kept = (points.clone(), self.reach, found)
        return found

    def _first_triangles(self, triangle_object: torch.Tensor) -> torch.Tensor:
        """Where each body's triangles start ``[B + 1]`` among triangles in body order (``triangle_object``
        ascending)."""
        bodies = torch.arange(self.num_objects + 1, device=triangle_object.device)
        return torch.searchsorted(triangle_object, bodies)

    def _search(self, x: torch.Tensor, motion, reach: float, bodies: Optional[torch.Tensor] = None):
        """:meth:`candidates`' hash search at ``x [V, 3]``, swept by ``motion`` (:meth:`_motion`'s,
        or None), triangles grown by ``reach``; self-contact's exclusions by :attr:`reach`.
        ``bodies [B]`` (bool): among these bodies' surfaces only."""
        device = x.device
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        if len(self.triangles) == 0:
            return empty, empty
        triangles, triangle_object = self.triangles, self.triangle_object
        vertices, vertex_object = self.vertices, self.vertex_object
        first = None if self.settings.self_contact else self._triangle_first
        if bodies is not None:
            triangle_ids = bodies[triangle_object].nonzero().squeeze(1)
            vertex_ids = bodies[vertex_object].nonzero().squeeze(1)
            triangles, triangle_object = triangles[triangle_ids], triangle_object[triangle_ids]
            vertices, vertex_object = vertices[vertex_ids], vertex_object[vertex_ids]
            if len(triangles) == 0:
                return empty, empty
            first = None if first is None else self._first_triangles(triangle_object)  # (a subset keeps the order)
        corners = x[triangles]  # [F, 3, 3]
        low, high = corners.amin(1), corners.amax(1)
        cell = (high - low).amax() + 2.0 * reach  # a 0-dim tensor: no host read
        points = x[vertices]
        point_low = point_high = points  # (the same tensor: one query per vertex)
        if motion is not None:
            # in each body's moving frame, grown by what the bodies it may meet close on it
            deviation, _, grow = motion
            moved = corners + deviation[triangles]
            low, high = torch.minimum(low, moved.amin(1)), torch.maximum(high, moved.amax(1))
            ends = points + deviation[vertices]
            grow = grow[vertex_object][:, None]
            point_low, point_high = torch.minimum(points, ends) - grow, torch.maximum(points, ends) + grow
        vertex, triangle = contact_ops.candidate_pairs(cell, low - reach, high + reach, triangle_object,
                                                       point_low, point_high, vertex_object,
                                                       same_body=self.settings.self_contact, triangle_first=first)
        if bodies is not None:  # back to the surface's ids (ascending, as the subsets are)
            vertex, triangle = vertex_ids[vertex], triangle_ids[triangle]
        if not self.settings.self_contact:
            return vertex, triangle
        # self-contact: not the vertex's own triangles, nor those near it at rest
        node = self.vertices[vertex]
        tri = self.triangles[triangle]
        own = (tri == node[:, None]).any(1)
        same = self.vertex_object[vertex] == self.triangle_object[triangle]
        s_rest, _, _ = signed_distance(self.rest[node], *(self.rest[tri[:, i]] for i in range(3)))
        keep = (~same | (~own & (s_rest.abs() > self.reach))).nonzero().squeeze(1)
        return vertex[keep], triangle[keep]

    def nearby(self, x: torch.Tensor, v: Optional[torch.Tensor] = None, dt: float = 0.0, found=None):
        """Every pair a step at ``x [V, 3]`` may need, and which of them :meth:`detect` keeps:
        (pairs, closing ``[P]`` bool). The pairs: for each surface vertex and each other body,
        the nearest of its candidate triangles within :attr:`reach`, whatever its gap (without
        the exact Hessians; :meth:`select` adds them). closing: the gap is negative or, given
        the velocities ``v [V, 3]`` and a step ``dt``, the gap the pair would have after the step
        at those velocities, g + dt u . (v_p - sum w_i v_i), is (see the module).

        ``found``: candidates to take instead of a search, a list of runs (vertex ids, triangle
        ids, the bodies whose pairs the run leaves to another or None), each grouped by vertex
        (:meth:`relinearise`'s, from the step's start search: :meth:`_step_candidates`). A step's
        start query (``v`` and ``dt`` given) searches with its triangles grown by twice
        :attr:`check_margin` more and keeps its candidates for the step's checks; its pairs are
        the same (the narrow phase keeps only those within the reach)."""
        swept = self.settings.swept and v is not None and dt > 0
        margin = self.check_margin if found is None and v is not None and dt > 0 and len(self.triangles) else 0.0
        motion = self._motion(x, v, dt, self.reach + 2.0 * margin) if swept else None
        point_order = False  # whether the candidates come by vertex, then triangle (as a point query's)
        if margin > 0:
            candidates = self._search(x, motion, self.reach + 2.0 * margin)
            with torch.no_grad():  # (kept across the step: no autograd graph with it)
                predicted = x[self.vertices] if motion is None else x[self.vertices] + dt * v[self.vertices]
            self._step_search = (x, x._version, predicted, margin, candidates)
            self._check_search = None  # (the last step's)
            found, point_order = [(*candidates, None)], motion is None
        elif found is None:
            vertex, triangle, point_order = self._candidates(x, v, dt, motion)
            found = [(vertex, triangle, None)]
        spread = body_step = None
        if swept:  # what the pair may close over the step joins its reach
            deviation, body_step, _ = motion
            spread = torch.linalg.vector_norm(deviation, dim=-1)
        # the nearest triangle per (vertex, body), its side by the pseudonormal of the triangles
        # tied with it (ops.contact: the narrow phase as an op), over each run of candidates (a
        # (vertex, body)'s pair from the one run that gives it)
        runs = []
        for run_vertex, run_triangle, leaves in found:
            run = contact_ops.nearest_pairs(x, self.vertices, self.vertex_object, self.triangles, self.triangle_object,
                                            run_vertex, run_triangle, spread, body_step, self.reach)
            if leaves is not None:
                gives = (~leaves[self.vertex_object[run[0]]] & ~leaves[self.triangle_object[run[1]]]).nonzero()
                run = tuple(t[gives.squeeze(1)] for t in run)
            runs.append(run)
        vertex, triangle, w, diff, d, normal, side = runs[0] if len(runs) == 1 else (torch.cat(t) for t in zip(*runs))
        if not point_order:
            # a swept search's vertex may have candidates in several cells' runs, and its pairs
            # come in the order of their cells (which the cell's size sets), and given runs come
            # one after another: in a point query's order (by triangle, so by body), whatever the
            # search (the kept candidates, a point query's, are in it already)
            order = torch.argsort(vertex * len(self.triangles) + triangle)
            vertex, triangle, w, diff, d, normal, side = (t[order] for t in (vertex, triangle, w, diff, d, normal,
                                                                             side))
        node = self.vertices[vertex]
        tri = self.triangles[triangle]
        gap = side * d - self.settings.thickness
        nodes = torch.cat([node[:, None], tri], dim=1)
        objects = torch.stack([self.vertex_object[vertex], self.triangle_object[triangle]], dim=1)
        pairs = ContactPairs(nodes, w, _direction(diff, d, side, normal), side * d, gap, objects,
                             self.settings.stiffness, None, self.num_nodes)
        closing = gap < 0
        if v is not None and dt > 0:
            closing = closing | (pairs.end_gap(dt * v) < 0)
        if self.settings.friction > 0 and v is not None:
            pairs.friction = self._friction(pairs, v)
        return pairs, closing

    def select(self, x: torch.Tensor, pairs: ContactPairs, index: torch.Tensor) -> ContactPairs:
        """The pairs at ``index`` of :meth:`nearby`'s ``pairs`` (found at ``x [V, 3]``), with their
        exact Hessians where the tangent is ``"exact"``."""
        chosen = pairs.select(index)
        if self.settings.tangent == "exact":
            side = torch.where(chosen.signed >= 0, 1.0, -1.0).to(chosen.signed.dtype)
            chosen.hessians = _pair_energy_hessians(x, chosen.nodes, side, chosen.stiffness, self.settings.thickness)
        return chosen

    def relinearise(self, x: torch.Tensor, dx: torch.Tensor, pairs: ContactPairs, active: torch.Tensor,
                    v: Optional[torch.Tensor] = None, solution: int = -1, tolerance: Optional[float] = None,
                    later: bool = False):
        """The pairs a step from ``x [V, 3]`` needs once its solve moved the nodes by ``dx [V, 3]``:
        (pairs, active ``[P']`` bool, whether any pair changed), from :meth:`nearby`'s ``pairs``
        and the ``active`` mask the solve used.

        A pair's linear model g + u . J dx (its triangle, closest point and direction fixed where
        the step starts) misses the surface's curvature: a vertex sliding over a crease of the
        other surface, or across a triangle that turns, ends deeper than the model says, by
        about the slide times the turn. Where the surfaces at ``x + dx`` put a vertex deeper
        into a body than the active pairs' models do, by more than :attr:`tolerance`, that
        (vertex, body) takes the pair found there, linearised there: direction u_e, weights
        w_e and gap g_e at ``x + dx``, so that its model g_e + u_e . J_e (dx' - dx) is exact at
        the solution it was found from (written as a pair at x: gap g_e - u_e . J_e dx). A
        (vertex, body) has at most one pair (the new one replaces the old); ``v``: the
        velocities the friction coefficients are taken at (as :meth:`nearby`'s); ``solution``:
        which of the step's solves moved the nodes by ``dx`` (the new pairs' ``born``);
        ``tolerance``: in place of :attr:`tolerance` (a round's solve: :attr:`recheck_tolerance`);
        ``later``: the step checks a later solve too (its search may serve that check,
        :meth:`_step_candidates`)."""
        end, _ = self.nearby(x + dx, found=self._step_candidates(x, dx, later))
        objects = max(self.num_objects, 1)
        key = pairs.nodes[:, 0] * objects + pairs.objects[:, 1]
        end_key = end.nodes[:, 0] * objects + end.objects[:, 1]
        # the (vertex, body) of each pair at the end among the pairs: its model's end gap, or
        # +inf where it has no active pair (no force at all)
        model = torch.full_like(end.gap, math.inf)
        matched = torch.zeros_like(end_key, dtype=torch.bool)
        index = torch.zeros_like(end_key)
        if len(pairs):
            sorted_key, order = torch.sort(key)
            position = torch.searchsorted(sorted_key, end_key).clamp(max=len(pairs) - 1)
            matched = sorted_key[position] == end_key
            index = order[position]
            model = torch.where(matched & active[index], pairs.end_gap(dx)[index], model)
        tolerance = self.tolerance if tolerance is None else tolerance
        deeper = (end.gap < torch.clamp(model, max=0.0) - tolerance).nonzero().squeeze(1)
        fresh = end.select(deeper)
        fresh.gap = fresh.end_gap(-dx)  # g_e - u_e . J_e dx
        fresh.signed = fresh.gap + self.settings.thickness
        fresh.shift = dx[fresh.nodes]
        fresh.born = torch.full_like(fresh.gap, solution, dtype=torch.int64)
        if self.settings.friction > 0 and v is not None:
            fresh.friction = self._friction(fresh, v)
        # the pairs the fresh ones replace (an unmatched one's index goes to a spare slot, P: no
        # host read for the matched ones)
        keep = torch.ones(len(key) + 1, dtype=torch.bool, device=key.device)
        keep[torch.where(matched[deeper], index[deeper], len(key))] = False
        keep = keep[:-1].nonzero().squeeze(1)
        kept = pairs.select(keep)
        merged = ContactPairs(*(torch.cat([getattr(kept, f), getattr(fresh, f)])
                                for f in ("nodes", "weights", "direction", "signed", "gap", "objects")),
                              pairs.stiffness, None, pairs.num_nodes,
                              None if kept.friction is None else torch.cat([kept.friction, fresh.friction]),
                              *((None, None) if kept.shift is None and not deeper.numel() else (
                                  torch.cat([kept.direction.new_zeros(len(kept), 4, 3) if kept.shift is None
                                             else kept.shift, fresh.shift]),
                                  torch.cat([torch.full_like(kept.gap, -1, dtype=torch.int64) if kept.born is None
                                             else kept.born, fresh.born]))))
        active = torch.cat([active[keep], torch.ones_like(fresh.gap, dtype=torch.bool)])
        return merged, active, deeper.numel() > 0

    @torch.no_grad()
    def _step_candidates(self, x: torch.Tensor, dx: torch.Tensor, later: bool = False):
        """Candidates for a check at ``x + dx`` (``x, dx [V, 3]``) from the step's start search at
        ``x`` (:meth:`nearby`): a list of runs (vertex ids, triangle ids, bodies ``[B]`` bool whose
        pairs the run does not give, or None), each grouped by vertex, which together hold every
        pair a fresh search at ``x + dx`` finds, each (vertex, body)'s candidates in the one run
        that gives its pair; None where a fresh search is the cheaper (or the step's search is
        another state's). One host read where no body ended past the margin, three where a later
        check takes the first's search, a search's more otherwise.

        The start search swept each surface point from x to its predicted end x + dt v (in its
        body's moving frame, grown by what the bodies it may meet close on it, :meth:`_motion`),
        triangles grown by reach + 2 m (m: the margin). Where a vertex p and a triangle T's nodes
        end within m (each axis) of their predicted ends, e = dx - dt v, and the pair is within
        the reach at x + dx, p at its predicted end is within reach + |e_p| + |e_T| <= reach + 2 m
        of T's nodes at theirs, which that search's boxes held. So the kept candidates serve
        every pair of two bodies whose surfaces all ended within the margin; the pairs of a body
        that did not (a tumbling block the solve stopped) are searched again among the bodies
        within the reach of it at x + dx.

        With ``later`` (the step checks a later solve too), that search is grown and kept for it:
        it holds the pairs within reach + 4 m at x + dx_1, among the bodies whose boxes come within
        reach + 4 m of one past the margin there. A later check at x + dx_2 whose bodies past the
        margin were all past at x + dx_1, and moved at most 2 m since (each axis), takes it as it
        is: every other body ended both checks within m of its prediction, so it moved at most 2 m
        too, and a pair within the reach at x + dx_2 was within reach + 4 m at x + dx_1."""
        start = self._step_search
        if start is None or start[0] is not x or start[1] != x._version:
            return None
        _, _, predicted, margin, (vertex, triangle) = start
        y = x + dx
        points = y[self.vertices]
        past = self._per_body_max((points - predicted).abs().amax(-1)) > margin  # [B]
        moved = past.nonzero().squeeze(1)
        if len(moved) == 0:
            return [(vertex, triangle, None)]
        held = self._check_search
        found = None
        if held is not None and held[0] is start:
            _, first_points, first_past, found = held
            drift = self._per_body_max((points - first_points).abs().amax(-1))
            if not bool(~(past & ~first_past).any() & (torch.where(first_past, drift, 0.0).amax() <= 2.0 * margin)):
                found = None
        if found is None:
            # the bodies within the reach (grown for a later check) of a moved one, at y (boxes
            # of their surfaces)
            grown = self.reach + 4.0 * margin if later else self.reach
            lower, upper = self._body_boxes(points)
            near = past.clone()
            for rows in moved.split(BODY_ROWS):  # [rows, B] at a time
                near |= self._boxes_meet(lower, upper, rows, grown).any(0)
            if 2 * int(near[self.vertex_object].sum()) > len(self.vertices):
                return None  # half the surfaces or more: one search of all is the cheaper
            found = self._search(y, None, grown, near)
            self._check_search = (start, points, past, found) if later else None
        near_vertex, near_triangle = found
        again = (past[self.vertex_object[near_vertex]] | past[self.triangle_object[near_triangle]]).nonzero()
        again = again.squeeze(1)
        # the kept candidates whole (filtering millions of them costs more than dropping the
        # pairs of the bodies past the margin once the narrow phase found them)
        return [(vertex, triangle, past), (near_vertex[again], near_triangle[again], None)]

    @property
    def tolerance(self) -> float:
        """How much deeper than its pair's linear model a vertex may end a step before the step
        is solved again with the pair linearised where it ends (:meth:`relinearise`), and how
        deep a vertex with no pair may end before its pair joins the step: ``Contact.tolerance``,
        by default 1/400 of :attr:`search` (by default the mean surface edge length), a geometric
        error small against the 1 % of an edge that the contact's interpenetration is held to."""
        return 0.0025 * self.search if self.settings.tolerance is None else float(self.settings.tolerance)

    @property
    def recheck_tolerance(self) -> float:
        """:attr:`tolerance` for the check of a round's solve: ``Contact.recheck_tolerance``, by
        default 1/100 of :attr:`search`, and at least :attr:`tolerance`."""
        recheck = self.settings.recheck_tolerance
        return max(self.tolerance, 0.01 * self.search if recheck is None else float(recheck))

    def detect(self, x: torch.Tensor, v: Optional[torch.Tensor] = None, dt: float = 0.0) -> ContactPairs:
        """The pairs in contact at ``x [V, 3]``: for each surface vertex and each body, the nearest
        of its candidate triangles within :attr:`reach`, where the gap is negative, or, given the
        velocities ``v [V, 3]`` and a step ``dt``, where the gap the pair would have after the
        step at those velocities, g + dt u . (v_p - sum w_i v_i), is negative (see the module).
        """
        pairs, closing = self.nearby(x, v, dt)
        return self.select(x, pairs, closing.nonzero().squeeze(1))

    def _friction(self, pairs: ContactPairs, v: torch.Tensor) -> torch.Tensor:
        """``[P]`` the pairs' friction damping mu lambda / max(|v_t|, eps_v) at velocities ``v``,
        lambda = k max(0, -g) the normal force: Coulomb's mu lambda opposing a slip faster than
        eps_v, a viscous drag below it (zero for pairs only predicted to touch)."""
        return coulomb_damping(self.settings.friction, pairs.stiffness * torch.clamp(-pairs.gap, min=0.0),
                               torch.linalg.vector_norm(pairs.slip(v), dim=-1), self.settings.friction_velocity)

    def detect_at_state(self, x: torch.Tensor, v: torch.Tensor, dt: float) -> ContactPairs:
        """:meth:`detect` ``(x, v, dt)``, found once per state: the pairs found at the end of a step
        (for its report) serve the next step's linearisation. The same tensors, unchanged since
        (their in-place version counters), with the same dt, give the same pairs."""
        return self.at_state(x, v, dt)[2]

    def at_state(self, x: torch.Tensor, v: torch.Tensor, dt: float):
        """(:meth:`nearby`'s pairs and closing mask, :meth:`detect`'s pairs) at ``(x, v, dt)``,
        found once per state as in :meth:`detect_at_state`."""
        last = self._last
        if (last is not None and last[0] is x and last[1] == x._version and last[2] is v
                and last[3] == v._version and last[4] == dt):
            return last[5]
        near, closing = self.nearby(x, v, dt)
        found = (near, closing, self.select(x, near, closing.nonzero().squeeze(1)))
        self._last = (x, x._version, v, v._version, dt, found)
        return found

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """The penalty energy (0-dim) at ``x [V, 3]`` (pairs found at x)."""
        return self._pairs_at(x).energy()

    def forces(self, x: torch.Tensor) -> torch.Tensor:
        """The penalty forces ``[V, 3]`` at ``x [V, 3]``."""
        return self._pairs_at(x).forces()

    def dforces(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """(df/dx) dx ``[V, 3]`` at ``x [V, 3]`` for node motions ``dx [V, 3]``, with the pairs in
        contact at x (the contacts' interface of ``solve_static``: its CG products at one x
        share the pairs, found once)."""
        return self._pairs_at(x).dforces(dx)

    def _pairs_at(self, x: torch.Tensor) -> ContactPairs:
        """:meth:`detect` ``(x)``, found once for the same tensor unchanged (its version)."""
        last = self._static
        if last is None or last[0] is not x or last[1] != x._version:
            self._static = last = (x, x._version, self.detect(x))
        return last[2]

    def with_values(self, stiffness: Optional[float] = None, thickness: Optional[float] = None) -> "SurfaceContact":
        """This contact with another penalty ``stiffness`` and ``thickness`` (None: kept), its
        tensors and its search shared (a differentiable step's own values: ``solver.adjoint``)."""
        changes = {name: float(value) for name, value in (("stiffness", stiffness), ("thickness", thickness))
                   if value is not None}
        other = copy.copy(self)
        other.settings = dataclasses.replace(self.settings, **changes)
        other._last = other._static = other._kept = other._step_search = other._check_search = None
        other.first_check_found = False
        other._settled_failures = other._settled_left = 0
        return other

    def to(self, device=None, dtype=None) -> "SurfaceContact":
        """This contact with its tensors on ``device`` (rest positions in ``dtype``)."""
        rest = self.rest.to(device=device, dtype=dtype)
        other = SurfaceContact(self.triangles.to(rest.device), self.node_object.to(rest.device), rest,
                               self.settings)
        other.search = self.search
        return other


def coupled_ranges(pairs: ContactPairs, num_objects: int) -> List[int]:
    """The object ranges ``[0, ..., B]`` (a ptr) of the solves a step with these pairs needs: runs of
    consecutive objects such that each pair's two bodies lie in one run (every object alone
    where no pair joins two)."""
    ends = list(range(1, num_objects + 1))
    if len(pairs) == 0:
        return [0] + ends
    lo = pairs.objects.amin(1)
    hi = pairs.objects.amax(1)
    # reach[i]: the furthest object a run starting at or before i must cover; a run ends at i
    # where nothing before or at i joins anything after it
    objects = torch.arange(num_objects, device=lo.device)
    reach = torch.cummax(objects.scatter_reduce(0, lo, hi, "amax"), 0).values
    return [0] + ((reach == objects).nonzero().squeeze(1) + 1).tolist()
