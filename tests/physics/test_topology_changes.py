"""Topology changes: element removal (``TensorMass.remove_elements``, ``Simulator.remove_elements``:
the Tensor-Mass way, each group drops the rows, the hooke tensor form subtracts the removed
elements' tensors from their edges, the lumped masses lose their shares) checked against models
and simulators built afresh from the remaining elements (forces, force differentials, energy,
masses, steps to 1e-12 in float64, every model, form and element kind, the CPU extension, the
pure-torch path and CUDA); bad ids raise and change nothing; and ``Simulator.cut`` (a blade
through a body: its pieces part) against a simulator of the cut mesh."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch import _backend
from tensormass_torch.errors import MeshError

CASES = [  # (kind, dim, model, form, rotation)
    ("tet", 3, "hooke", "tensor", "polar"), ("tet", 3, "hooke", "stress", "polar"),
    ("tet", 3, "stvk", "tensor", "polar"), ("tet", 3, "stvk", "stress", "polar"),
    ("tet", 3, "corotational", "stress", "polar"), ("tet", 3, "corotational", "stress", "qr"),
    ("tri", 2, "hooke", "tensor", "polar"), ("tri", 2, "stvk", "stress", "polar"),
    ("tri", 2, "corotational", "stress", "polar"),
    ("tri", 3, "hooke", "tensor", "polar"), ("tri", 3, "stvk", "tensor", "polar"),
    ("tri", 3, "corotational", "stress", "polar"),
]
BACKENDS = ["torch"] + (["extension"] if _backend.load_extension() is not None else [])


def mesh_of(kind, dim):
    if kind == "tet":
        return tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    mesh = tm.beam_tri_mesh(5, 3, size=(1.0, 0.6), dim=dim, dtype=torch.float64)
    return mesh


def material(model, rotation, young=None):
    return tm.Material(model=model, young=2e4 if young is None else young, poisson=0.3, density=800.0,
                       rotation=rotation)


def assert_same(model, fresh, x, dx):
    tol = dict(rtol=1e-12, atol=1e-12 * float(fresh(x).abs().max()))
    torch.testing.assert_close(model(x), fresh(x), **tol)
    torch.testing.assert_close(model.dforce(x, dx), fresh.dforce(x, dx), rtol=1e-12,
                               atol=1e-12 * float(fresh.dforce(x, dx).abs().max()))
    torch.testing.assert_close(model.energy(x), fresh.energy(x), rtol=1e-12, atol=0)
    torch.testing.assert_close(model.lumped_mass(), fresh.lumped_mass(), rtol=1e-12, atol=1e-15)
    # kept between calls while the tensors are unmodified: read after every removal, so that a
    # removal whose ops did not tell torch of their writes would leave them stale (models only:
    # the cuts' tests pass views over the used nodes, which have no such cache)
    for name in ("stiffness_diagonal", "stiffness_diagonal_blocks"):
        if not hasattr(model, name):
            continue
        want = getattr(fresh, name)()
        torch.testing.assert_close(getattr(model, name)(), want, rtol=1e-12, atol=1e-12 * float(want.abs().max()))


@pytest.fixture(params=BACKENDS)
def backend(request, monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", request.param)
    return request.param


def check_removals(kind, dim, model_name, form, rotation, device="cpu"):
    mesh = mesh_of(kind, dim).to(device=device)
    n = mesh.elements.shape[0]
    young = torch.linspace(1e4, 3e4, n, dtype=torch.float64, device=device)  # per element: rows stay matched
    model = tm.TensorMass(mesh, material(model_name, rotation, young), form=form)
    gen = torch.Generator().manual_seed(5)
    x = mesh.vertices + 0.02 * torch.randn(mesh.vertices.shape, generator=gen, dtype=torch.float64).to(device)
    dx = torch.randn(mesh.vertices.shape, generator=gen, dtype=torch.float64).to(device)
    alive = torch.ones(n, dtype=torch.bool, device=device)
    for count in (1, 5, n // 3):  # removals one after another, ids in the original numbering
        ids = torch.nonzero(alive).flatten()[torch.randperm(int(alive.sum()), generator=gen)[:count].to(device)]
        model.remove_elements(ids)
        alive[ids] = False
        fresh = tm.TensorMass.packed(mesh.vertices, [(mesh.elements[alive], material(model_name, rotation,
                                                                                        young[alive]), kind)],
                                     form=form)
        assert_same(model, fresh, x, dx)
        assert torch.equal(model.alive_elements(), alive)


CASE_IDS = [f"{k}{d}-{m}-{f}-{r}" for k, d, m, f, r in CASES]


@pytest.mark.parametrize("kind,dim,model_name,form,rotation", CASES, ids=CASE_IDS)
def test_removals_leave_the_model_of_the_remaining_elements(backend, kind, dim, model_name, form, rotation):
    check_removals(kind, dim, model_name, form, rotation)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("kind,dim,model_name,form,rotation", CASES, ids=CASE_IDS)
def test_removals_on_cuda_leave_the_model_of_the_remaining_elements(kind, dim, model_name, form, rotation):
    check_removals(kind, dim, model_name, form, rotation, "cuda")


def test_a_packed_batch_loses_elements_of_each_body_and_isolated_nodes_lose_all_mass():
    a, b = tm.beam_mesh(3, 2, 2, dtype=torch.float64), tm.beam_tri_mesh(4, 2, dim=3, dtype=torch.float64)
    rest = torch.cat([a.vertices, b.vertices])
    parts = lambda keep_a, keep_b: [  # noqa: E731
        (a.elements[keep_a], material("stvk", "polar"), "tet"),
        (b.elements[keep_b] + a.vertices.shape[0], material("hooke", "polar"), "tri")]
    na, nb = a.elements.shape[0], b.elements.shape[0]
    model = tm.TensorMass.packed(rest, parts(slice(None), slice(None)))
    total = float(model.lumped_mass().sum())
    corner = torch.nonzero((a.elements == 0).any(1)).flatten()  # every element on node 0
    removed = model.remove_elements(torch.cat([corner, torch.tensor([na + 1, na + nb - 1])]))
    keep_a = torch.ones(na, dtype=torch.bool)
    keep_a[corner] = False
    keep_b = torch.ones(nb, dtype=torch.bool)
    keep_b[[1, nb - 1]] = False
    fresh = tm.TensorMass.packed(rest, parts(keep_a, keep_b))
    x = rest + 0.01 * torch.randn(rest.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    assert_same(model, fresh, x, torch.ones_like(x))
    assert float(model.lumped_mass()[0]) == 0.0  # node 0 has no element left: no mass, exactly
    torch.testing.assert_close(float(model.lumped_mass().sum()) + removed, total, rtol=1e-13, atol=0)
    assert bool((model.lumped_mass() >= 0).all())


@pytest.mark.parametrize("ids,message", [
    ([0, 0], "given twice"), ([-1], "out of range"), ([10**6], "out of range"),
    ([[1, 2]], "1-D integer"), ([0.5], "1-D integer"), ([3, 7], "already removed")])
def test_bad_ids_are_one_error_and_change_nothing(ids, message):
    mesh = tm.beam_mesh(2, 2, 2, dtype=torch.float64)
    model = tm.TensorMass(mesh, material("hooke", "polar"))
    model.remove_elements([7])
    before = {k: v.clone() for k, v in model.state_dict().items()}
    with pytest.raises(MeshError, match=message):
        model.remove_elements(ids)
    after = model.state_dict()
    assert before.keys() == after.keys()
    for k in before:
        assert torch.equal(before[k], after[k]), k


def test_removing_nothing_changes_nothing_and_everything_leaves_no_force():
    mesh = tm.beam_mesh(2, 1, 1, dtype=torch.float64)
    model = tm.TensorMass(mesh, material("hooke", "polar"))
    f = model(mesh.vertices * 1.01)
    assert model.remove_elements([]) == 0.0
    torch.testing.assert_close(model(mesh.vertices * 1.01), f, rtol=0, atol=0)
    model.remove_elements(torch.arange(mesh.elements.shape[0]))
    assert float(model(mesh.vertices * 1.01).abs().max()) == 0.0
    assert float(model.lumped_mass().abs().max()) == 0.0


def node_graph_storage(model):
    """The storage of the node graphs cached on the model's groups (the hooke tensor form's)."""
    return [t.data_ptr() for g in model.groups for key in ("_native_hooke_graph",)
            if key in g.__dict__ for t in g.__dict__[key][2] if isinstance(t, torch.Tensor)]


DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
SCENES = {  # body models: two groups (element-by-element products), or one (the node-graph paths)
    "corotational+hooke": ("corotational", "hooke"), "hooke": ("hooke",), "corotational": ("corotational",),
    "stvk": ("stvk",)}


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("scene", SCENES)
def test_a_simulator_step_after_removals_is_that_of_a_simulator_of_the_remaining_elements(device, scene):
    """Bodies in one batch lose elements between steps (the beam loses every element on a node:
    that node leaves the system); the next steps equal those of a simulator built from the
    remaining elements at the same state, the mass is accounted for, and nothing was rebuilt:
    the system, its solver caches (captured CUDA graphs) and the model's buffers are the same
    storage."""
    beam, sheet = tm.beam_mesh(4, 2, 2, dtype=torch.float64), tm.beam_tri_mesh(5, 3, dim=3, dtype=torch.float64)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), sheet.elements)
    materials = [material(name, "polar") for name in SCENES[scene]]
    meshes = [beam, sheet][:len(materials)]
    fixed = [m.vertices[:, 0] == 0 for m in meshes]

    def simulator(meshes):
        # a vertex no element uses must be fixed (tm.Body): the removals' isolated node is held as well
        holds = [f | torch.isin(torch.arange(m.num_vertices), m.unused_vertices()) for f, m in zip(fixed, meshes)]
        bodies = [tm.Body(m, mat, fixed=f, name=name) for m, mat, f, name in zip(meshes, materials, holds, "ab")]
        return tm.Simulator(bodies, dt=0.01, cg_tol=1e-12, check_inversion="warn", device=device)

    sim = simulator(meshes)
    total = float(sim.model.lumped_mass().sum())
    sim.step(3)
    last = beam.num_vertices - 1  # the far corner: its elements all go
    corner = torch.nonzero((beam.elements == last).any(1)).flatten()
    sim.step(2)  # a second run of steps: on CUDA the captured step graphs exist before the removal
    lost = sim.remove_elements("a", torch.cat([corner, torch.tensor([0, 9])]))
    system, caches = sim.system, (sim.system._cg, dict(sim.system._matvecs), dict(sim.system._step_graphs))
    storage = {name: t.data_ptr() for name, t in sim.model.named_buffers()}
    graphs = node_graph_storage(sim.model)
    lost += sim.remove_elements("a", [4, 20])
    if len(meshes) == 2:
        lost += sim.remove_elements(1, [2, 3, 17])
    assert sim.alive_elements(0).sum() == beam.elements.shape[0] - corner.numel() - 4
    assert sim.system is system and (system._cg, system._matvecs, system._step_graphs) == caches
    assert {name: t.data_ptr() for name, t in sim.model.named_buffers()} == storage
    kept = [type(m)(m.vertices, m.elements[sim.alive_elements(i).cpu()], check=False) for i, m in enumerate(meshes)]
    fresh = simulator(kept)
    fresh.x, fresh.v = sim.x.clone(), sim.v.clone()
    sim.step(3)
    fresh.step(3)
    assert node_graph_storage(sim.model) == graphs  # updated in place, not built again
    torch.testing.assert_close(sim.x, fresh.x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(sim.v, fresh.v, rtol=1e-12, atol=1e-12)
    assert float(sim.v[last].abs().max()) == 0.0  # the isolated corner stays put
    torch.testing.assert_close(float(sim.model.lumped_mass().sum()) + lost, total, rtol=1e-13, atol=0)
    torch.testing.assert_close(float(sim.removed_mass.sum()), lost, rtol=1e-13, atol=0)
    assert int(sim.last_inversion.inverted.sum()) == 0


def test_a_simulator_refuses_bad_removals_and_changes_nothing():
    sim = tm.Simulator([tm.Body(tm.beam_mesh(2, 1, 1, dtype=torch.float64), material("hooke", "polar"),
                                name="b")])
    sim.remove_elements(0, [1])
    before = (sim.model.lumped_mass().clone(), sim.alive_elements(0).clone())
    for body, ids, message in [(0, [12], "out of range: body 0 has 12 elements"), (0, [1], "already removed"),
                               ("nope", [0], "no body named"), (3, [0], "body index"), (0, [2, 2], "twice")]:
        with pytest.raises((MeshError, tm.SceneError), match=message):
            sim.remove_elements(body, ids)
    assert torch.equal(sim.model.lumped_mass(), before[0]) and torch.equal(sim.alive_elements(0), before[1])


def test_a_model_never_cut_holds_nothing_for_removals_and_one_moved_after_building_can_be_cut():
    mesh = tm.beam_mesh(2, 1, 1, dtype=torch.float32)
    model = tm.TensorMass(mesh, material("hooke", "polar"))
    names = {n for n, _ in model.named_buffers()}
    assert not any(k in n for n in names for k in ("removed", "element_group", "element_row", "element_mass",
                                                   "node_elements", "edge_elements"))
    assert bool(model.alive_elements().all())
    model = model.to(torch.float64)  # its materials' tensors stay float32: the removal converts them
    model.remove_elements([0, 5])
    fresh = tm.TensorMass.packed(mesh.vertices, [(mesh.elements[1:5], material("hooke", "polar"), "tet"),
                                                 (mesh.elements[6:], material("hooke", "polar"), "tet")]).to(torch.float64)
    x = mesh.vertices.double() * 1.01
    # both hold float32 data widened: their float32 sums were rounded in another order
    torch.testing.assert_close(model.lumped_mass(), fresh.lumped_mass(), rtol=1e-6, atol=0)
    torch.testing.assert_close(model(x), fresh(x), rtol=1e-6, atol=1e-6 * float(fresh(x).abs().max()))


def test_a_cut_through_the_section_lets_the_far_piece_fall_and_equals_a_simulator_of_the_cut_mesh():
    """A clamped beam cut through its whole section between steps: the far piece falls freely
    (no force holds it: its centre accelerates at g), the near one stays clamped; the step after
    the cut is that of a simulator built from the cut mesh at the same state; removed elements
    stay removed and positions, velocities and time carry over."""
    mesh = tm.beam_mesh(6, 2, 2, size=(1.2, 0.4, 0.4), dtype=torch.float64)
    mat = material("corotational", "polar")
    fixed = mesh.vertices[:, 0] == 0
    sim = tm.Simulator([tm.Body(mesh, mat, fixed=fixed, name="beam")], dt=0.01, cg_tol=1e-12, rayleigh_mass=0.0)
    sim.step(2)
    sim.remove_elements(0, [0, 1])
    blade = tm.Blade.swept((0.61, -1, -1), (0.61, 2, -1), (0.61, -1, 2), (0.61, 2, 2))
    before = sim.positions(0).clone()
    added = sim.cut("beam", blade)
    assert added == 9 and sim.positions(0).shape[0] == mesh.num_vertices + 9
    cut_mesh = sim.bodies[0].mesh
    torch.testing.assert_close(sim.positions(0)[:mesh.num_vertices], before)  # the old nodes where they were
    assert sim.time == pytest.approx(0.02) and not bool(sim.alive_elements(0)[:2].any())
    fresh = tm.Simulator([tm.Body(cut_mesh, mat, fixed=sim.bodies[0].fixed, name="beam")], dt=0.01, cg_tol=1e-12)
    fresh.remove_elements(0, [0, 1])
    fresh.x, fresh.v = sim.positions(0).clone(), sim.velocities(0).clone()
    mass = sim.model.lumped_mass()[:cut_mesh.num_vertices]
    far = torch.zeros(cut_mesh.num_vertices, dtype=torch.bool)
    far[cut_mesh.elements[cut_mesh.vertices[cut_mesh.elements].mean(1)[:, 0] > 0.6].reshape(-1)] = True
    centre_velocity = lambda v: (mass[far, None] * v[far]).sum(0) / mass[far].sum()  # noqa: E731
    start = centre_velocity(sim.velocities(0))
    sim.step(5)
    fresh.step(5)
    torch.testing.assert_close(sim.positions(0), fresh.x, rtol=1e-12, atol=1e-12)
    # the far piece's centre of mass falls at g: nothing holds it, its elastic forces sum to zero
    # (implicit Euler: M dv = h (f + M g) with sum f = 0 over the piece, so dv_centre = h g a step)
    torch.testing.assert_close(centre_velocity(sim.velocities(0)) - start,
                               torch.tensor([0.0, 0.0, -9.81 * 5 * 0.01], dtype=torch.float64), rtol=0, atol=1e-9)
    with pytest.raises(MeshError, match="crosses no interior face"):
        sim.cut(0, tm.Blade.swept((5, -1, -1), (5, 2, -1), (5, -1, 2), (5, 2, 2)))
