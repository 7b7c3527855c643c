"""Differentiable rollouts: a simulation's trajectory as tensors autograd reaches through.

``tm.rollout(sim, steps, young=..., forces=...)`` steps a copy of the simulator's state (the
simulator itself is not advanced) with the adjoint step of ``solver.adjoint``: the trajectory it
returns carries gradients back to the initial positions and velocities, the per-element Young's
moduli, Poisson ratios and densities, gravity and the external node forces of each step, the
planes', tools' and body contact's values, and, through the prescribed nodes' imposed
velocities, to whatever the positions depend on.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from os import PathLike
from typing import List, Optional, Sequence

import torch
from torch.utils.checkpoint import checkpoint

from ..errors import SceneError
from ..physics.differentiable import DifferentiableModel, check_per_element
from ..solver.adjoint import ImplicitStep, adjoint_options, check_differentiable, differentiable_step
from .simulator import Body, Simulator


@dataclass
class Rollout:
    """A trajectory: ``x, v [F, V, 3]`` at the steps ``frames`` (step 0 is the initial state), over
    the simulator's node rows (``sim.x``'s: bodies in order, spare rows included)."""

    x: torch.Tensor
    v: torch.Tensor
    frames: List[int]


def rollout(sim, steps: int, *, x0: Optional[torch.Tensor] = None, v0: Optional[torch.Tensor] = None,
            young=None, poisson=None, density=None, gravity=None, forces: Optional[torch.Tensor] = None,
            prescribed: Optional[torch.Tensor] = None, plane_offsets=None, plane_stiffness=None,
            tool_positions: Optional[torch.Tensor] = None, tool_stiffness=None, contact_stiffness=None,
            contact_thickness=None, exact: bool = True,
            cg_tol: Optional[float] = None, checkpoint_every: Optional[int] = None,
            frames: Optional[Sequence[int]] = None) -> Rollout:
    """``steps`` implicit Euler steps of ``sim`` from its state (or ``x0, v0``), differentiable.

    Every argument left None is the simulator's own (no gradient); a tensor that requires grad
    gets one through every step by the adjoint method (``solver.adjoint``).

    Args:
        sim: the simulator (not advanced: its state, time and caches of solves stay as they are),
            a built-in or file scene (``tm.load_scene``'s), or a scene file's path.
        steps: number of steps (>= 1).
        x0, v0: initial positions and velocities ``[V, 3]`` (V = ``sim.x.shape[0]``).
        young, poisson, density: a scalar or one value per element ``[N]`` in the simulator's
            element numbering (bodies in order, ``sim.element_ptr``). Given any of them, the steps
            run on a simulator built again with these values (detached).
        gravity: ``[3]``.
        forces: external node forces ``[V, 3]`` on every step, or ``[steps, V, 3]`` one per step.
        prescribed: the prescribed nodes' positions at the end of each step ``[steps, P, 3]`` (P:
            the prescribed nodes, bodies in order, each body's in ascending node order), in place
            of the bodies' ``motion``; their imposed velocities take them there from where they are.
        plane_offsets, plane_stiffness: the planes' offsets d (n . x >= d outside) and penalty
            stiffness ``[P]``, in the order the simulator was given them.
        tool_positions: the tools' origins at the end of each step ``[steps, T, 3]``, in place of
            their paths (tools in the order the simulator was given them).
        tool_stiffness: the tools' penalty stiffness ``[T]``.
        contact_stiffness, contact_thickness: the contact between bodies' penalty stiffness k and
            thickness delta (numbers or 0-dim tensors), in place of its ``tm.Contact``'s. The
            gradient is that of each step with its contact pairs held: which vertex meets which
            triangle, on which side (``solver.adjoint``).
        exact: converge the forward and the adjoint solves (to ``cg_tol``, default the
            simulator's; every solve of a step's contact set too, ``tm.Contact``'s check_tol
            aside): the gradient is that of the computed trajectory. False: the solves run as
            the simulator's options say; with a fixed CG budget the gradient is then the
            adjoint of the converged steps along the truncated trajectory (``solver.adjoint``).
        checkpoint_every: keep the state every k steps only and recompute the steps in between
            during the backward (memory ~ steps / k + k states instead of ~ steps); None: keep all.
        frames: the steps whose states are returned (default: all, 0 .. steps).

    Returns:
        :class:`Rollout`.

    Raises:
        SceneError for bad arguments; SolverError where the simulation has something the
        adjoint does not differentiate (friction, the exact tangent of contact between bodies,
        several Newton iterations, removed or cut elements) or a solve fails. Nothing of ``sim`` is changed.
    """
    sim = _simulator_of(sim)
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise SceneError(f"steps must be a positive integer, got {steps!r}")
    if checkpoint_every is not None and (isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int)
                                         or checkpoint_every < 1):
        raise SceneError(f"checkpoint_every must be a positive integer or None, got {checkpoint_every!r}")
    if sim.scalpels:
        raise SceneError("a simulator with scalpels changes its mesh as it steps: rollouts do not differentiate cuts")
    like = sim.x
    num_elements = sim.element_ptr[-1]
    young = check_per_element("young", young, num_elements, like, 0.0, float("inf"))
    poisson = check_per_element("poisson", poisson, num_elements, like, -1.0, 0.5)
    density = check_per_element("density", density, num_elements, like, 0.0, float("inf"))
    x = _state("x0", x0, sim.x)
    v = _state("v0", v0, sim.v)
    gravity = _vector("gravity", gravity, sim.gravity)
    forces = _forces(forces, steps, like)
    prescribed = _prescribed(sim, prescribed, steps)
    plane_offsets, plane_stiffness = (_plane_values(sim, name, value, low) for name, value, low in
                                      (("plane_offsets", plane_offsets, -float("inf")),
                                       ("plane_stiffness", plane_stiffness, 0.0)))
    tool_origins = _tool_origins(sim, tool_positions, steps)
    tool_stiffness = _tool_stiffness(sim, tool_stiffness)
    contact_stiffness = _contact_value(sim, "contact_stiffness", contact_stiffness, positive=True)
    contact_thickness = _contact_value(sim, "contact_thickness", contact_thickness, positive=False)
    frames = _frames(frames, steps)

    stepping = sim if young is None and poisson is None and density is None else \
        _rebuilt(sim, young, poisson, density)
    free_dofs = max(3 * int((~(b.fixed | b.prescribed)).sum()) for b in sim.bodies)
    forward, adjoint = adjoint_options(stepping.options, exact, cg_tol, free_dofs)
    check_differentiable(stepping.system, forward)
    DifferentiableModel.check(stepping.model)  # also where the view was made by an earlier rollout
    step = differentiable_step(stepping.system, forward, adjoint, lambda: DifferentiableModel(stepping.model),
                              exact)
    model = step.model
    young_all = model.per_element("young", young)
    poisson_all = model.per_element("poisson", poisson)
    mass = stepping.system.mass[:, 0] if density is None else model.lumped_mass(model.per_element("density", density))
    with_external = gravity is not None or forces is not None or density is not None
    g = sim.gravity if gravity is None else gravity
    h = forward.dt
    start = sim.time
    rows = _prescribed_rows(stepping) if stepping._has_prescribed else None  # found once, not per step

    def run(first: int, count: int, x, v):
        """Steps first+1 .. first+count from x, v: (x, v, the frames' states among them)."""
        kept = []
        for n in range(first, first + count):
            imposed = None if rows is None else _imposed_velocity(
                stepping, rows, x, start + (n + 1) * h, h, None if prescribed is None else prescribed[n])
            external = None
            if with_external:
                external = mass[:, None] * g
                if forces is not None:
                    external = external + (forces[n] if forces.dim() == 3 else forces)
            x, v = ImplicitStep.apply(step, x, v, imposed, external, mass, young_all, poisson_all, plane_offsets,
                                      plane_stiffness, None if tool_origins is None else tool_origins[n],
                                      tool_stiffness, contact_stiffness, contact_thickness)
            if n + 1 in frames:
                kept.append((x, v))
        return x, v, kept

    recorded = [(x, v)] if 0 in frames else []
    chunk = checkpoint_every or steps
    for first in range(0, steps, chunk):
        count = min(chunk, steps - first)
        if checkpoint_every is None:
            x, v, kept = run(first, count, x, v)
        else:
            def segment(x, v, first=first, count=count):
                x, v, kept = run(first, count, x, v)
                return (x, v, *[t for pair in kept for t in pair])

            x, v, *flat = checkpoint(segment, x, v, use_reentrant=False)
            kept = list(zip(flat[0::2], flat[1::2]))
        recorded.extend(kept)
    return Rollout(torch.stack([s[0] for s in recorded]), torch.stack([s[1] for s in recorded]), sorted(frames))


def _simulator_of(sim) -> Simulator:
    """The simulator of a simulator, a scene (``sim.builtin.Scene``) or a scene file's path."""
    if isinstance(sim, (str, PathLike)):
        from .scene_file import load_scene

        sim = load_scene(sim)
    sim = getattr(sim, "simulator", sim)
    if not isinstance(sim, Simulator):
        raise SceneError(f"rollout steps a tm.Simulator, a scene or a scene file's path; got {type(sim).__name__}")
    if sim._held is not None:
        raise SceneError("rollout: the simulator holds nodes (hold_nodes); release them (release_nodes) or give "
                         "their path as prescribed nodes")
    return sim


def _checked(name: str, value, shapes, expected: str, like: torch.Tensor) -> torch.Tensor:
    """``value`` after checking it is a tensor of one of ``shapes`` (``expected`` says which, in the
    error) with finite entries, in ``like``'s dtype and on its device (its graph kept)."""
    if not isinstance(value, torch.Tensor) or tuple(value.shape) not in [tuple(s) for s in shapes]:
        shape = tuple(value.shape) if isinstance(value, torch.Tensor) else type(value).__name__
        raise SceneError(f"{name} must have shape {expected}, got {shape}")
    if not bool(torch.isfinite(value.detach()).all()):
        raise SceneError(f"{name} has NaN or inf entries")
    return value.to(dtype=like.dtype, device=like.device)


def _state(name: str, value, own: torch.Tensor) -> torch.Tensor:
    if value is None:
        return own.detach()
    return _checked(name, value, [own.shape], f"{tuple(own.shape)} (the simulator's node rows)", own)


def _vector(name: str, value, own: torch.Tensor) -> Optional[torch.Tensor]:
    if value is None:
        return None
    t = value if isinstance(value, torch.Tensor) else torch.as_tensor(value, dtype=own.dtype)
    if t.shape != own.shape or not bool(torch.isfinite(t.detach()).all()):
        raise SceneError(f"{name} must be {own.shape[0]} finite numbers, got {t.detach().tolist()}")
    return t.to(dtype=own.dtype, device=own.device)


def _forces(forces, steps: int, like: torch.Tensor) -> Optional[torch.Tensor]:
    if forces is None:
        return None
    return _checked("forces", forces, [like.shape, (steps, *like.shape)],
                    f"{tuple(like.shape)} (every step) or {(steps, *like.shape)} (one per step)", like)


def _plane_values(sim: Simulator, name: str, value, low: float) -> Optional[torch.Tensor]:
    """``value`` (None, or one number per plane ``[P]``) checked: finite, above ``low``."""
    if value is None:
        return None
    count = 0 if sim.planes is None else len(sim.planes)
    if count == 0:
        raise SceneError(f"{name} was given, but the simulator has no planes")
    value = value if isinstance(value, torch.Tensor) else torch.as_tensor(value, dtype=sim.dtype)
    value = _checked(name, value, [(count,)], f"({count},) (one per plane)", sim.x)
    if bool((value.detach() <= low).any()):
        raise SceneError(f"{name} must be > {low:g}, got {value.detach().tolist()}")
    return value


def _tool_origins(sim: Simulator, tool_positions, steps: int) -> Optional[torch.Tensor]:
    """The tools' origins at the end of each step ``[steps, T, 3]``: ``tool_positions`` checked, or
    their paths' (None without tools). A rollout writes each step's into the tools (restored
    after) rather than moving them, so the simulator's tools stay where they are."""
    count = 0 if sim.tools is None else len(sim.tools)
    if tool_positions is not None:
        if count == 0:
            raise SceneError("tool_positions was given, but the simulator has no tools")
        return _checked("tool_positions", tool_positions, [(steps, count, 3)],
                        f"{(steps, count, 3)} (each step's end origin of the {count} tools)", sim.x)
    if count == 0:
        return None
    h = sim.options.dt
    path = [[list(tool.origin(sim.time + (n + 1) * h)) for tool in sim.tools.tools] for n in range(steps)]
    return torch.tensor(path, dtype=sim.dtype).to(sim.device)


def _tool_stiffness(sim: Simulator, value) -> Optional[torch.Tensor]:
    """``value`` (None, or one number per tool ``[T]``) checked: finite and positive."""
    if value is None:
        return None
    count = 0 if sim.tools is None else len(sim.tools)
    if count == 0:
        raise SceneError("tool_stiffness was given, but the simulator has no tools")
    value = value if isinstance(value, torch.Tensor) else torch.as_tensor(value, dtype=sim.dtype)
    value = _checked("tool_stiffness", value, [(count,)], f"({count},) (one per tool)", sim.x)
    if bool((value.detach() <= 0).any()):
        raise SceneError(f"tool_stiffness must be > 0, got {value.detach().tolist()}")
    return value


def _contact_value(sim: Simulator, name: str, value, positive: bool) -> Optional[torch.Tensor]:
    """``value`` (None, or one number) checked: finite, > 0 (``positive``) or >= 0."""
    if value is None:
        return None
    if sim.body_contact is None:
        raise SceneError(f"{name} was given, but the simulator has no contact between bodies (tm.Contact)")
    value = value if isinstance(value, torch.Tensor) else torch.as_tensor(value, dtype=sim.dtype)
    value = _checked(name, value, [()], "() (one number)", sim.x)
    if bool(value.detach() <= 0) if positive else bool(value.detach() < 0):
        raise SceneError(f"{name} must be {'> 0' if positive else '>= 0'}, got {float(value.detach())}")
    return value


def _frames(frames, steps: int) -> set:
    if frames is None:
        return set(range(steps + 1))
    chosen = set()
    for f in frames:
        if isinstance(f, bool) or not isinstance(f, int) or not 0 <= f <= steps:
            raise SceneError(f"frames must be steps in 0 .. {steps}, got {f!r}")
        chosen.add(f)
    if not chosen:
        raise SceneError("frames is empty: name at least one step to return")
    return chosen


def _rebuilt(sim: Simulator, young, poisson, density) -> Simulator:
    """``sim`` built again with per-element material values (detached; None: the body's own)."""
    if "removed" in sim.model._buffers:
        raise SceneError("rollouts with new material values rebuild the simulator, which a simulator whose "
                         "elements were removed or cut cannot be: build one from the remaining mesh")
    bodies = []
    for i, body in enumerate(sim.bodies):
        lo, hi = sim.element_ptr[i], sim.element_ptr[i + 1]
        changes = {name: value.detach().expand(sim.element_ptr[-1])[lo:hi]
                   for name, value in (("young", young), ("poisson", poisson), ("density", density))
                   if value is not None}
        material = dataclasses.replace(body.material, **changes)
        bodies.append(Body._trusted(body.mesh, material, body.fixed, body.prescribed, body.motion, body.name))
    spare = [sim.ptr[i + 1] - sim.ptr[i] - sim.used_nodes[i] for i in range(len(sim.bodies))]
    rebuilt = Simulator(bodies, spare_nodes=spare, **sim._init_args)
    rebuilt.options = sim.options
    return rebuilt


def _prescribed_rows(sim: Simulator) -> torch.Tensor:
    """The prescribed nodes' rows of ``sim.x`` ``[P]``, bodies in order, ascending in each."""
    rows = [torch.nonzero(b.prescribed.to(sim.device)).flatten() + sim.ptr[i] for i, b in enumerate(sim.bodies)]
    return torch.cat(rows)


def _prescribed(sim: Simulator, prescribed, steps: int) -> Optional[torch.Tensor]:
    if prescribed is None:
        return None
    count = int(sum(int(b.prescribed.sum()) for b in sim.bodies))
    if count == 0:
        raise SceneError("prescribed positions were given, but the simulator has no prescribed nodes")
    return _checked("prescribed", prescribed, [(steps, count, 3)],
                    f"{(steps, count, 3)} (each step's end positions of the {count} prescribed nodes)", sim.x)


def _imposed_velocity(sim: Simulator, rows: torch.Tensor, x: torch.Tensor, t_next: float, h: float,
                      targets: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The prescribed nodes' (``rows [P]``) end velocities ``[V, 3]`` taking them from ``x`` to
    ``targets [P, 3]`` (None: their motion at ``t_next``), 0 elsewhere, differentiable in x and
    targets."""
    if targets is None:
        parts = []
        for i, body in enumerate(sim.bodies):
            if body.motion is None:
                continue
            count = int(body.prescribed.sum())
            target = torch.as_tensor(body.motion(t_next), dtype=x.dtype, device=x.device)
            if target.shape != (count, 3):
                raise SceneError(f"body {i}: motion(t) returned shape {tuple(target.shape)}; expected [{count}, 3]")
            parts.append(target)
        targets = torch.cat(parts)
    goal = torch.zeros_like(x).index_copy(0, rows, targets)
    mask = torch.zeros(x.shape[0], 1, dtype=x.dtype, device=x.device).index_fill(0, rows, 1.0)
    return mask * (goal - x) / h
