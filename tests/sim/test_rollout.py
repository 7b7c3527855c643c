"""Differentiable rollouts (``tm.rollout``, ``solver.adjoint``): gradients of a loss on the
trajectory against central finite differences of the forward in float64, for every parameter
kind, model and element kind; gradcheck; checkpointing; the CPU extension against pure torch;
bad input."""
import numpy as np
import pytest
import torch

import tensormass_torch as tm
from tests.conftest import build_scene, on_each_cpu_backend, random_material

STEPS = 3


def _sim(rng, kind: str, model: str, steps_before: int = 2, **options):
    """A small float64 simulator of one body held at one end, deformed by a few steps. stvk with
    its exact tangent: the definite one's positive part of S has kinks where an eigenvalue
    crosses 0, which central differences straddle (its gradient: gradcheck, the rest test)."""
    scene = build_scene(rng, kind)
    material = random_material(rng, model, young=float(rng.uniform(5e3, 2e4)))
    rest = scene.mesh.vertices
    fixed = rest[:, 0] < rest[:, 0].min() + 1e-6 if kind == "tet" else rest[:, 0] < rest[:, 0].min() + 0.1
    defaults = dict(dt=0.01, cg_tol=1e-13, rayleigh_mass=0.1, rayleigh_stiffness=0.01)
    defaults.update(options)
    sim = tm.Simulator([tm.Body(scene.mesh, material, fixed=fixed)], **defaults)
    if steps_before:
        sim.step(steps_before)
    return sim


def _loss(sim, weights, **kwargs):
    """A loss on every frame's positions and velocities of a rollout."""
    run = tm.rollout(sim, STEPS, **kwargs)
    return (run.x * weights[0]).sum() + 0.3 * (run.v * weights[1]).sum()


def _directional_error(sim, weights, name, value, rng, **fixed_kwargs) -> float:
    """|g . d - (L(p + e d) - L(p - e d)) / 2e| / |g . d| for a random direction d."""
    leaf = value.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(_loss(sim, weights, **{name: leaf}, **fixed_kwargs), leaf)
    direction = torch.tensor(rng.standard_normal(tuple(value.shape)), dtype=value.dtype)
    eps = 1e-5 * float(value.abs().mean().clamp_min(1e-2))
    with torch.no_grad():
        plus = _loss(sim, weights, **{name: value + eps * direction}, **fixed_kwargs)
        minus = _loss(sim, weights, **{name: value - eps * direction}, **fixed_kwargs)
    fd = float(plus - minus) / (2 * eps)
    analytic = float((grad * direction).sum())
    return abs(analytic - fd) / abs(fd)


def _parameters(sim, rng):
    """One value of every parameter kind the rollout differentiates."""
    V, N = sim.x.shape[0], sim.element_ptr[-1]
    young = float(sim.bodies[0].material.young)
    f = lambda *shape: torch.tensor(rng.standard_normal(shape), dtype=torch.float64)  # noqa: E731
    return {
        "x0": sim.x + 1e-3 * f(V, 3),
        "v0": sim.v + 1e-2 * f(V, 3),
        "gravity": torch.tensor([0.5, 1.0, -9.81], dtype=torch.float64),
        "forces": f(STEPS, V, 3),
        "young": torch.tensor(young, dtype=torch.float64),
        "young_per_element": young * (1 + 0.2 * torch.tensor(rng.uniform(size=N))),
        "poisson": 0.3 + 0.1 * torch.tensor(rng.uniform(size=N)),
        "density": 1000 * (1 + 0.3 * torch.tensor(rng.uniform(size=N))),
    }


@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
@pytest.mark.parametrize("kind", ["tet", "tri3d"])
def test_gradients_match_finite_differences(rng, kind, model):
    """Every parameter kind, against central differences: relative error <= 1e-6."""
    sim = _sim(rng, kind, model)
    V = sim.x.shape[0]
    weights = [torch.tensor(rng.standard_normal((STEPS + 1, V, 3))) for _ in range(2)]
    errors = {}
    for label, value in _parameters(sim, rng).items():
        name = "young" if label == "young_per_element" else label
        errors[label] = _directional_error(sim, weights, name, value, rng)
    assert max(errors.values()) <= 1e-6, errors


def test_prescribed_nodes_and_a_floor(rng):
    """A beam whose held end is moved (prescribed nodes: their imposed velocities depend on the
    positions) falling onto a floor plane it reaches during the rollout."""
    scene = build_scene(rng, "tet")
    rest = scene.mesh.vertices
    held = rest[:, 0] < rest[:, 0].min() + 1e-6
    start = rest[held].clone()
    body = tm.Body(scene.mesh, random_material(rng, "corotational", young=3e3), prescribed=held,
                   motion=lambda t: start + torch.tensor([0.0, 0.0, -2.0 * t], dtype=torch.float64))
    floor = rest[:, 2].min() - 0.004
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-13, planes=[tm.Plane((0, 0, 1), float(floor), 3e4)])
    sim.step(2)
    run = tm.rollout(sim, STEPS)
    assert bool((run.x[-1, :, 2] < floor).any()), "the scene must touch the floor"
    V = sim.x.shape[0]
    weights = [torch.tensor(rng.standard_normal((STEPS + 1, V, 3))) for _ in range(2)]
    params = _parameters(sim, rng)
    for name in ("x0", "v0", "young", "forces"):
        assert _directional_error(sim, weights, name, params[name], rng) <= 1e-6, name
    # the held end's path as a tensor in place of its motion: the same trajectory, and its gradient
    path = torch.stack([start + torch.tensor([0.0, 0.0, -2.0 * (sim.time + (n + 1) * 0.01)], dtype=torch.float64)
                        for n in range(STEPS)])
    torch.testing.assert_close(tm.rollout(sim, STEPS, prescribed=path).x, run.x, rtol=0, atol=1e-12)
    assert _directional_error(sim, weights, "prescribed", path, rng) <= 1e-6
    # the floor's offset and stiffness, at the simulator's values and at others (the adjoint
    # solve's operator is then that of the given planes, not the simulator's)
    for offset, stiffness in ((float(floor), 3e4), (float(floor) + 0.002, 9e4)):
        for name, value in (("plane_offsets", torch.tensor([offset], dtype=torch.float64)),
                            ("plane_stiffness", torch.tensor([stiffness], dtype=torch.float64))):
            assert _directional_error(sim, weights, name, value, rng) <= 1e-6, name
    given = dict(plane_offsets=torch.tensor([float(floor) + 0.002], dtype=torch.float64),
                 plane_stiffness=torch.tensor([9e4], dtype=torch.float64))
    assert _directional_error(sim, weights, "x0", params["x0"], rng, **given) <= 1e-6
    with pytest.raises(tm.SceneError, match=r"plane_stiffness must be > 0"):
        tm.rollout(sim, STEPS, plane_stiffness=torch.tensor([-1.0], dtype=torch.float64))
    with pytest.raises(tm.SceneError, match=r"prescribed must have shape \(3, %d, 3\)" % int(held.sum())):
        tm.rollout(sim, STEPS, prescribed=path[:, 1:])


def test_gradcheck_on_a_tiny_scene():
    """torch.autograd.gradcheck of two steps of six tetrahedra (initial state, moduli, forces)."""
    mesh = tm.beam_mesh(1, 1, 1, size=(0.2, 0.1, 0.1), dtype=torch.float64)
    fixed = mesh.vertices[:, 0] < 1e-9
    sim = tm.Simulator([tm.Body(mesh, tm.Material(young=1e4, poisson=0.3, model="stvk"), fixed=fixed)],
                       dt=0.01, cg_tol=1e-14)
    sim.step(2)
    V, N = sim.x.shape[0], sim.element_ptr[-1]

    def positions(x0, young, forces):
        return tm.rollout(sim, 2, x0=x0, young=young, forces=forces, frames=[2]).x

    x0 = sim.x.clone().requires_grad_(True)
    young = torch.full((N,), 1e4, dtype=torch.float64, requires_grad=True)
    forces = torch.zeros(V, 3, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(positions, (x0, young, forces), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_a_rollout_steps_as_the_simulator_and_changes_nothing(rng):
    """Without parameters the trajectory is the simulator's (to rounding); the simulator is not
    advanced."""
    sim = _sim(rng, "tet", "corotational")
    x, v, time = sim.x.clone(), sim.v.clone(), sim.time
    run = tm.rollout(sim, STEPS)
    assert torch.equal(sim.x, x) and torch.equal(sim.v, v) and sim.time == time
    assert torch.equal(run.x[0], x) and run.frames == list(range(STEPS + 1))
    sim.step(STEPS)
    torch.testing.assert_close(run.x[-1], sim.x, rtol=0, atol=1e-12)
    torch.testing.assert_close(run.v[-1], sim.v, rtol=0, atol=1e-10)


def test_checkpointing_gives_the_same_gradients(rng):
    """States kept every 2 steps, the rest recomputed in the backward: the same gradients."""
    sim = _sim(rng, "tet", "stvk")
    N = sim.element_ptr[-1]
    grads = []
    for every in (None, 2):
        young = torch.full((N,), 1e4, dtype=torch.float64, requires_grad=True)
        v0 = sim.v.clone().requires_grad_(True)
        run = tm.rollout(sim, 5, young=young, v0=v0, checkpoint_every=every, frames=[5])
        (run.x.square().sum() + run.v.sum()).backward()
        grads.append((young.grad, v0.grad))
    for a, b in zip(*grads):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=0)


@pytest.mark.parametrize("model,rotation,kind", [("stvk", "polar", "tet"), ("corotational", "polar", "tet"),
                                                 ("corotational", "qr", "tet"), ("corotational", "polar", "tri")])
def test_gradients_from_rest_are_finite(model, rotation, kind):
    """At rest the stvk stress is 0 and the deformation gradient I (all eigenvalues, all singular
    values equal), where eigh's and svd's own backwards divide by 0: the definite tangent's
    positive part and the polar rotation have derivatives of their own there."""
    if kind == "tet":
        mesh = tm.beam_mesh(2, 1, 1, size=(0.2, 0.1, 0.1), dtype=torch.float64)
    else:
        mesh = tm.beam_tri_mesh(2, 1, size=(0.2, 0.1), dim=3, dtype=torch.float64)
    material = tm.Material(young=1e4, poisson=0.3, model=model, rotation=rotation, thickness=0.01)
    sim = tm.Simulator([tm.Body(mesh, material, fixed=mesh.vertices[:, 0] < 1e-9)], dt=0.01, cg_tol=1e-12)
    young = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
    x0 = sim.x.clone().requires_grad_(True)
    tm.rollout(sim, 2, young=young, x0=x0).x[-1, :, 2].sum().backward()
    assert torch.isfinite(young.grad) and bool(torch.isfinite(x0.grad).all()) and float(young.grad) != 0.0


def test_the_cpu_extension_and_pure_torch_agree(rng, monkeypatch):
    def run():
        sim = _sim(np.random.default_rng(7), "tet", "corotational")
        young = torch.tensor(1e4, dtype=torch.float64, requires_grad=True)
        x0 = sim.x.clone().requires_grad_(True)
        tm.rollout(sim, STEPS, young=young, x0=x0).x.square().sum().backward()
        return young.grad, x0.grad

    for a, b in zip(*on_each_cpu_backend(monkeypatch, run)):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-12)


def test_a_budgeted_simulator_differentiates_exactly_by_default(rng):
    """A simulator on a fixed CG budget: ``exact=True`` (default) converges both solves; with
    ``exact=False`` the forward keeps the budget and the gradient differs."""
    sim = _sim(rng, "tet", "hooke", cg_max_iter=3, require_convergence=False, cg_tol=1e-12)
    young = torch.tensor(1e4, dtype=torch.float64)
    grads = []
    for exact in (True, False):
        leaf = young.clone().requires_grad_(True)
        run = tm.rollout(sim, STEPS, young=leaf, exact=exact, frames=[STEPS])
        run.x.square().sum().backward()
        grads.append(float(leaf.grad))
    assert grads[0] != grads[1]
    assert np.isfinite(grads).all()


def test_bad_input_gives_one_clear_error(rng):
    sim = _sim(rng, "tet", "hooke", steps_before=0)
    x = sim.x.clone()
    N, V = sim.element_ptr[-1], sim.x.shape[0]
    cases = [
        (dict(steps=0), r"steps must be a positive integer"),
        (dict(young=torch.ones(N + 1)), r"young has shape \(%d,\); expected a scalar or \[%d\]" % (N + 1, N)),
        (dict(young=torch.tensor(float("nan"))), r"young must be finite"),
        (dict(poisson=torch.tensor(0.5)), r"poisson must be finite and in \(-1, 0.5\)"),
        (dict(density=torch.tensor(-1.0)), r"density must be finite and in \(0, inf\)"),
        (dict(x0=torch.zeros(V - 1, 3)), r"x0 must have shape \(%d, 3\)" % V),
        (dict(forces=torch.zeros(2, V, 3)), r"forces must have shape"),
        (dict(gravity=[0.0, float("inf"), 0.0]), r"gravity must be 3 finite numbers"),
        (dict(frames=[STEPS + 1]), r"frames must be steps in 0 \.\. 3"),
        (dict(checkpoint_every=0), r"checkpoint_every must be a positive integer"),
        (dict(contact_stiffness=1e3), r"contact_stiffness was given, but the simulator has no contact between"),
    ]
    for kwargs, message in cases:
        steps = kwargs.pop("steps", STEPS)
        with pytest.raises(tm.SceneError, match=message):
            tm.rollout(sim, steps, **kwargs)
    assert torch.equal(sim.x, x) and sim.time == 0.0


@pytest.mark.parametrize("shape", ["sphere", "box"])
def test_tools_pressing_on_a_beam(rng, shape):
    """A tool moving down into a held beam (the projected tangent of a curved sphere, a box's
    flat face): gradients of its path, its stiffness, the initial positions and the moduli
    against central differences; a path equal to the tool's keyframes gives the same rollout."""
    scene = build_scene(rng, "tet")
    rest = scene.mesh.vertices
    body = tm.Body(scene.mesh, random_material(rng, "corotational", young=3e3), fixed=rest[:, 0] < rest[:, 0].min() + 1e-6)
    top = float(rest[:, 2].max())
    start, end = (0.9, 0.4, top + 0.18), (0.9, 0.4, top + 0.02)
    size = dict(sphere=dict(radius=0.2), box=dict(half_extents=(0.2, 0.5, 0.2)))[shape]
    tool = (tm.Sphere if shape == "sphere" else tm.Box)(**size, stiffness=2e4, times=(0.0, 0.05), positions=(start, end))
    sim = tm.Simulator([body], dt=0.01, cg_tol=1e-13, gravity=(0.0, 0.0, 0.0), tools=[tool])
    sim.step(1)
    run = tm.rollout(sim, STEPS)
    path = torch.tensor([list(tool.origin(sim.time + (n + 1) * 0.01)) for n in range(STEPS)],
                        dtype=torch.float64)[:, None, :]
    assert bool((sim.tools.replaced(path[-1]).penetration(run.x[-1]) > 0).any()), "the tool must touch the beam"
    torch.testing.assert_close(tm.rollout(sim, STEPS, tool_positions=path).x, run.x, rtol=0, atol=1e-12)
    V = sim.x.shape[0]
    weights = [torch.tensor(rng.standard_normal((STEPS + 1, V, 3))) for _ in range(2)]
    params = _parameters(sim, rng)
    assert _directional_error(sim, weights, "tool_positions", path, rng) <= 1e-6
    assert _directional_error(sim, weights, "tool_stiffness", torch.tensor([3e4], dtype=torch.float64), rng) <= 1e-6
    for name in ("x0", "young"):
        assert _directional_error(sim, weights, name, params[name], rng) <= 1e-6, name
    origin = tuple(sim.tools.origins[0].tolist())
    with pytest.raises(tm.SceneError, match=r"tool_positions must have shape \(3, 1, 3\)"):
        tm.rollout(sim, STEPS, tool_positions=path[:2])
    with pytest.raises(tm.SceneError, match=r"tool_stiffness must be > 0"):
        tm.rollout(sim, STEPS, tool_stiffness=torch.tensor([0.0], dtype=torch.float64))
    assert tuple(sim.tools.origins[0].tolist()) == origin and sim.time == 0.01  # nothing of sim changed


def _blocks_in_contact(rough: bool = False, device="cpu", **contact):
    """A small block pressed by gravity onto a larger one held at its base (float64, corotational),
    after three steps: every step of a rollout from there has pairs between the two. ``rough``:
    the larger one's top nodes jittered (a surface of turning triangles)."""
    material = tm.Material(young=2e4, poisson=0.3, density=1000, model="corotational")
    lower = tm.beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=torch.float64)
    if rough:
        jitter = torch.rand(lower.vertices.shape, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
        lower = tm.TetMesh(lower.vertices + 0.004 * (jitter - 0.5) * (lower.vertices[:, 2:] > 0.05), lower.elements)
    upper = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), origin=(0.05, 0.06, 0.098), dtype=torch.float64)
    settings = dict(stiffness=2e3, thickness=0.005)
    settings.update(contact)
    sim = tm.Simulator([tm.Body(lower, material, fixed=lower.vertices[:, 2] < 1e-6), tm.Body(upper, material)],
                       dt=0.01, cg_tol=1e-13, contact=tm.Contact(**settings), rayleigh_mass=0.1, device=device)
    sim.step(3)
    return sim


def _contact_solves(monkeypatch) -> list:
    """Record each differentiable step's contact-set solves: per step, (solves, pairs of its last
    solve linearised at an earlier solve's end)."""
    from tensormass_torch.solver.adjoint import DifferentiableStep

    seen, step = [], DifferentiableStep.step

    def recording(self, *args):
        out = step(self, *args)
        pairs = out[2][-1][0]
        seen.append((len(out[2]), 0 if pairs.born is None else int((pairs.born >= 0).sum())))
        return out

    monkeypatch.setattr(DifferentiableStep, "step", recording)
    return seen


def test_bodies_in_contact(rng, monkeypatch):
    """Contact between bodies: gradients of the initial state, the moduli, gravity and the
    contact's stiffness and thickness against central differences; the contact's own values
    give the simulator's trajectory; the contact's values are checked."""
    sim = _blocks_in_contact()
    seen = _contact_solves(monkeypatch)
    run = tm.rollout(sim, STEPS)
    assert len(seen) == STEPS and all(pairs > 0 for pairs in sim.step().contact.body_contacts.tolist())
    sim = _blocks_in_contact()
    again = tm.rollout(sim, STEPS, contact_stiffness=2e3, contact_thickness=torch.tensor(0.005, dtype=torch.float64))
    torch.testing.assert_close(again.x, run.x, rtol=0, atol=0)
    V = sim.x.shape[0]
    weights = [torch.tensor(rng.standard_normal((STEPS + 1, V, 3))) for _ in range(2)]
    params = _parameters(sim, rng)
    params["contact_stiffness"] = torch.tensor(2.5e3, dtype=torch.float64)
    params["contact_thickness"] = torch.tensor(0.006, dtype=torch.float64)
    for name in ("x0", "v0", "young", "gravity", "contact_stiffness", "contact_thickness"):
        assert _directional_error(sim, weights, name, params[name], rng) <= 1e-6, name
    for kwargs, message in [(dict(contact_stiffness=0.0), r"contact_stiffness must be > 0"),
                            (dict(contact_thickness=-1e-3), r"contact_thickness must be >= 0"),
                            (dict(contact_thickness=torch.zeros(2)), r"contact_thickness must have shape \(\)")]:
        with pytest.raises(tm.SceneError, match=message):
            tm.rollout(sim, STEPS, **kwargs)
    assert sim.body_contact.settings.stiffness == 2e3 and sim.time == pytest.approx(0.03)  # nothing changed


def test_a_pair_linearised_at_an_earlier_solve_carries_its_gradient_back(rng, monkeypatch):
    """A block spun onto another: a step's contact set takes a pair linearised where its first
    solve ended (the block turns over the other's surface), whose shift is that solve's motion;
    the gradient goes back through both solves and matches central differences (the contact's
    check_tol, on by default, is off for the rollout's steps: every solve converged)."""
    sim = _blocks_in_contact(rough=True)
    lower = sim.ptr[1]
    centre = sim.x[lower:].mean(0)
    arm = sim.x[lower:] - centre
    v0 = sim.v.clone()
    v0[lower:] = 6.0 * torch.stack([-arm[:, 1], arm[:, 0], torch.zeros_like(arm[:, 0])], 1) \
        + torch.tensor([0.3, 0.0, -0.3], dtype=torch.float64)
    steps = 4
    seen = _contact_solves(monkeypatch)
    tm.rollout(sim, steps, v0=v0)
    assert any(solves > 1 and born > 0 for solves, born in seen), seen
    V = sim.x.shape[0]
    weights = [torch.tensor(rng.standard_normal((steps + 1, V, 3))) for _ in range(2)]

    def loss(**kwargs):
        kwargs.setdefault("v0", v0)
        run = tm.rollout(sim, steps, **kwargs)
        return (run.x * weights[0]).sum() + 0.3 * (run.v * weights[1]).sum()

    for name, value in (("x0", sim.x.clone()), ("v0", v0), ("contact_stiffness", torch.tensor(2e3, dtype=torch.float64))):
        leaf = value.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(loss(**{name: leaf}), leaf)
        direction = torch.tensor(rng.standard_normal(tuple(value.shape)), dtype=torch.float64)
        eps = 1e-5 * float(value.abs().mean().clamp_min(1e-2))
        with torch.no_grad():
            fd = float(loss(**{name: value + eps * direction}) - loss(**{name: value - eps * direction})) / (2 * eps)
        assert abs(float((grad * direction).sum()) - fd) <= 1e-6 * abs(fd), name
    assert sim.body_contact.settings.check_tol == tm.Contact().check_tol is not None  # restored


def test_a_rollout_with_contact_leaves_nothing_alive():
    """Once the trajectory and the gradient are dropped, so are the simulator and its steps (no
    reference cycle through the autograd graph, which the collector cannot break)."""
    import gc
    import weakref

    sim = _blocks_in_contact()
    x0 = sim.x.clone().requires_grad_(True)
    run = tm.rollout(sim, 2, x0=x0)
    run.x.sum().backward()
    alive = weakref.ref(sim.system)
    del sim, run, x0
    gc.collect()
    assert alive() is None


@pytest.mark.parametrize("what", ["tools", "newton", "friction", "removed", "body friction", "exact tangent"])
def test_what_the_adjoint_does_not_differentiate_is_named(rng, what):
    """No silent zero gradient: a simulation with something the adjoint step leaves out raises."""
    if what in ("body friction", "exact tangent"):
        sim = _blocks_in_contact(**(dict(friction=0.3) if what == "body friction" else dict(tangent="exact")))
        message = {"body friction": "contact between bodies with friction",
                   "exact tangent": "contact between bodies with tangent='exact'"}[what]
        with pytest.raises(tm.SolverError, match=message):
            tm.rollout(sim, 2, x0=sim.x.clone().requires_grad_(True))
        return
    scene = build_scene(rng, "tet")
    body = tm.Body(scene.mesh, random_material(rng, "hooke"), fixed=scene.mesh.vertices[:, 0] < 1e-6)
    options = {"tools": dict(tools=[tm.Sphere(0.1, position=(0.5, 0.4, 0.9), friction=0.3)]),
               "newton": dict(newton_iters=2),
               "friction": dict(planes=[tm.Plane((0, 0, 1), -0.5, 1e4, friction=0.5)]),
               "removed": {}}[what]
    sim = tm.Simulator([body], **options)
    message = {"tools": "tools with friction", "newton": "newton_iters=2", "friction": "planes with friction",
               "removed": "removed or cut"}[what]
    if what == "removed":
        tm.rollout(sim, 2)  # a rollout before: its differentiable view is kept, and checked again
        sim.remove_elements(0, [0])
    with pytest.raises((tm.SolverError, tm.SceneError), match=message):
        tm.rollout(sim, 2, young=torch.tensor(1e4, dtype=torch.float64))
    with pytest.raises((tm.SolverError, tm.SceneError), match=message):
        tm.rollout(sim, 2, x0=sim.x.clone().requires_grad_(True))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "stvk", "corotational"])
def test_cuda_gradients_match_the_cpu(model, monkeypatch):
    """The same rollout and gradients on CUDA (captured steps, the extension's CUDA ops, each
    step's vector-Jacobian product captured and replayed) as on the CPU, in float64; the hooke
    case in the tensor form (the default) and the stress form."""
    from tensormass_torch.solver import adjoint

    replays = []

    def recording(graphs, key, work):
        replayed = adjoint_run_captured(graphs, key, work)
        replays.append((replayed, graphs[key] is not False))
        return replayed

    adjoint_run_captured = adjoint.run_captured
    monkeypatch.setattr(adjoint, "run_captured", recording)
    grads = {}
    for device in ("cpu", "cuda"):
        for form in (("tensor", "stress") if model == "hooke" else ("auto",)):
            sim = _sim(np.random.default_rng(3), "tet", model, form=form, device=device)
            N, V = sim.element_ptr[-1], sim.x.shape[0]
            young = torch.full((N,), 1e4, dtype=torch.float64, device=device, requires_grad=True)
            x0 = sim.x.clone().requires_grad_(True)
            forces = torch.zeros(STEPS, V, 3, dtype=torch.float64, device=device, requires_grad=True)
            for every in (None, 2):  # checkpointed: the same gradients
                for t in (young, x0, forces):
                    t.grad = None
                run = tm.rollout(sim, STEPS, young=young, x0=x0, forces=forces, checkpoint_every=every)
                (run.x.square().sum() + run.v[-1].sum()).backward()
                grads[device, form, every] = [t.grad.cpu() for t in (young, x0, forces)]
    # the first step's backward captured, the next ones replayed
    assert replays and all(captured for _, captured in replays) and sum(r for r, _ in replays) >= STEPS - 1
    for (device, form, every), got in grads.items():
        for a, b in zip(got, grads["cpu", form, None]):
            torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)


def test_a_scene_file_rolls_out(tmp_path):
    """A scene file's path (or the scene) in place of a simulator: its simulator's steps."""
    scene = tmp_path / "beam.toml"
    scene.write_text("""dt = 0.01
dtype = "float64"
steps = 3

[solver]
cg_tol = 1e-10

[[bodies]]
mesh = { generator = "beam", cells = [3, 1, 1], size = [0.3, 0.1, 0.1] }
material = { model = "hooke", young = 2e4, poisson = 0.3, density = 1000.0 }
fixed = { box = [[0.0, 0.0, 0.0], [0.0, 0.1, 0.1]] }
""")
    young = torch.tensor(2e4, dtype=torch.float64, requires_grad=True)
    run = tm.rollout(str(scene), 3, young=young)
    run.x[-1, :, 2].sum().backward()
    assert young.grad is not None and float(young.grad) > 0  # stiffer: sags less
    direct = tm.rollout(tm.load_scene(scene).simulator, 3)
    torch.testing.assert_close(direct.x, run.x.detach())
    with pytest.raises(tm.SceneError, match="rollout steps a tm.Simulator"):
        tm.rollout(42, 3)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_cuda_contact_gradients_match_the_cpu(model):
    """The planes' offsets and stiffness and a tool's path and stiffness written in place for the
    captured CUDA steps: the same trajectory and gradients as on the CPU (float64)."""
    results = {}
    for device in ("cpu", "cuda"):
        sim = _sim(np.random.default_rng(5), "tet", model, device=device, steps_before=0, gravity=(0.0, 0.0, -30.0),
                   planes=[tm.Plane((0, 0, 1), -0.02, 2e4)], tools=[tm.Sphere(0.2, position=(0.9, 0.4, 0.8))])
        offsets = torch.tensor([-0.01], dtype=torch.float64, device=device, requires_grad=True)
        stiffness = torch.tensor([3e4], dtype=torch.float64, device=device, requires_grad=True)
        path = torch.tensor([[[0.9, 0.4, 0.8 - 0.02 * n]] for n in range(1, 7)], dtype=torch.float64,
                            device=device, requires_grad=True)
        tool_stiffness = torch.tensor([5e4], dtype=torch.float64, device=device, requires_grad=True)
        run = tm.rollout(sim, 6, plane_offsets=offsets, plane_stiffness=stiffness, tool_positions=path,
                         tool_stiffness=tool_stiffness)
        run.x[-1].square().sum().backward()
        results[device] = (run.x.detach().cpu(), offsets.grad.cpu(), stiffness.grad.cpu(), path.grad.cpu(),
                           tool_stiffness.grad.cpu())
        assert float(sim.planes.offsets[0]) == -0.02 and float(sim.tools.origins[0, 2]) == 0.8  # restored
    assert float(results["cpu"][2]) != 0.0 and float(results["cpu"][4]) != 0.0  # the scene touches both
    for a, b in zip(results["cuda"], results["cpu"]):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_body_contact_gradients_match_the_cpu():
    """Contact between bodies on CUDA (eager steps and backward: each step's pairs differ): the
    same trajectory and gradients of the initial positions and the contact's stiffness and
    thickness as on the CPU (float64)."""
    results = {}
    for device in ("cpu", "cuda"):
        sim = _blocks_in_contact(device=device)
        x0 = sim.x.detach().clone().requires_grad_(True)
        stiffness = torch.tensor(2e3, dtype=torch.float64, device=device, requires_grad=True)
        thickness = torch.tensor(0.005, dtype=torch.float64, device=device, requires_grad=True)
        run = tm.rollout(sim, STEPS, x0=x0, contact_stiffness=stiffness, contact_thickness=thickness)
        run.x[-1].square().sum().backward()
        results[device] = (run.x.detach().cpu(), x0.grad.cpu(), stiffness.grad.cpu(), thickness.grad.cpu())
    assert float(results["cpu"][2]) != 0.0
    for a, b in zip(results["cuda"], results["cpu"]):
        torch.testing.assert_close(a, b, rtol=1e-8, atol=1e-12)
