"""Cuts in place: ``TensorMass.repoint_elements`` (a cut's elements re-pointed to new nodes in
spare rows: the lists of the gather plans, the hooke tensor form's edges and the lumped masses
edited where they change) and ``Simulator.cut`` with room for it (``spare_nodes``), checked
against models and simulators built afresh from the cut mesh (forces, force differentials,
energy, masses, steps to 1e-12 in float64, every model, form and 3-D element kind, the CPU
extension, the pure-torch path and CUDA), interleaved with removals; a cut with no room left
builds the simulator again with more, and equals it as well."""
from __future__ import annotations

import pytest
import torch
from test_topology_changes import BACKENDS, CASE_IDS, CASES, DEVICES, assert_same, material, mesh_of

import tensormass_torch as tm
from tensormass_torch.errors import CapacityError, SceneError
from tensormass_torch.mesh import cutting
from tensormass_torch.ops import node_graph
from tensormass_torch.physics.groups import ElementGroup

CASES_3D = [(case, name) for case, name in zip(CASES, CASE_IDS) if case[1] == 3]


@pytest.fixture(params=BACKENDS)
def backend(request, monkeypatch):
    monkeypatch.setenv("TENSORMASS_BACKEND", request.param)
    return request.param


@pytest.fixture(params=["own tables", "host copies"])
def planned_on(request, monkeypatch):
    """Where a cut is planned: the model's own tables (a model on the CPU) or host copies of
    them (a model on an accelerator: ``ElementGroup.cut_tables``), made here on the CPU too so
    that that path is checked on every machine."""
    if request.param == "host copies":
        monkeypatch.setattr(ElementGroup, "_plans_on_a_copy", lambda self: True)
    return request.param


def blades(kind):
    """Three cuts across the body: two through it, one a slit (its front stays joined)."""
    if kind == "tet":
        return [cutting.Blade.swept((x, -1, -1), (x, -1, 2), (x, 2, -1), (x, 2, 2)) for x in (0.5, 0.26, 0.74)]
    return [cutting.Blade.swept((x, -1, -1), (x, -1, 1), (x, top, -1), (x, top, 1))
            for x, top in ((0.5, 0.3), (0.26, 0.5), (0.74, 0.7))]


class Used:
    """The first ``used`` rows of a model over spare rows, as a model of those nodes."""

    def __init__(self, model, rest, used):
        self.model, self.rest, self.used = model, rest, used

    def _pad(self, x, value):
        return torch.cat([x, self.rest[self.used:] if value is None else torch.zeros_like(self.rest[self.used:])])

    def __call__(self, x):
        return self.model(self._pad(x, None))[:self.used]

    def dforce(self, x, dx):
        return self.model.dforce(self._pad(x, None), self._pad(dx, 0))[:self.used]

    def energy(self, x):
        return self.model.energy(self._pad(x, None))

    def lumped_mass(self):
        return self.model.lumped_mass()[:self.used]


@pytest.mark.parametrize("case", [c for c, _ in CASES_3D], ids=[n for _, n in CASES_3D])
def test_cuts_in_place_leave_the_model_of_the_cut_mesh(backend, planned_on, case):
    kind, dim, model_name, form, rotation = case
    mesh = mesh_of(kind, dim)
    count, spare = mesh.elements.shape[0], 40
    young = torch.linspace(1e4, 3e4, count, dtype=torch.float64)  # per element: rows stay matched
    rest = torch.cat([mesh.vertices, mesh.vertices[:1].expand(spare, 3)])
    model = tm.TensorMass.packed(rest, [(mesh.elements, material(model_name, rotation, young), kind)], form=form)
    model.reserve_slots()
    gen = torch.Generator().manual_seed(5)
    elements, vertices, alive, slit = mesh.elements.clone(), mesh.vertices, torch.ones(count, dtype=torch.bool), None
    removed = torch.randperm(count, generator=gen)[:3]
    model.remove_elements(removed)
    alive[removed] = False
    for blade in blades(kind):
        used = vertices.shape[0]
        result = cutting.cut(elements, used, vertices, blade, ~alive, slit)
        changed = torch.nonzero((result.elements != elements).any(1)).flatten()
        model.repoint_elements(changed, result.elements[changed], torch.arange(used, result.parents.shape[0]),
                               result.parents[used:])
        elements, vertices, slit = result.elements, vertices[result.parents], result.slit
        used = vertices.shape[0]
        fresh = tm.TensorMass.packed(vertices, [(elements[alive], material(model_name, rotation, young[alive]), kind)],
                                     form=form)
        x = vertices + 0.02 * torch.randn(vertices.shape, generator=gen, dtype=torch.float64)
        dx = torch.randn(vertices.shape, generator=gen, dtype=torch.float64)
        assert_same(Used(model, rest, used), fresh, x, dx)
        spare_rows = torch.cat([x, rest[used:]])
        assert float(model(spare_rows)[used:].abs().max()) == 0.0 and float(model.lumped_mass()[used:].max()) == 0.0
    assert used > mesh.num_vertices  # the cuts split nodes


def test_a_cut_that_needs_more_slots_than_the_plan_has_changes_nothing():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    rest = torch.cat([mesh.vertices, mesh.vertices[:1].expand(40, 3)])
    model = tm.TensorMass.packed(rest, [(mesh.elements, material("hooke", "polar"), "tet")], form="tensor")
    # no slots reserved (model.reserve_slots): the plan's last slot, which the edges a cut
    # empties would take, is a node's, so a cut does not fit
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blades("tet")[0])
    changed = torch.nonzero((result.elements != mesh.elements).any(1)).flatten()
    before = {name: t.clone() for name, t in model.named_buffers()}
    x = rest * 1.01
    forces = model(x)
    with pytest.raises(CapacityError, match="room for"):
        model.repoint_elements(changed, result.elements[changed], torch.arange(mesh.num_vertices,
                                                                               result.parents.shape[0]),
                               result.parents[mesh.num_vertices:])
    assert all(torch.equal(t, before[name]) for name, t in model.named_buffers() if name in before)
    assert torch.equal(model(x), forces)


SCENES = {"hooke": ("hooke",), "corotational": ("corotational",), "corotational+hooke": ("corotational", "hooke"),
          "stvk": ("stvk",)}


def node_graph_storage(model):
    return [t.data_ptr() for g in model.groups for key in ("_native_hooke_graph", "_native_tangent_graph", "_native_by_rows_tangent")
            if key in g.__dict__ for t in g.__dict__[key][2] if isinstance(t, torch.Tensor)]


def assert_tangent_graph_is_a_builds(group):
    """The stress form's tangent graph as the cuts edited it in place on the CPU
    (``tangent_topology_changed`` with the cut: not built again) holds a build's edges from the group's elements now, each with
    a build's members in a build's ranks (its sums bitwise a build's), and each node lists a
    build's edges (in another order), by node and by rows."""
    from tensormass_torch.mesh.topology import EdgeGraph

    assert "_tangent_members" in group.__dict__  # edited, not built again (a build drops it)
    graph, neighbor, incidences = group.__dict__["_native_tangent_graph"][2]
    built = EdgeGraph.build(group.elements.long().cpu(), group.num_nodes)
    edges, counts = graph.edges.long().cpu(), graph.edge_counts.long().cpu()
    alive = counts > 0
    key = lambda e: (e[:, 0] * group.num_nodes + e[:, 1]).tolist()  # noqa: E731
    assert sorted(key(edges[alive])) == key(built.edges)
    row_of_key = dict(zip(key(edges[alive]), torch.nonzero(alive).flatten().tolist()))
    renumber = torch.tensor([row_of_key[k] for k in key(built.edges)])  # a build's edge -> the graph's
    assert torch.equal(counts[renumber], built.edge_counts.long())
    assert torch.equal(graph.element_edges.long().cpu(), renumber[built.element_edges.long()])
    assert torch.equal(graph.edge_slots.long().cpu(), built.edge_slots.long())
    used = torch.arange(neighbor.shape[0])[:, None] < incidences.long().cpu()[None, :]
    assert torch.equal(incidences.long().cpu(), built.plan.incidences.long())
    fresh_neighbor = torch.zeros_like(built.slot_edge)
    code = built.slot_edge
    edge = torch.where(code >= 0, code, -code - 1)
    fresh_neighbor = torch.where(code >= 0, built.edges[edge, 1], built.edges[edge, 0])
    fresh_used = torch.arange(fresh_neighbor.shape[0])[:, None] < built.plan.incidences[None, :]
    for node in range(group.num_nodes):  # the same neighbours, in another order
        assert sorted(neighbor.cpu()[used[:, node], node].tolist()) == sorted(fresh_neighbor[fresh_used[:, node],
                                                                                             node].tolist())
    rows_cache = group.__dict__.get("_native_by_rows_tangent")
    if rows_cache is not None and rows_cache[3] is not None:
        rows = rows_cache[3].long()
        for by_rows, tensor in zip(rows_cache[2], (neighbor, incidences, graph.slot_edge)):
            assert torch.equal(by_rows, tensor.index_select(1 if tensor.dim() >= 2 else 0, rows))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("scene", SCENES)
def test_a_simulator_cuts_in_place_and_steps_as_a_simulator_of_the_cut_meshes(device, planned_on, scene):
    """Bodies with spare rows cut between steps (through, then a slit), with removals between:
    the steps after each cut equal those of a simulator built from the cut meshes at the same
    state; nothing was rebuilt (the model, the node graphs' storage, the hooke tensor form's and the
    stress forms' tangent graphs, and on the CPU the integrator, are the same)."""
    beam = tm.beam_mesh(6, 2, 2, size=(1.2, 0.4, 0.4), origin=(0.0, -0.2, -0.2), dtype=torch.float64)
    sheet = tm.beam_tri_mesh(6, 3, size=(0.6, 0.3), dim=3, dtype=torch.float64)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, -1.0, 0.3], dtype=torch.float64), sheet.elements)
    materials = [material(name, "polar") for name in SCENES[scene]]
    if len(materials) == 2:
        materials[1] = tm.Material(model="hooke", young=2e4, poisson=0.3, density=800.0, thickness=0.01)

    def bodies_of(meshes, fixed):
        return [tm.Body(m, mat, fixed=f, name=name) for m, mat, f, name in zip(meshes, materials, fixed, "ab")]

    meshes = [beam, sheet][:len(materials)]
    sim = tm.Simulator(bodies_of(meshes, [m.vertices[:, 0] == 0 for m in meshes]), dt=0.01, cg_tol=1e-12,
                       device=device, spare_nodes=64)
    sim.step(3)
    model, system, graphs = sim.model, sim.system, node_graph_storage(sim.model)
    def edge_arrays():  # the hooke tensor-form groups' edge arrays
        return [id(t) for g in model.groups if hasattr(g, "edge_rows_used") for t in (g.edges, g.edge_k,
                                                                                     g.plan.force_index)]

    before = edge_arrays()
    cuts = [(0, tm.Blade.swept((0.61, -1, -1), (0.61, 2, -1), (0.61, -1, 2), (0.61, 2, 2))),
            (0, tm.Blade.swept((0.3, -1, -1), (0.3, 0.05, -1), (0.3, -1, 2), (0.3, 0.05, 2)))]
    if len(meshes) == 2:
        cuts.append((1, tm.Blade.swept((0.3, -2, -1), (0.3, -0.8, -1), (0.3, -2, 2), (0.3, -0.8, 2))))
    for k, (body, blade) in enumerate(cuts):
        if k == 1:
            sim.remove_elements(0, [0, 5])
        assert sim.cut(body, blade) > 0
        assert sim.model is model
        # the new edges taken from the pool of edge rows: no edge array moved
        assert edge_arrays() == before
        if device == "cpu":  # (on CUDA a chunk of the pipelined solve may outgrow its launches)
            assert sim.system is system
        fresh = tm.Simulator(bodies_of([b.mesh for b in sim.bodies], [b.fixed for b in sim.bodies]), dt=0.01,
                             cg_tol=1e-12, device=device)
        for i in range(sim.num_bodies):
            removed = torch.nonzero(~sim.alive_elements(i)).flatten()
            if removed.numel():
                fresh.remove_elements(i, removed)
        fresh.x = torch.cat([sim.positions(i) for i in range(sim.num_bodies)])
        fresh.v = torch.cat([sim.velocities(i) for i in range(sim.num_bodies)])
        sim.step(2)
        fresh.step(2)
        for i in range(sim.num_bodies):
            torch.testing.assert_close(sim.positions(i), fresh.positions(i), rtol=1e-12, atol=1e-12)
            torch.testing.assert_close(sim.velocities(i), fresh.velocities(i), rtol=1e-12, atol=1e-12)
    # the node graphs (hooke, tangent) written in place, not built again
    assert graphs and node_graph_storage(model) == graphs
    for group in model.groups:
        if "_native_tangent_graph" in group.__dict__ and device == "cpu":  # (built again on an accelerator)
            assert_tangent_graph_is_a_builds(group)
    if scene == "hooke":
        group = model.groups[0]  # its node graph as cached (by rows), as one built from its edges now
        cache = group.__dict__["_native_hooke_graph"]  # (what the steps read, not a graph built now)
        (neighbor, node_k, incidences), rows = cache[2], cache[3]
        fresh_neighbor, fresh_node_k = node_graph.graph_of_edges(group.edges, group.plan.force_index,
                                                                 group.plan.num_slots, group.num_nodes, group.edge_k)
        if rows is not None:
            fresh_neighbor, fresh_node_k = fresh_neighbor[:, rows.long()], fresh_node_k[:, rows.long()]
        assert torch.equal(incidences.long(), group.plan.incidences[rows.long()].long() if rows is not None
                           else group.plan.incidences.long())
        read = torch.arange(neighbor.shape[0], device=neighbor.device)[:, None] < incidences[None, :]
        assert torch.equal(neighbor[read], fresh_neighbor.to(neighbor.dtype)[read])
        assert torch.equal(node_k[read], fresh_node_k[read])


def test_a_cut_with_no_room_builds_the_simulator_again_with_room_and_the_next_cuts_run_in_place():
    beam = tm.beam_mesh(6, 2, 2, size=(1.2, 0.4, 0.4), origin=(0.0, -0.2, -0.2), dtype=torch.float64)
    sim = tm.Simulator([tm.Body(beam, material("hooke", "polar"), fixed=beam.vertices[:, 0] == 0)], dt=0.01,
                       cg_tol=1e-12, spare_nodes=2)
    sim.step()
    model = sim.model
    added = sim.cut(0, tm.Blade.swept((0.61, -1, -1), (0.61, 2, -1), (0.61, -1, 2), (0.61, 2, 2)))
    assert added > 2 and sim.model is not model  # no room: built again
    assert sim.ptr[1] - sim.used_nodes[0] >= tm.sim.simulator.MIN_SPARE_NODES
    model = sim.model
    sim.cut(0, tm.Blade.swept((0.3, -1, -1), (0.3, 2, -1), (0.3, -1, 2), (0.3, 2, 2)))
    assert sim.model is model  # in place
    assert sim.positions(0).shape == (sim.bodies[0].mesh.num_vertices, 3)
    assert sim.bodies[0].mesh.num_vertices > beam.num_vertices + added  # the second cut's nodes


@pytest.mark.parametrize("spare", [-1, 1.5, True, [1, 2], "4"])
def test_bad_spare_nodes_are_one_error(spare):
    with pytest.raises(SceneError, match="spare_nodes"):
        tm.Simulator([tm.Body(tm.beam_mesh(2, 1, 1), material("hooke", "polar"))], spare_nodes=spare)


def test_a_tangent_graph_with_no_room_for_a_cut_is_built_again():
    """A stress-form body whose tangent graph has no edge rows to spare: the cut drops it (built
    again at the next step, the integrator made again) and the steps equal a fresh simulator's."""
    beam = tm.beam_mesh(6, 2, 2, size=(1.2, 0.4, 0.4), origin=(0.0, -0.2, -0.2), dtype=torch.float64)
    mat = material("corotational", "polar")
    sim = tm.Simulator([tm.Body(beam, mat, fixed=beam.vertices[:, 0] == 0)], dt=0.01, cg_tol=1e-12, spare_nodes=64)
    sim.model.groups[0].reserved_edges = 0  # a cut adds edges: the graph cannot take them
    sim.step(3)
    system, graph = sim.system, sim.model.groups[0].__dict__.get("_native_tangent_graph")
    sim.cut(0, tm.Blade.swept((0.61, -1, -1), (0.61, 2, -1), (0.61, -1, 2), (0.61, 2, 2)))
    if graph is not None:  # (the pure-torch path has no tangent graph)
        assert sim.system is not system and "_native_tangent_graph" not in sim.model.groups[0].__dict__
    fresh = tm.Simulator([tm.Body(sim.bodies[0].mesh, mat, fixed=sim.bodies[0].fixed)], dt=0.01, cg_tol=1e-12)
    fresh.x, fresh.v = sim.positions(0).clone(), sim.velocities(0).clone()
    sim.step(2)
    fresh.step(2)
    torch.testing.assert_close(sim.positions(0), fresh.positions(0), rtol=1e-12, atol=1e-12)


def test_cuts_that_empty_edges_of_node_0_beside_the_edge_pool_leave_the_forces_of_the_cut_mesh(planned_on):
    """The pool's zero edges (0, 0) sit in node 0's sink slot, past its count: cuts that empty
    edges of node 0 (and take pool rows) keep them out of node 0's list."""
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=torch.float64)
    rest = torch.cat([mesh.vertices, mesh.vertices[:1].expand(80, 3)])
    mat = material("hooke", "polar")
    model = tm.TensorMass.packed(rest, [(mesh.elements, mat, "tet")], form="tensor")
    model.reserve_slots(spare_nodes=7)  # a pool that the cuts outgrow too
    elements, vertices, slit = mesh.elements.clone(), mesh.vertices, None
    gen = torch.Generator().manual_seed(0)
    for blade in (cutting.Blade.swept((-1, 0.1, -1), (2, 0.1, -1), (-1, 0.1, 2), (2, 0.1, 2)),
                  cutting.Blade.swept((0.6, -1, -1), (0.6, -1, 2), (0.6, 2, -1), (0.6, 2, 2)),
                  cutting.Blade.swept((0.35, -1, -1), (0.35, -1, 2), (0.35, 2, -1), (0.35, 2, 2)),
                  cutting.Blade.swept((-1, -1, 0.1), (2, -1, 0.1), (-1, 2, 0.1), (2, 2, 0.1))):
        used = vertices.shape[0]
        result = cutting.cut(elements, used, vertices, blade, None, slit)
        ids = torch.nonzero((result.elements != elements).any(1)).flatten()
        model.repoint_elements(ids, result.elements[ids], torch.arange(used, result.parents.shape[0]),
                               result.parents[used:])
        elements, vertices, slit = result.elements, vertices[result.parents], result.slit
        fresh = tm.TensorMass.packed(vertices, [(elements, mat, "tet")], form="tensor")
        x = vertices + 0.02 * torch.randn(vertices.shape, generator=gen, dtype=torch.float64)
        assert_same(Used(model, rest, vertices.shape[0]), fresh, x, torch.randn_like(x))
