"""Rigid tools (physics.tools): the penalty force and stiffness against finite differences of the
energy (float64), the implicit step with tools against a dense solve, the reaction at static
equilibrium against the fixed nodes' forces and gravity, the simulator's reports, bad input."""
import dataclasses
import math

import numpy as np
import pytest
import torch
from conftest import on_each_cpu_backend, random_rotation, u_shape_surface

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces
from tensormass_torch.physics.tools import ToolSet

DT = torch.float64


def tool_cases():
    rot = random_rotation(np.random.default_rng(7), 3).tolist()
    return {
        "sphere": tm.Sphere(0.3, position=(0.1, -0.2, 0.05), stiffness=2e3, thickness=0.02),
        "capsule": tm.Capsule(0.2, 0.25, position=(0.0, 0.1, 0.0), rotation=rot, stiffness=3e3, thickness=0.01),
        "box": tm.Box((0.3, 0.2, 0.25), position=(-0.05, 0.0, 0.1), rotation=rot, stiffness=1e3, thickness=0.03),
    }


def points_near(tool: tm.Tool, count: int, gen) -> torch.Tensor:
    """Points ``[count, 3]`` around and inside the tool (every regime: faces, edges, corners,
    a capsule's side and ends), none on a kink of the distance."""
    reach = max(tool.size) + tool.thickness
    local = (torch.rand(count, 3, generator=gen, dtype=DT) * 2 - 1) * 1.3 * reach
    if tool.shape == "capsule":
        local[:, 0] *= 1.0 + tool.size[1] / reach
    rotation = torch.tensor(tool.rotation, dtype=DT)
    return local @ rotation.T + torch.tensor(tool.position, dtype=DT)


@pytest.mark.parametrize("shape", ["sphere", "capsule", "box"])
def test_force_and_stiffness_are_derivatives_of_the_energy(shape):
    """tangent="exact": the force is minus the energy's gradient, the stiffness its Hessian."""
    tool = dataclasses.replace(tool_cases()[shape], tangent="exact")
    tools = ToolSet([tool], DT, "cpu")
    gen = torch.Generator().manual_seed(3)
    x = points_near(tool, 400, gen)
    gaps = tools.gaps(x)[0][0]
    assert bool((gaps < 0).sum() > 40) and bool((gaps > 0).sum() > 40)  # both sides are tested
    forces, stiffness = tools.linearize(x)
    # the force is minus the energy's gradient (autograd of the energy)
    y = x.clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(tools.energy(y), y)
    torch.testing.assert_close(forces, -gradient, rtol=1e-12, atol=1e-12)
    # the stiffness is minus the force's derivative: central differences, node by node
    eps = 1e-6
    for k in range(3):
        step = torch.zeros_like(x)
        step[:, k] = eps
        column = -(tools.forces(x + step) - tools.forces(x - step)) / (2 * eps)  # [V, 3]
        # points within eps of a kink (the contact distance, a box's edges) are skipped
        near_kink = (gaps.abs() < 10 * eps)
        torch.testing.assert_close(stiffness[~near_kink, :, k], column[~near_kink], rtol=1e-6, atol=1e-4)
    # and the tool's stiffness is symmetric
    torch.testing.assert_close(stiffness, stiffness.transpose(1, 2), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("shape", ["sphere", "capsule", "box"])
def test_projected_stiffness_is_the_hessian_made_semidefinite(shape):
    """The default stiffness: the exact Hessian with its negative eigenvalues set to zero."""
    tool = tool_cases()[shape]
    assert tool.tangent == "projected"
    gen = torch.Generator().manual_seed(5)
    x = points_near(tool, 300, gen)
    exact = ToolSet([dataclasses.replace(tool, tangent="exact")], DT, "cpu").node_stiffness(x)
    values, vectors = torch.linalg.eigh(exact)
    projected = vectors @ torch.diag_embed(torch.clamp(values, min=0.0)) @ vectors.transpose(1, 2)
    stiffness = ToolSet([tool], DT, "cpu").node_stiffness(x)
    torch.testing.assert_close(stiffness, projected, rtol=1e-9, atol=1e-9 * tool.stiffness)
    assert bool((torch.linalg.eigvalsh(stiffness) > -1e-9 * tool.stiffness).all())
    assert bool((values < -1e-6 * tool.stiffness).any()) or shape == "box"  # the projection did something


def test_distances_are_the_shapes():
    """The signed distances against closed forms at points of known distance."""
    sphere = ToolSet([tm.Sphere(0.5, position=(1.0, 0.0, 0.0))], DT, "cpu")
    g, n, _ = sphere.gaps(torch.tensor([[1.0, 0.0, 2.0], [1.2, 0.0, 0.0]], dtype=DT))[0]
    torch.testing.assert_close(g, torch.tensor([1.5, -0.3], dtype=DT))
    torch.testing.assert_close(n, torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=DT))
    capsule = ToolSet([tm.Capsule(0.1, 1.0, rotation=[[0, 0, 1], [0, 1, 0], [-1, 0, 0]])], DT, "cpu")  # axis -z
    g, _, _ = capsule.gaps(torch.tensor([[0.3, 0.0, 0.5], [0.0, 0.0, -1.5], [0.0, 0.05, 0.0]], dtype=DT))[0]
    torch.testing.assert_close(g, torch.tensor([0.2, 0.4, -0.05], dtype=DT))
    box = ToolSet([tm.Box((1.0, 2.0, 3.0))], DT, "cpu")
    g, n, _ = box.gaps(torch.tensor([[0.5, 0.0, 0.0], [2.0, 3.0, 0.0], [0.0, 0.0, -3.5]], dtype=DT))[0]
    torch.testing.assert_close(g, torch.tensor([-0.5, math.sqrt(2.0), 0.5], dtype=DT))
    torch.testing.assert_close(n[0], torch.tensor([1.0, 0.0, 0.0], dtype=DT))
    torch.testing.assert_close(n[2], torch.tensor([0.0, 0.0, -1.0], dtype=DT))


def block(n=(3, 3, 2), model="corotational", young=2e4):
    mesh = tm.beam_mesh(*n, size=(0.3, 0.3, 0.2), origin=(-0.15, -0.15, 0.0), dtype=DT)
    return mesh, tm.Material(young=young, poisson=0.3, density=1000.0, model=model)


def test_implicit_step_with_a_tool_matches_dense_system():
    """One step with a sphere pressing on a held block against the dense float64 system
    (M - h^2 K) dv = h (f + h K v) with K the elastic and tool stiffness."""
    mesh, mat = block(model="hooke")
    fixed = mesh.vertices[:, 2] < 1e-9
    sphere = tm.Sphere(0.1, position=(0.02, -0.01, 0.27), stiffness=5e3, thickness=0.01)
    h = 0.01
    sim = tm.Simulator([tm.Body(mesh, mat, fixed=fixed)], dt=h, tools=[sphere], cg_tol=1e-13, cg_max_iter=5000)
    sim.step(2)
    x, v = sim.x.clone(), sim.v.clone()
    assert int(sim.last_report.contact.contacts[0]) > 0  # the sphere presses
    tools = sim.tools
    n = x.numel()
    eye = torch.eye(n, dtype=DT)
    K = torch.stack([(sim.model.dforce(x, eye[k].view_as(x)) + tools.dforces(x, eye[k].view_as(x))).reshape(-1)
                     for k in range(n)], dim=1)
    M = torch.diag(sim.model.lumped_mass().repeat_interleave(3))
    f = (sim.model(x) + sim.system.external + tools.forces(x)).reshape(-1)
    A = M - h * h * K
    b = h * (f + h * K @ v.reshape(-1))
    keep = (~fixed).repeat_interleave(3)
    dv = torch.zeros_like(b)
    dv[keep] = torch.linalg.solve(A[keep][:, keep], b[keep])
    sim.step()
    torch.testing.assert_close(sim.v.reshape(-1), v.reshape(-1) + dv, rtol=1e-9, atol=1e-11)


def test_tool_reaction_balances_fixed_nodes_and_gravity():
    """At static equilibrium the force on the tool equals the forces at the fixed nodes plus
    gravity (float64, 1e-6 relative); a sphere's torque about its centre is zero."""
    mesh, mat = block(model="corotational", young=1e6)
    fixed = mesh.vertices[:, 0] < -0.15 + 1e-9  # a cantilever held at x = -0.15
    model = tm.TensorMass(mesh, mat)
    sphere = tm.Sphere(0.08, position=(0.1, 0.02, 0.25), stiffness=2e4, thickness=0.005)
    tools = ToolSet([sphere], DT, "cpu")
    gravity = (0.0, 0.0, -9.81)
    u = tm.solve_static(model, fixed=fixed, gravity=gravity, tools=tools, tol=1e-12)
    x = mesh.vertices + u
    contact = tools.forces(x)
    assert bool((contact.abs().sum(1) > 0).any())
    weight = model.lumped_mass()[:, None] * torch.tensor(gravity, dtype=DT)
    at_fixed = -(model(x) + weight + contact)[fixed]  # what the support puts on the body
    force, torque = tools.reactions(x)
    expected = at_fixed.sum(0) + weight.sum(0)
    torch.testing.assert_close(force[0], expected, rtol=1e-6, atol=1e-6 * float(expected.norm()))
    assert float(force[0, 2]) > 0  # the body pushes the tool up
    assert float(torque.norm()) <= 1e-9 * float(force.norm()) * 0.08


def test_simulator_reports_and_moving_tool():
    """A box pushed down onto a block on a floor: contact counts, penetration and the reaction
    in each step's report; the tool moves along its keyframes; nothing passes through."""
    mesh, mat = block(young=2e5)
    box = tm.Box((0.12, 0.12, 0.05), times=[0.0, 0.2], positions=[[0, 0, 0.3], [0, 0, 0.23]], stiffness=2e5,
                 name="pusher")
    sim = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, planes=[tm.Plane((0, 0, 1), 0.0, 2e5)], tools=[box])
    sim.step(30)
    report = sim.last_report.contact
    assert sim.tools.origins[0].tolist() == pytest.approx([0.0, 0.0, 0.23])
    assert int(report.contacts[0]) > 0
    assert float(report.tool_force[0, 2]) > 0
    assert 0 < float(report.max_penetration[0]) < 0.01
    again = sim.contact_report()
    torch.testing.assert_close(again.tool_force, report.tool_force)
    assert bool(torch.isfinite(sim.x).all())


def test_a_tool_moved_live_is_its_path():
    """A box held by ``move_tool`` where its keyframes would put it at each step's end moves the
    body as the keyframed box does, friction (the tool's velocity) included; by index or name;
    bad tools and positions raise and change nothing; held tools are not chained."""
    mesh, mat = block(young=2e5)
    runs = []
    for live in (False, True):
        box = tm.Box((0.12, 0.12, 0.05), times=[0.0, 0.2], positions=[[0, 0, 0.3], [0.03, 0, 0.22]], stiffness=2e5,
                     friction=0.5, name="pusher")
        if live:
            box = dataclasses.replace(box, times=(), positions=(), position=(0.0, 0.0, 0.3))
        sim = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, planes=[tm.Plane((0, 0, 1), 0.0, 2e5)], tools=[box],
                           cg_tol=1e-12)
        keyed = tm.Box((0.12, 0.12, 0.05), times=[0.0, 0.2], positions=[[0, 0, 0.3], [0.03, 0, 0.22]])
        for k in range(25):
            if live:
                sim.move_tool("pusher" if k % 2 else 0, keyed.origin(0.01 * (k + 1)))
            sim.step()
        runs.append((sim.x.clone(), sim.last_report.contact.tool_force.clone()))
        if live:
            assert sim.tools.moves and sim._chain_graphs() is None
            x = sim.x.clone()
            for bad, match in ((lambda: sim.move_tool(1, (0, 0, 0)), "tool index must be an integer in \\[0, 1\\)"),
                               (lambda: sim.move_tool("knife", (0, 0, 0)), "no tool named 'knife'"),
                               (lambda: sim.move_tool(0, (0, float("nan"), 0)), "tool position must be 3 finite")):
                with pytest.raises(tm.SceneError, match=match):
                    bad()
            assert sim.tools.held[0] == pytest.approx(keyed.origin(0.25)) and torch.equal(sim.x, x)
    torch.testing.assert_close(runs[1][0], runs[0][0], rtol=0, atol=1e-12)
    torch.testing.assert_close(runs[1][1], runs[0][1], rtol=1e-9, atol=1e-9)
    assert float(runs[0][1][0].norm()) > 0  # the box pressed
    plain = tm.Simulator([tm.Body(mesh, mat)], dt=0.01)
    with pytest.raises(tm.SceneError, match="this simulator has no tools"):
        plain.move_tool(0, (0, 0, 0))


def test_no_tool_changes_nothing():
    mesh, mat = block()
    far = tm.Sphere(0.05, position=(5.0, 5.0, 5.0))
    a = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, planes=[tm.Plane((0, 0, 1), 0.0, 1e4)])
    b = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, planes=[tm.Plane((0, 0, 1), 0.0, 1e4)], tools=[far])
    a.step(5)
    b.step(5)
    torch.testing.assert_close(a.x, b.x, rtol=1e-12, atol=1e-12)
    assert a.last_report.contact is None
    assert b.last_report.contact.tool_force.abs().max() == 0


@pytest.mark.parametrize("make, match", [
    (lambda: tm.Sphere(-0.1), "sphere radius must be a positive"),
    (lambda: tm.Sphere(0.1, position=(0.0, float("nan"), 0.0)), "tool position must be 3 finite"),
    (lambda: tm.Sphere(0.1, times=[0.0, 1.0], positions=[[0, 0, 0], [0, float("inf"), 0]]), r"positions\[1\]"),
    (lambda: tm.Sphere(0.1, times=[1.0, 0.0], positions=[[0, 0, 0], [0, 0, 1]]), "increasing"),
    (lambda: tm.Sphere(0.1, times=[0.0], positions=[[0, 0, 0], [0, 0, 1]]), "must match"),
    (lambda: tm.Sphere(0.1, stiffness=0.0), "stiffness must be a positive"),
    (lambda: tm.Sphere(0.1, thickness=-1.0), "thickness must be a non-negative"),
    (lambda: tm.Capsule(0.1, -1.0), "half_length must be a non-negative"),
    (lambda: tm.Box((1.0, 0.0, 1.0)), r"half_extents\[1\] must be a positive"),
    (lambda: tm.Box((1.0, 1.0)), "box half_extents must be 3"),
    (lambda: tm.Box((1.0, 1.0, 1.0), rotation=[[1, 0, 0], [0, 1, 0], [0, 0, -1]]), "rotation matrix"),
    (lambda: tm.Sphere(0.1, tangent="gauss"), "tool tangent must be one of"),
])
def test_bad_tools_raise_one_clear_error(make, match):
    with pytest.raises(tm.SceneError, match=match):
        make()


def test_bad_motion_and_tool_list_raise():
    mesh, mat = block()
    with pytest.raises(tm.SceneError, match="not a tm.Tool"):
        tm.Simulator([tm.Body(mesh, mat)], tools=["sphere"])
    wild = tm.Sphere(0.1, motion=lambda t: (0.0, float("nan") if t > 0 else 0.0, 0.0))
    sim = tm.Simulator([tm.Body(mesh, mat)], tools=[wild])
    x = sim.x.clone()
    with pytest.raises(tm.SceneError, match=r"tool motion\(0.01\) must be 3 finite"):
        sim.step()
    assert torch.equal(sim.x, x) and sim.time == 0.0


def test_cpu_extension_and_pure_torch_agree(monkeypatch):
    """The same steps with the extension's kernels and with the pure-torch ops."""
    mesh, mat = block(model="hooke")
    sphere = tm.Sphere(0.1, times=[0.0, 0.1], positions=[[0, 0, 0.3], [0, 0, 0.25]], stiffness=1e4)

    def run():
        sim = tm.Simulator([tm.Body(mesh, mat)], dt=0.01, planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], tools=[sphere],
                           cg_tol=1e-12, cg_max_iter=3000)
        sim.step(12)
        return sim.x.clone()

    extension, pure = on_each_cpu_backend(monkeypatch, run)
    torch.testing.assert_close(extension, pure, rtol=1e-9, atol=1e-11)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("model", ["hooke", "corotational"])
def test_cuda_steps_match_the_cpu(model):
    """A moving sphere and a still box on CUDA (captured steps; the tools' poses written in place
    between replays) against the CPU, in float64."""
    mesh, mat = block(model=model, young=2e5)
    tools = [tm.Sphere(0.1, times=[0.0, 0.1, 0.2], positions=[[0, 0, 0.32], [0, 0, 0.27], [0.1, 0, 0.27]],
                       stiffness=2e4),
             tm.Box((0.05, 0.05, 0.05), position=(0.12, 0.12, 0.24), stiffness=2e4)]
    runs = []
    for device in ("cpu", "cuda"):
        sim = tm.Simulator([tm.Body(mesh.to(device), mat)], dt=0.01,
                           planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], tools=tools, cg_tol=1e-12, cg_max_iter=3000,
                           device=device)
        sim.step(25)
        runs.append((sim.x.cpu(), sim.last_report.contact.tool_force.cpu()))
    assert float(runs[0][1].abs().max()) > 0
    torch.testing.assert_close(runs[1][0], runs[0][0], rtol=1e-8, atol=1e-10)
    torch.testing.assert_close(runs[1][1], runs[0][1], rtol=1e-6, atol=1e-8)


def u_tool(**kwargs):
    """A mesh tool of a non-convex closed surface, turned and placed."""
    rot = random_rotation(np.random.default_rng(4), 3).tolist()
    return tm.MeshTool(u_shape_surface(), position=(0.05, -0.02, 0.1), rotation=rot, resolution=12, **kwargs)


def test_mesh_tool_force_and_stiffness_are_derivatives_of_the_energy():
    """A tool of any closed surface: its force is minus the energy's gradient, its exact stiffness
    the force's derivative inside the grid's cells, its projected one k grad(phi) grad(phi)^T."""
    tool = u_tool(stiffness=3e3, thickness=0.01, tangent="exact")
    tools = ToolSet([tool], DT, "cpu")
    gen = torch.Generator().manual_seed(5)
    grid = tool.grid
    cells = torch.rand(600, 3, generator=gen, dtype=DT) * (torch.tensor(grid.values.shape, dtype=DT) - 1)
    rotation = torch.tensor(tool.rotation, dtype=DT)
    x = (grid.lower + grid.spacing * cells) @ rotation.T + torch.tensor(tool.position, dtype=DT)
    gaps = tools.gaps(x)[0][0]
    assert bool((gaps < 0).sum() > 40) and bool((gaps > 0).sum() > 40)
    forces, stiffness = tools.linearize(x)
    y = x.clone().requires_grad_(True)
    (gradient,) = torch.autograd.grad(tools.energy(y), y)
    torch.testing.assert_close(forces, -gradient, rtol=1e-12, atol=1e-12)
    eps = 1e-7
    # skipped: points within eps of a cell's face (the interpolant's gradient jumps there) or of
    # the contact distance
    near_kink = ((cells - cells.round()).abs() < 10 * eps / grid.spacing).any(1) | (gaps.abs() < 10 * eps)
    for k in range(3):
        step = torch.zeros_like(x)
        step[:, k] = eps
        column = -(tools.forces(x + step) - tools.forces(x - step)) / (2 * eps)
        torch.testing.assert_close(stiffness[~near_kink, :, k], column[~near_kink], rtol=1e-5, atol=1e-3)
    projected = ToolSet([dataclasses.replace(tool, tangent="projected")], DT, "cpu").node_stiffness(x)
    g, n, _ = tools.gaps(x)[0]
    expected = 3e3 * (g < 0).to(DT)[:, None, None] * n[:, :, None] * n[:, None, :]
    torch.testing.assert_close(projected, expected, rtol=1e-12, atol=1e-12)


def test_a_mesh_tool_of_a_box_presses_as_the_box():
    """The surface of a box as a mesh tool: the same distances near its faces and the same
    pressing on a held block as the analytic box (the trilinear grid is exact on flat parts)."""
    cube = tm.beam_mesh(2, 2, 2, size=(0.2, 0.2, 0.1), origin=(-0.1, -0.1, -0.05), dtype=DT)
    surface = tm.TriMesh(cube.vertices, boundary_faces(cube.elements), check=False)
    path = dict(times=[0.0, 0.2], positions=[(0.0, 0.0, 0.26), (0.0, 0.0, 0.24)], stiffness=2e4)
    mesh, mat = block(n=(4, 4, 2), young=1e5)
    runs = []
    for tool in (tm.MeshTool(surface, resolution=20, **path), tm.Box((0.1, 0.1, 0.05), **path)):
        sim = tm.Simulator([tm.Body(mesh, mat, fixed=mesh.vertices[:, 2] < 1e-9)], dt=0.01, tools=[tool], dtype=DT,
                           rayleigh_mass=1.0, cg_tol=1e-12)
        sim.step(30)
        runs.append((sim.x.clone(), sim.last_report.contact.tool_force.clone()))
    assert float(runs[1][1][0, 2]) > 1.0  # the box presses
    torch.testing.assert_close(runs[0][0], runs[1][0], rtol=1e-9, atol=1e-11)
    torch.testing.assert_close(runs[0][1], runs[1][1], rtol=1e-9, atol=1e-9)


def test_bad_mesh_tools_raise_one_clear_error(tmp_path):
    vertices, faces = u_shape_surface()
    with pytest.raises(tm.MeshError, match=r"tool mesh 'probe' is not closed: 3 edges"):
        tm.MeshTool((vertices, faces[1:]), name="probe")
    bad = vertices.clone()
    bad[3, 1] = float("nan")
    with pytest.raises(tm.MeshError, match="tool mesh: surface vertices must be finite"):
        tm.MeshTool((bad, faces))
    with pytest.raises(tm.MeshError, match="tool mesh: surface file not found"):
        tm.MeshTool(tmp_path / "missing.stl")
    with pytest.raises(tm.SceneError, match="a mesh tool needs its signed distance grid"):
        tm.Tool("mesh", (), 1e5)


def test_mesh_tool_scene_key(tmp_path):
    vertices, faces = u_shape_surface()
    tm.save_mesh(tmp_path / "u.obj", tm.TriMesh(vertices, faces, check=False))
    tm.save_mesh(tmp_path / "open.obj", tm.TriMesh(vertices, faces[1:], check=False))
    text = """
dt = 0.01
steps = 1
[[tools]]
shape = "mesh"
file = "u.obj"
resolution = 10
position = [0, 0, 0.5]
[[bodies]]
mesh = { generator = "beam", cells = [2, 2, 2], size = [0.1, 0.1, 0.1] }
material = { young = 1e6, poisson = 0.3, density = 1000 }
"""
    path = tmp_path / "scene.toml"
    path.write_text(text)
    tool = tm.load_scene(path).simulator.tools.tools[0]
    assert tool.shape == "mesh" and tool.grid.values.shape[0] > 10
    path.write_text(text.replace("u.obj", "open.obj"))
    with pytest.raises(tm.SceneError, match=r"tools\[0\].*not closed"):
        tm.load_scene(path)
    path.write_text(text.replace("u.obj", "none.stl"))
    with pytest.raises(tm.SceneError, match=r"tools\[0\].file.*not found"):
        tm.load_scene(path)
