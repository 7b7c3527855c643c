"""Friction of planes and tools on the nodes (physics.contact: regularised Coulomb, implicit as a
damper): Coulomb's sliding acceleration and sticking on a plane and on a box tool, a moving tool
carrying a block at its speed with the reaction it feels, one step against a dense float64 solve
(fused and composed products, imposed velocities), the scene keys and bad input."""
import math

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops.segments import Segments
from tensormass_torch.physics.contact import Planes
from tensormass_torch.sim.scene_file import load_scene
from tensormass_torch.solver.implicit_euler import DynamicsSystem, StepOptions, implicit_euler_step

DT = torch.float64


def cube_on_a_floor(theta_deg, friction, floor, steps=125, dt=2e-3, friction_velocity=1e-3):
    """A soft 0.1 m cube (1 kg) on a floor (a plane, or the top face of a box tool), gravity tilted
    by theta from the floor's normal: the cube's mass-weighted mean velocity along the slope at
    each step ``[steps]``, and the simulator."""
    theta = math.radians(theta_deg)
    cube = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), origin=(0.1, 0.15, 0.0), dtype=DT)
    if floor == "plane":
        contact = dict(planes=[tm.Plane((0, 0, 1), 0.0, 1e5, friction=friction, friction_velocity=friction_velocity)])
    else:
        contact = dict(tools=[tm.Box((1, 1, 0.1), position=(0, 0, -0.1), stiffness=1e5, friction=friction,
                                     friction_velocity=friction_velocity)])
    sim = tm.Simulator([tm.Body(cube, tm.Material(young=1e6, poisson=0.3, density=1000))], dt=dt, dtype=DT,
                       gravity=(9.81 * math.sin(theta), 0.0, -9.81 * math.cos(theta)), cg_tol=1e-10, **contact)
    mass = sim.system.mass[:, 0]
    speeds = []
    for _ in range(steps):
        sim.step()
        speeds.append(float((mass * sim.v[:, 0]).sum() / mass.sum()))
    return torch.tensor(speeds, dtype=DT), sim


@pytest.mark.parametrize("floor", ["plane", "box"])
@pytest.mark.parametrize("theta, friction", [(40, 0.5), (30, 0.3)])
def test_a_cube_slides_at_coulombs_acceleration(floor, theta, friction):
    """Past the friction angle the cube slides at g (sin theta - mu cos theta), and the floor
    (a tool) feels mu times the normal force along the slope."""
    dt = 2e-3
    speeds, sim = cube_on_a_floor(theta, friction, floor, dt=dt)
    first = 25  # past the first steps, where the normal force builds up
    measured = float(speeds[-1] - speeds[first]) / ((len(speeds) - 1 - first) * dt)
    coulomb = 9.81 * (math.sin(math.radians(theta)) - friction * math.cos(math.radians(theta)))
    assert abs(measured - coulomb) < 0.05 * coulomb, (measured, coulomb)
    if floor == "box":
        force = sim.last_report.contact.tool_force[0]
        assert float(force[0]) == pytest.approx(-friction * float(force[2]), rel=1e-6)


@pytest.mark.parametrize("floor", ["plane", "box"])
def test_a_cube_below_the_friction_angle_sticks(floor):
    """tan theta < mu: the cube creeps slower than the regularisation's slip speed (frictionless,
    it would be moving at g sin theta t ~ 0.8 m/s by the end); the floor holds its weight's
    component along the slope."""
    speeds, sim = cube_on_a_floor(20, 0.5, floor, friction_velocity=1e-3)
    assert float(speeds[-25:].abs().max()) < 1e-3
    if floor == "box":
        force = sim.last_report.contact.tool_force[0]
        assert float(force[0]) == pytest.approx(9.81 * math.sin(math.radians(20)), rel=1e-2)


def test_a_moving_tool_carries_a_block_at_its_speed():
    """A box moving at U under a block (a conveyor belt): friction accelerates the block at
    about mu g, the belt feeling -mu times the normal force, until it moves with the belt."""
    speed, friction, dt = 0.2, 0.5, 2e-3
    cube = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), origin=(0.1, 0.15, 0.0), dtype=DT)
    belt = tm.Box((1, 1, 0.1), stiffness=1e5, friction=friction, times=[0.0, 10.0],
                  positions=[(0.0, 0.0, -0.1), (10 * speed, 0.0, -0.1)])
    sim = tm.Simulator([tm.Body(cube, tm.Material(young=1e6, poisson=0.3, density=1000))], dt=dt, dtype=DT,
                       cg_tol=1e-10, tools=[belt])
    mass = sim.system.mass[:, 0]
    sim.step(10)
    force = sim.last_report.contact.tool_force[0]
    assert float(force[0]) == pytest.approx(friction * float(force[2]), rel=1e-3)  # both negative: pulled back
    sim.step(90)
    carried = float((mass * sim.v[:, 0]).sum() / mass.sum())
    assert carried == pytest.approx(speed, abs=1e-3)
    assert abs(float(sim.last_report.contact.tool_force[0, 0])) < 1e-2  # no more slip, no more drag


class Composed(torch.nn.Module):
    """A TensorMass seen as any force model (x -> forces, its tangent): the step's composed path."""

    def __init__(self, model):
        super().__init__()
        self.inner = model
        self.rest = model.rest

    def forward(self, x):
        return self.inner(x)

    def tangent(self, x):
        return self.inner.tangent(x)


def plane_damping(planes, x, v):
    """The friction matrix C ``[V, 3, 3]`` of the planes written out node by node, plane by plane."""
    out = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    for n, d, k, mu, eps in zip(planes.normals, planes.offsets, planes.stiffness, planes.friction,
                                planes.friction_velocity):
        for i in range(x.shape[0]):
            depth = float(d - n @ x[i])
            if depth > 0:
                projector = torch.eye(3, dtype=x.dtype) - torch.outer(n, n)
                out[i] += mu * k * depth / max(float((projector @ v[i]).norm()), float(eps)) * projector
    return out


@pytest.mark.parametrize("composed", [False, True])
def test_step_with_friction_matches_dense_system(composed):
    """One step with a floor and a tilted wall rubbing on a block, some nodes moved at an imposed
    velocity, against the dense float64 system (M + h C - h^2 K) dv = h (f + h K v - C v) with
    the free rows solved: through the fused product (C folded into the node stiffness) and the
    composed one."""
    mesh = tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.2), dtype=DT)
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, model="hooke"))
    mass = model.lumped_mass()
    external = mass[:, None] * torch.tensor([0.0, 0.0, -9.81], dtype=DT)
    planes = Planes([tm.Plane((0, 0, 1), 0.01, 1e4, friction=0.6, friction_velocity=1e-2),
                     tm.Plane((-1, 0, 0.2), -0.28, 3e3, friction=0.3)], DT, "cpu")
    constrained = mesh.vertices[:, 0] < 1e-9
    system = DynamicsSystem(Composed(model) if composed else model, mass, external,
                            Segments.from_lengths([model.num_nodes], "cpu"), constrained, planes)
    gen = torch.Generator().manual_seed(3)
    x = mesh.vertices + 0.01 * torch.randn(mesh.vertices.shape, generator=gen, dtype=DT)
    v = 0.2 * torch.randn(mesh.vertices.shape, generator=gen, dtype=DT)
    imposed = torch.zeros_like(v)
    imposed[:, 1] = 0.05
    h = 0.01
    opts = StepOptions(dt=h, cg_tol=1e-13, cg_max_iter=5000)
    _, v_new, _ = implicit_euler_step(system, x, v, opts, imposed)

    n = x.numel()
    eye = torch.eye(n, dtype=DT)
    K = torch.stack([(model.dforce(x, eye[k].view_as(x)) + planes.dforces(x, eye[k].view_as(x))).reshape(-1)
                     for k in range(n)], dim=1)
    C = torch.block_diag(*plane_damping(planes, x, v))
    assert float(C.abs().max()) > 0  # the planes rub
    M = torch.diag(mass.repeat_interleave(3))
    f = (model(x) + external + planes.forces(x)).reshape(-1)
    A = M + h * C - h * h * K
    b = h * (f + h * K @ v.reshape(-1) - C @ v.reshape(-1))
    dv = torch.zeros_like(b)
    keep = (~constrained).repeat_interleave(3)
    dv[~keep] = (imposed - v).reshape(-1)[~keep]
    rhs = b - A @ dv
    dv[keep] = torch.linalg.solve(A[keep][:, keep], rhs[keep])
    torch.testing.assert_close(v_new.reshape(-1), v.reshape(-1) + dv, rtol=1e-9, atol=1e-11)


def test_friction_damping_is_symmetric_semidefinite_and_dissipates():
    mesh = tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.2), dtype=DT)
    gen = torch.Generator().manual_seed(8)
    x = mesh.vertices + 0.02 * torch.randn(mesh.vertices.shape, generator=gen, dtype=DT)
    v = torch.randn(mesh.vertices.shape, generator=gen, dtype=DT)
    planes = Planes([tm.Plane((0, 0, 1), 0.01, 1e4, friction=0.6), tm.Plane((1, 1, 0), 0.02, 1e3, friction=0.2)],
                    DT, "cpu")
    damping = planes.friction_damping(x, v)
    torch.testing.assert_close(damping.matrix, plane_damping(planes, x, v), rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(damping.matrix, damping.matrix.transpose(1, 2))
    assert float(torch.linalg.eigvalsh(damping.matrix).min()) > -1e-9
    forces = damping.forces(v)
    assert float((forces * v).sum()) < 0  # negative power
    # Coulomb: a fast-slipping node feels mu times its normal force
    frictionless = Planes([tm.Plane((0, 0, 1), 0.01, 1e4)], DT, "cpu")
    assert not frictionless.has_friction and planes.has_friction


def test_scene_keys(tmp_path):
    text = """
dt = 0.002
steps = 1
[[planes]]
normal = [0, 0, 1]
stiffness = 1e5
friction = 0.4
friction_velocity = 0.01
[[tools]]
shape = "sphere"
radius = 0.05
position = [0, 0, 0.3]
friction = 0.2
[[bodies]]
mesh = { generator = "beam", cells = [2, 2, 2], size = [0.1, 0.1, 0.1] }
material = { young = 1e6, poisson = 0.3, density = 1000 }
"""
    path = tmp_path / "rub.toml"
    path.write_text(text)
    scene = load_scene(path)
    assert scene.simulator.planes.friction.tolist() == pytest.approx([0.4])
    assert scene.simulator.planes.friction_velocity.tolist() == pytest.approx([0.01])
    assert scene.simulator.tools.tools[0].friction == 0.2
    path.write_text(text.replace("friction = 0.4", "friction = -0.4"))
    with pytest.raises(tm.SceneError, match=r"planes.*friction"):
        load_scene(path)


@pytest.mark.parametrize("make, match", [
    (lambda: tm.Plane((0, 0, 1), 0.0, 1e5, friction=-0.1), "plane friction must be a non-negative"),
    (lambda: tm.Plane((0, 0, 1), 0.0, 1e5, friction=float("nan")), "plane friction must be a non-negative"),
    (lambda: tm.Plane((0, 0, 1), 0.0, 1e5, friction_velocity=0.0), "plane friction_velocity must be a positive"),
    (lambda: tm.Sphere(0.1, friction=-1.0), "tool friction must be a non-negative"),
    (lambda: tm.Box((1, 1, 1), friction_velocity=-1.0), "tool friction_velocity must be a positive"),
])
def test_bad_friction_raises_one_clear_error(make, match):
    with pytest.raises(tm.SceneError, match=match):
        make()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_cuda_steps_with_friction_match_the_cpu(model):
    """A block on a rubbing floor, under a rubbing box that moves (captured steps, the friction
    folded into the node stiffness in place), and on a rubbing floor alone (the right-hand side
    op, then the friction), on CUDA against the CPU in float64."""
    mesh = tm.beam_mesh(3, 3, 2, size=(0.3, 0.3, 0.2), origin=(-0.15, -0.15, 0.0), dtype=DT)
    material = tm.Material(young=2e5, poisson=0.3, density=1000, model=model)
    floor = tm.Plane((0, 0, 1), 0.0, 1e5, friction=0.5)
    pusher = tm.Box((0.1, 0.1, 0.05), times=[0.0, 0.1, 0.2], positions=[[0, 0, 0.26], [0, 0, 0.24], [0.1, 0, 0.24]],
                    stiffness=2e4, friction=0.4)
    for tools in ([pusher], []):
        runs = []
        for device in ("cpu", "cuda"):
            sim = tm.Simulator([tm.Body(mesh, material)], dt=0.01, planes=[floor], tools=tools, dtype=DT,
                               device=device, gravity=(3.0, 0.0, -9.81), cg_tol=1e-12, cg_max_iter=3000)
            sim.step(25)
            runs.append(sim.x.cpu())
        torch.testing.assert_close(runs[1], runs[0], rtol=1e-9, atol=1e-11)
