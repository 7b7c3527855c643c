"""The implicit Euler step as a differentiable function, by the adjoint method.

One linearised step (``implicit_euler_step``, ``newton_iters=1``) solves ``A dv = b`` with

    A(x)          = c_M M - c_K K(x)                       c_M = 1 + h r_M, c_K = h (h + r_K)
    b(x, v)       = h (f(x) + f_ext + (h + r_K) K(x) v - r_M M v)
    v' = v + dv,  x' = x + h v'

(K: the elastic, planes', tools' and body contact's stiffness the solver uses; constrained rows: dv is imposed
there and the system holds the free rows only). Written as a residual of the free rows,

    R(dv; x, v, theta) = c_M M dv + h r_M M v - h (f(x) + f_ext) - c_K K(x) (dv + v),

the step's dv is the root of R, and A = dR/d(dv) is symmetric. For a loss L with cotangents
g_x' = dL/dx', g_v' = dL/dv', the velocity change's cotangent is g = g_v' + h g_x', and by the
implicit-function theorem, for any input p of R (x, v, the imposed velocities, f_ext, M, the
material through f and K, and the planes' and tools' values through their forces and stiffness):

    A lam = P g                  (the adjoint solve: the step's own operator and CG; P: free rows)
    dL/dp += -lam . dR/dp        (one vector-Jacobian product of R: autograd through the ops)

plus the direct terms of v' = v + dv and x' = x + h v'. No tape is kept through the CG's
iterations: a step's backward is one solve and one pass of the ops' gradients (K's derivative
along lam for the non-linear models: stvk's, and the corotational rotations').

Contact between bodies enters R through its pairs' forces and projected stiffness. Which surface
vertex meets which triangle, and on which side, are discrete choices, held as the forward made
them (the gradient exists where a small change of the inputs keeps them); each pair's closest
point, direction and gap are functions of x and of the contact's stiffness and thickness
(``body_contact.HeldPairs``). A step whose contact set took several solves holds pairs that were
linearised where an earlier solve ended (at x + h v_q): its backward goes back through those
solves, one adjoint solve each (``DifferentiableStep._contact_solves_backward``).

This is the gradient of the *converged* step at the states the forward computed. Where the
forward stops CG on a budget (``require_convergence=False``) its dv is not A^-1 b and the
returned gradient is not that of the truncated computation: it is the adjoint of the exact
step, evaluated along the inexact trajectory (``sim.rollout``'s ``exact=True`` converges both
solves instead).
"""
from __future__ import annotations

import contextlib
import dataclasses
from typing import Optional

import torch

from ..errors import SolverError
from ..physics.body_contact import HeldPairs
from .capture import run_captured
from .cg import BREAKDOWN, CONVERGED, NONFINITE
from .implicit_euler import (
    DynamicsSystem,
    StepOptions,
    _coefficients,
    _raise_if_failed,
    _solve,
    auto_cg_max_iter,
    implicit_euler_step,
)


@dataclasses.dataclass
class DifferentiableStep:
    """What :class:`ImplicitStep` needs beyond its tensors: the packed ``system`` it steps, the
    options of the forward solve (``forward``) and of the adjoint solve (``adjoint``), and the
    model's differentiable view (``physics.differentiable.DifferentiableModel``)."""

    system: DynamicsSystem
    forward: StepOptions
    adjoint: StepOptions
    model: object
    #: every solve of a contact set to the forward's cg_tol (the contact's check_tol off): the
    #: backward takes each as the root of its residual, which a solve paused for a check is not
    exact_contact_solves: bool = True
    _backward_graphs: dict = dataclasses.field(default_factory=dict, repr=False)

    def step(self, x, v, imposed, external, contact: dict):
        """The forward step from ``x, v [V, 3]`` (``imposed``: the constrained nodes' end
        velocities or None; ``external``: this step's external forces ``[V, 3]`` in place of the
        system's, or None; ``contact``: values of :data:`CONTACT_VALUES` and
        :data:`BODY_CONTACT_VALUES` in place of the system's, None where kept): ``(x', v',
        solves)``, solves: each solve of the step's contact set (``StepReport.contact_solves``:
        its pairs and end velocities), or None without body contact."""
        with self._written(external, contact), self._checks_converged():
            # (detached: the body contact keeps the state it last found pairs at, which must not
            # hold the rollout's autograd graph alive)
            x_new, v_new, report = implicit_euler_step(self.system, x.detach(), v.detach(), self.forward,
                                                       None if imposed is None else imposed.detach())
        return x_new, v_new, report.contact_solves

    @contextlib.contextmanager
    def _checks_converged(self):
        """The body contact's ``check_tol`` off for the body of the ``with`` where
        ``exact_contact_solves`` asks for it (its settings restored after, whatever happens)."""
        body = self.system.body_contact
        if not self.exact_contact_solves or body is None or body.settings.check_tol is None:
            yield
            return
        settings = body.settings
        body.settings = dataclasses.replace(settings, check_tol=None)
        try:
            yield
        finally:
            body.settings = settings

    @contextlib.contextmanager
    def _written(self, external, contact: dict):
        """The system's external forces and contact values replaced by those given (None: kept)
        for the body of the ``with``: written in place (captured graphs read that storage) and
        restored after, whatever happens; the body contact's stiffness and thickness (numbers
        in its settings) by a copy of it with those values in the system's place."""
        system = self.system
        body = system.body_contact
        if body is not None and any(contact.get(name) is not None for name in BODY_CONTACT_VALUES):
            system.body_contact = body.with_values(**{setting: contact.get(name)
                                                      for name, setting in BODY_CONTACT_VALUES.items()})
        targets = [(system.external, external)] + [
            (getattr(getattr(system, owner), attribute), contact.get(name))
            for name, (owner, attribute) in CONTACT_VALUES.items() if getattr(system, owner) is not None]
        swaps = [(target, value) for target, value in targets if value is not None]
        kept = [target.clone() for target, _ in swaps]
        for target, value in swaps:
            target.copy_(value)
        try:
            yield
        finally:
            for (target, _), old in zip(swaps, kept):
                target.copy_(old)
            system.body_contact = body

    def residual(self, x, v, dv, external, mass, young, poisson, contact: dict, pairs=None,
                 shift=None) -> torch.Tensor:
        """``R(dv; x, v, ...)`` ``[V, 3]`` of the module's docstring, every row (the caller keeps the
        free ones): ``external`` None leaves f_ext out (a constant: no gradient needs its value),
        ``mass [V]``, ``young, poisson [N]``, ``contact``: values of :data:`CONTACT_VALUES` and
        :data:`BODY_CONTACT_VALUES` (None: the system's), ``pairs``: the body contact's pairs the
        solve held (``body_contact.ContactPairs``; their forces and stiffness as
        ``body_contact.HeldPairs``, with ``shift`` in place of theirs where given) or None."""
        opts = self.forward
        h = opts.dt
        mass_coef, stiffness_coef = _coefficients(opts)
        system = self.system
        w = dv + v
        elastic = self.model.step_forces(x - system.model.rest, w, h, stiffness_coef, young, poisson)
        m = mass[:, None]
        residual = mass_coef * m * dv - elastic
        for term in system.contacts:
            if term is system.planes:
                term = term.replaced(contact.get("plane_offsets"), contact.get("plane_stiffness"))
            elif term is system.tools:
                term = term.replaced(contact.get("tool_origins"), contact.get("tool_stiffness"))
            residual = residual - h * term.forces(x) - stiffness_coef * term.dforces(x, w)
        if pairs is not None and len(pairs):
            settings = system.body_contact.settings
            held = HeldPairs(pairs, **{setting: getattr(settings, setting) if contact.get(name) is None
                                       else contact[name] for name, setting in BODY_CONTACT_VALUES.items()},
                             shift=shift)
            residual = residual - h * held.forces(x) - stiffness_coef * held.dforces(x, w)
        if opts.rayleigh_mass:
            residual = residual + (h * opts.rayleigh_mass) * m * v
        if external is not None:
            residual = residual - h * external
        return residual

    def backward(self, rhs: torch.Tensor, saved: dict, wanted: frozenset) -> dict:
        """The adjoint solve ``A lam = rhs`` (``rhs [V, 3]``: P g) and ``-lam . dR/dp`` for p = x, v and
        the inputs named in ``wanted`` (of :data:`_INPUTS`), at the step whose tensors ``saved``
        holds (x, v, v_new, imposed, mass, young, poisson, the values of :data:`CONTACT_VALUES` and
        :data:`BODY_CONTACT_VALUES`, None where absent, and ``solves``, the step's contact-set
        solves or None): ``{name: gradient}``, zeros where R does not depend on p. Raises
        SolverError where the solve fails.

        With body contact, the step's end velocities are those of its last contact-set solve,
        whose pairs include pairs linearised at an earlier solve's end (their shift: that
        solve's motion). The backward then goes back through the solves
        (:meth:`_contact_solves_backward`).

        On CUDA (``forward.cuda_graphs``), where the solve is one device op (the device deciding
        when it stops), the solve and the product, R's graph and its backward, run as one CUDA
        graph per pattern of wanted and absent inputs (:meth:`prepare_backward`): a rollout's
        steps differ only in their values, and a step's backward is otherwise hundreds of small
        launches (more than their arithmetic). The solve's outcome is read once after."""
        with self._written(None, {name: saved[name] for name in CONTACT_VALUES}):  # A(x) of the forward's contact
            captured = self._captured_backward(saved, wanted)
            if saved.get("solves"):
                return self._contact_solves_backward(rhs, saved, wanted)
            if captured is None:
                lam = self.adjoint_solve(saved["x"], rhs)
                return self._residual_vjp(lam, saved, wanted)
            captured.load(rhs, saved)
            run_captured(captured.graphs, "backward", captured.work)
            status = captured.cg.state.status
            failed = (status == BREAKDOWN) | (status == NONFINITE)
            if self.adjoint.require_convergence:
                failed = failed | (status != CONVERGED)
            if bool(failed.any()):  # the one synchronisation; the report only where it failed
                _raise_if_failed(captured.cg.result(), self.adjoint, "the adjoint solve of a step")
        return {name: t.clone() for name, t in captured.out.items()}

    def prepare_backward(self, saved: dict, wanted: frozenset) -> None:
        """Capture the backward's graph for this pattern of inputs now, at the forward's step
        (``saved``, ``wanted`` as :meth:`backward`; its right-hand side zero), where it is
        captured and not yet made. Captured here, on the caller's thread: inside the backward,
        autograd's other threads may touch the device while the graph is being captured, which
        spoils the capture."""
        captured = self._captured_backward(saved, wanted)
        if captured is None or "backward" in captured.graphs or _saved_tensor_hooks_active():
            # (hooks: inside torch.utils.checkpoint's forward, whose hooks would count the
            # capture's own saved tensors, and torch.func refuses to run under them: the
            # backward captures)
            return
        with self._written(None, {name: saved[name] for name in CONTACT_VALUES}):
            captured.load(torch.zeros_like(saved["x"]), saved)
            run_captured(captured.graphs, "backward", captured.work)

    def _captured_backward(self, saved: dict, wanted: frozenset) -> Optional["_CapturedBackward"]:
        """The backward's buffers and graphs for this pattern of wanted and absent inputs (made
        where absent), or None where the backward is not captured (not CUDA, no CUDA graphs, a
        scaled or several-op adjoint solve)."""
        x = saved["x"]
        if not (self.forward.cuda_graphs and x.device.type == "cuda") or self.system.body_contact is not None:
            return None  # (body contact: each step's pairs differ in number, and its forward is eager)
        key = (wanted, tuple(name for name, t in saved.items() if t is None))
        captured = self._backward_graphs.get(key)
        if captured is None:
            matvec = self._adjoint_matvec()
            cg = None if matvec is None else self.system.cg_solver(x, cuda_graphs=True)
            if cg is None or not cg.solves_in_one_op(matvec):
                return None
            captured = self._backward_graphs[key] = _CapturedBackward(
                self, wanted, matvec, cg, torch.zeros_like(x),
                {name: None if t is None else t.detach().clone() for name, t in saved.items()})
        return captured

    def _adjoint_matvec(self):
        """The step's fused system product (``SystemMatvec``) where the adjoint solve can use it
        directly (no preconditioner scaling), else None."""
        if self.adjoint.preconditioner in ("jacobi", "rigid", "multigrid", "cholesky"):
            return None
        return self.system.system_matvec(*_coefficients(self.adjoint), self.adjoint.pipelined, self.adjoint.variants)

    def _contact_solves_backward(self, rhs: torch.Tensor, saved: dict, wanted: frozenset) -> dict:
        """:meth:`backward` of a step with body contact: its solves r = R .. 0 (``saved["solves"]``),
        each solve's end velocities v_r = v + dv_r (the constrained rows: imposed) the root of its
        own residual R_r (its pairs; a pair linearised at solve q's end has the shift h v_q). The
        cotangent c_r of v_r (c_R: the step's, ``rhs``; an earlier one's: what the later pairs'
        shifts give it) takes one adjoint solve with solve r's operator, A_r lam = P c_r, and one
        vjp of R_r, which also gives the cotangents of the solves its shifts came from; plus
        v_r's direct terms (the last solve's are :class:`ImplicitStep`'s)."""
        solves, imposed, free = saved["solves"], saved["imposed"], self.system.free
        last = len(solves) - 1
        cotangents = {last: rhs}
        total = {}
        for r in range(last, -1, -1):
            c = cotangents.pop(r, None)
            if c is None:
                continue
            if r < last:
                if imposed is None or free is None:
                    direct = {"v": c}
                else:
                    direct = {"v": c * free, "imposed": c * (1.0 - free)}
                _accumulate(total, direct)
                if free is not None:
                    c = c * free
            lam = self.adjoint_solve(saved["x"], c, solves[r][0])
            got = self._residual_vjp(lam, saved, wanted, solve=r)
            for q, g in got.pop("solutions").items():
                cotangents[q] = g if q not in cotangents else cotangents[q] + g
            _accumulate(total, got)
        if "imposed" in total and "imposed" not in wanted:
            del total["imposed"]
        return total

    def _residual_vjp(self, lam: torch.Tensor, saved: dict, wanted: frozenset, solve: Optional[int] = None) -> dict:
        """``-lam . dR/dp`` ``{name: [...]}`` for x, v and the inputs named in ``wanted`` at the step
        ``saved`` holds (as :meth:`backward`'s). ``solve``: with body contact, the contact-set
        solve whose residual (its pairs, its end velocities) this is; its earlier solves' end
        velocities are then inputs too, their cotangents returned under ``"solutions"``
        (``{solve: [V, 3]}``)."""
        x, v, v_new = saved["x"], saved["v"], saved["v_new"]
        pairs = None
        if solve is not None:
            pairs, v_new = saved["solves"][solve]
        free = self.system.free
        with torch.enable_grad():
            leaves = {}

            def leaf(name):
                t = saved[name]
                if t is None or name not in wanted:
                    return t
                t = t.detach().requires_grad_(True)
                leaves[name] = t
                return t

            # x and v are leaves whenever anything is asked: R's value depends on them
            x_ = x.detach().requires_grad_(True)
            v_ = v.detach().requires_grad_(True)
            imposed_ = leaf("imposed")
            external_ = None
            if "external" in wanted:
                external_ = torch.zeros_like(x).requires_grad_(True)  # R is affine in f_ext
                leaves["external"] = external_
            mass_, young_, poisson_ = (leaf(name) for name in ("mass", "young", "poisson"))
            contact = {name: leaf(name) for name in _CONTACT_INPUTS}
            # dv: its free rows as solved (constants), its constrained rows imposed by the inputs
            dv = (v_new - v) if free is None else (v_new - v) * free
            if imposed_ is not None:
                dv = dv + (1.0 - free) * (imposed_ - v_)
            # pairs linearised at an earlier solve's end: their shift h v_q, v_q an input
            shift, earlier = None, {}
            if pairs is not None and pairs.born is not None:
                shift = pairs.shift
                for q in pairs.born.unique().tolist():
                    if q >= 0:
                        earlier[q] = saved["solves"][q][1].detach().requires_grad_(True)
                        moved = self.forward.dt * earlier[q][pairs.nodes]
                        shift = torch.where((pairs.born == q)[:, None, None], moved, shift)
            residual = self.residual(x_, v_, dv, external_, mass_, young_, poisson_, contact, pairs, shift)
            inputs = {"x": x_, "v": v_, **leaves, **{("solution", q): t for q, t in earlier.items()}}
            grads = torch.autograd.grad((lam * residual).sum(), list(inputs.values()), allow_unused=True)
        out = {name: (torch.zeros_like(t) if g is None else -g) for (name, t), g in zip(inputs.items(), grads)}
        if solve is not None:
            out["solutions"] = {q: out.pop(("solution", q)) for q in earlier}
        return out

    def adjoint_solve(self, x, rhs, pairs=None) -> torch.Tensor:
        """lam ``[V, 3]`` with A(x) lam = rhs on the free rows (0 on the constrained ones);
        ``pairs``: the body contact's pairs the forward step held, or None."""
        result = _solve(self.system, x, rhs, self.adjoint, pairs=pairs)
        _raise_if_failed(result, self.adjoint, "the adjoint solve of a step")
        return result.solution


@dataclasses.dataclass
class _CapturedBackward:
    """:meth:`DifferentiableStep.backward` as a CUDA graph: its input buffers (the adjoint solve's
    right-hand side ``rhs`` and the step's tensors ``saved``), the solve's product and CG, the
    graphs (``solver.capture.run_captured``'s) and the buffers ``out`` the graph writes its gradients
    into."""

    step: "DifferentiableStep"
    wanted: frozenset
    matvec: object
    cg: object
    rhs: torch.Tensor
    saved: dict
    graphs: dict = dataclasses.field(default_factory=dict)
    out: dict = dataclasses.field(default_factory=dict)

    def load(self, rhs: torch.Tensor, saved: dict) -> None:
        """Copy a step's right-hand side and tensors into the buffers the graph reads."""
        self.rhs.copy_(rhs)
        for name, t in saved.items():
            if t is not None:
                self.saved[name].copy_(t)

    def work(self) -> None:
        """The device work the graph holds: load the operator at x, solve in one op, the vjp."""
        opts = self.step.adjoint
        self.matvec.load(self.saved["x"])
        self.cg.begin(self.matvec, self.rhs, opts.cg_tol, opts.cg_max_iter, opts.cg_max_iter)
        grads = self.step._residual_vjp(self.cg.state.x, self.saved, self.wanted)
        if not self.out:  # the first, eager, run: the buffers the graph will write
            self.out.update({name: torch.empty_like(g) for name, g in grads.items()})
        for name, g in grads.items():
            self.out[name].copy_(g)


class ImplicitStep(torch.autograd.Function):
    """``(x', v') = step(x, v)`` with the adjoint backward of the module's docstring.

    Inputs: the :class:`DifferentiableStep`; positions, velocities ``[V, 3]``; the constrained
    nodes' end velocities ``[V, 3]`` or None (fixed nodes stay at rest); the step's external
    forces ``[V, 3]`` or None (the system's); lumped masses ``[V]``; per-element Young's moduli
    and Poisson ratios ``[N]``; the planes' offsets and stiffness ``[P]``, the tools' origins
    ``[T, 3]`` (where they are at the step's end) and stiffness ``[T]``, the body contact's
    stiffness and thickness (0-dim), each or None (theirs).
    Masses and material must be those the system was built with (the forward reads the
    system's; the backward differentiates through these).
    """

    @staticmethod
    def forward(ctx, step: DifferentiableStep, x, v, imposed, external, mass, young, poisson, plane_offsets=None,
                plane_stiffness=None, tool_origins=None, tool_stiffness=None, contact_stiffness=None,
                contact_thickness=None):
        contact = dict(plane_offsets=plane_offsets, plane_stiffness=plane_stiffness, tool_origins=tool_origins,
                       tool_stiffness=tool_stiffness, contact_stiffness=contact_stiffness,
                       contact_thickness=contact_thickness)
        with torch.no_grad():
            x_new, v_new, solves = step.step(x, v, imposed, external, contact)
        ctx.step = step
        # the contact set's solves (their pairs are constants of the step), each end velocity a
        # detached alias: the last is the output v_new, whose grad_fn is this node (a reference
        # cycle through the autograd graph, which Python's collector cannot see, would leak it)
        ctx.solves = None if solves is None else [(pairs, end.detach()) for pairs, end in solves]
        ctx.save_for_backward(x, v, imposed, mass, young, poisson, v_new, *contact.values())
        if any(ctx.needs_input_grad):
            step.prepare_backward(dict(x=x, v=v, v_new=v_new, imposed=imposed, mass=mass, young=young,
                                       poisson=poisson, solves=solves, **contact), _wanted(ctx.needs_input_grad))
        return x_new, v_new

    @staticmethod
    def backward(ctx, g_x, g_v):
        step: DifferentiableStep = ctx.step
        x, v, imposed, mass, young, poisson, v_new, *contact = ctx.saved_tensors
        h = step.forward.dt
        free = step.system.free
        if g_x is None:
            g_x = torch.zeros_like(x)
        if g_v is None:
            g_v = torch.zeros_like(v)
        g_dv = g_v + h * g_x
        needs = ctx.needs_input_grad
        wanted = _wanted(needs)
        got = step.backward(g_dv if free is None else g_dv * free,
                            dict(x=x, v=v, v_new=v_new, imposed=imposed, mass=mass, young=young, poisson=poisson,
                                 solves=ctx.solves, **dict(zip(_CONTACT_INPUTS, contact))), wanted)
        # the direct terms: x' = x + h v', v' = v + dv (constrained rows: v' = imposed there)
        grad_x = got["x"] + g_x
        if imposed is None:
            grad_v = got["v"] + g_dv
            grad_imposed = None
        else:
            grad_v = got["v"] + g_dv * free
            grad_imposed = got["imposed"] + g_dv * (1.0 - free) if "imposed" in got else None
        return (None, grad_x if needs[1] else None, grad_v if needs[2] else None, grad_imposed,
                *(got.get(name) for name in list(_INPUTS)[1:]))


#: The contact values a differentiable step takes in place of the system's: name -> (the system's
#: contact term, its attribute), each written in place for the forward (captured steps read it)
CONTACT_VALUES = {"plane_offsets": ("planes", "offsets"), "plane_stiffness": ("planes", "stiffness"),
                  "tool_origins": ("tools", "origins"), "tool_stiffness": ("tools", "stiffness")}
#: The body contact's values a differentiable step takes in place of its settings: name -> the
#: ``body_contact.Contact`` setting (numbers: the forward steps a copy of the contact with them)
BODY_CONTACT_VALUES = {"contact_stiffness": "stiffness", "contact_thickness": "thickness"}
_CONTACT_INPUTS = (*CONTACT_VALUES, *BODY_CONTACT_VALUES)
#: ImplicitStep's inputs that can take a gradient, by their position in ``forward``'s arguments
_INPUTS = {"imposed": 3, "external": 4, "mass": 5, "young": 6, "poisson": 7,
           **{name: 8 + i for i, name in enumerate(_CONTACT_INPUTS)}}


def differentiable_step(system: DynamicsSystem, forward: StepOptions, adjoint: StepOptions,
                        make_model, exact: bool = True) -> DifferentiableStep:
    """The system's :class:`DifferentiableStep` for these options, made once (``make_model()``:
    its differentiable model) and kept on the system: rollouts of one simulator then share its
    captured backward graphs, which read the model's tensors and the options' numbers.
    ``exact``: as :func:`adjoint_options`' (every solve of a contact set converged too)."""
    key = (dataclasses.astuple(forward), dataclasses.astuple(adjoint), bool(exact))
    step = system._differentiable_steps.get(key)
    if step is None:
        step = system._differentiable_steps[key] = DifferentiableStep(system, forward, adjoint, make_model(),
                                                                      bool(exact))
    return step


def _accumulate(total: dict, terms: dict) -> None:
    """``total[name] += terms[name]`` for each name (set where absent)."""
    for name, t in terms.items():
        total[name] = t if name not in total else total[name] + t


def _saved_tensor_hooks_active() -> bool:
    """Whether saved-tensor hooks (``torch.autograd.graph.saved_tensors_hooks``) are in force on
    this thread: disabling them refuses exactly then."""
    try:
        with torch.autograd.graph.disable_saved_tensors_hooks("saved-tensor hooks are active"):
            return False
    except RuntimeError:
        return True


def _wanted(needs) -> frozenset:
    """The names (of :data:`_INPUTS`) of the inputs whose gradient ``needs`` asks for."""
    return frozenset(name for name, i in _INPUTS.items() if needs[i])


def check_differentiable(system: DynamicsSystem, opts: StepOptions) -> None:
    """Raise SolverError naming what this system has that the adjoint step does not differentiate."""
    reasons = []
    if opts.newton_iters != 1:
        reasons.append(f"newton_iters={opts.newton_iters} (the adjoint is that of one linearisation: use 1)")
    if opts.integrator != "backward_euler":
        reasons.append(f"integrator={opts.integrator!r} (the adjoint is backward Euler's)")
    if system.tools is not None and system.tools.has_friction:
        reasons.append("tools with friction")
    body = system.body_contact
    if body is not None and body.settings.friction > 0:
        reasons.append("contact between bodies with friction")
    if body is not None and body.settings.tangent != "projected":
        reasons.append(f"contact between bodies with tangent={body.settings.tangent!r} (use 'projected')")
    if system.planes is not None and system.planes.has_friction:
        reasons.append("planes with friction")
    if reasons:
        raise SolverError("gradients through this simulation are not available: it has " + "; ".join(reasons)
                          + ". Differentiable steps support elastic bodies, fixed and prescribed nodes, "
                          "gravity, external forces, frictionless planes, tools and contact between bodies")


def adjoint_options(opts: StepOptions, exact: bool, tol: Optional[float] = None, free_dofs: int = 0):
    """(forward, adjoint) step options. ``exact``: both solves converged to ``tol`` (None: the
    forward's cg_tol) within at least ``auto_cg_max_iter(free_dofs)`` iterations (the largest
    object's free degrees of freedom: a budget is lifted), a solve that does not converge
    raising; otherwise both as ``opts`` run (a fixed CG budget accepted where ``opts`` accepts it)."""
    if not exact:
        return opts, opts
    tol = opts.cg_tol if tol is None else float(tol)
    converged = dataclasses.replace(opts, cg_tol=tol, require_convergence=True,
                                    cg_max_iter=max(opts.cg_max_iter, auto_cg_max_iter(free_dofs)))
    return converged, converged

__all__ = ["BODY_CONTACT_VALUES", "CONTACT_VALUES", "DifferentiableStep", "ImplicitStep", "SolverError",
           "adjoint_options", "check_differentiable", "differentiable_step"]
