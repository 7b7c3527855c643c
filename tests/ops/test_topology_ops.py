"""The topology op family (``ops.topology``: ``topology_refresh_nodes``,
``topology_refresh_hooke_edges``) and the node graph's ``node_graph_write_edges``: each op's writes
equal its pure-torch reference on real meshes (tetrahedra, planar triangles, membranes; float64;
targets touched by several removed elements), bitwise where both sum the same values in the same
order; the refreshed targets are those of a model assembled from the remaining elements (bitwise
for the masses); an emptied target holds exactly 0 and untouched ones are not written; CUDA
equals the CPU and repeats itself; bad arguments raise naming them and write nothing."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.ops import library, node_graph, topology

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
KINDS = [("tet", 3), ("tri", 2), ("tri", 3)]


def mesh_of(kind, dim):
    if kind == "tet":
        return tm.beam_mesh(5, 3, 3, size=(1.0, 0.6, 0.6), dtype=torch.float64)
    return tm.beam_tri_mesh(6, 4, size=(1.0, 0.6), dim=dim, dtype=torch.float64)


def material_of(n, keep=None):
    young = torch.linspace(1e4, 3e4, n, dtype=torch.float64)
    return tm.Material(model="hooke", young=young if keep is None else young[keep], poisson=0.3, density=900.0)


def prepared(kind, dim, device):
    """A hooke tensor-form model that has made what removals need, and its group."""
    mesh = mesh_of(kind, dim)
    model = tm.TensorMass(mesh, material_of(mesh.elements.shape[0]), form="tensor").to(device)
    model._prepare_removals()
    return mesh, model, model.groups[0]


def some_rows(n, count, device, seed=3):
    gen = torch.Generator().manual_seed(seed)
    return torch.randperm(n, generator=gen)[:count].to(device)


def edge_args(model, group, rows, removed):
    return (model.rest, group.elements, rows.to(group.elements.dtype), group.element_edges, group.edge_slots, model.element_row, removed,
            group.measure, group.young, group.poisson, group.edge_k.clone())


def flagged(model, rows):
    removed = model.removed.clone()
    removed[rows] = True
    return removed


@pytest.mark.parametrize("kind,dim", KINDS)
@pytest.mark.parametrize("device", DEVICES)
def test_refresh_hooke_edges_equals_its_reference_and_a_fresh_assembly(kind, dim, device):
    mesh, model, group = prepared(kind, dim, device)
    n = mesh.elements.shape[0]
    rows = some_rows(n, n // 3, device)
    removed = flagged(model, rows)
    args, ref_args = edge_args(model, group, rows, removed), edge_args(model, group, rows, removed)
    library.op("topology_refresh_hooke_edges")(*args)
    topology._ref_topology_refresh_hooke_edges(*ref_args)
    scale = float(group.edge_k.abs().max())
    torch.testing.assert_close(args[-1], ref_args[-1], rtol=0, atol=1e-13 * scale)
    keep = ~removed.cpu()
    fresh = tm.TensorMass(type(mesh)(mesh.vertices, mesh.elements[keep]), material_of(n, keep),
                          form="tensor").groups[0]
    touched = torch.zeros(group.edges.shape[0], dtype=torch.bool, device=device)
    touched[group.element_edges[rows].reshape(-1)] = True
    assert not torch.equal(args[-1][touched], group.edge_k[touched])
    assert torch.equal(args[-1][~touched], group.edge_k[~touched])  # nothing else written
    # the edges a fresh assembly has are those with an element left, in the same order
    alive = torch.zeros_like(touched)
    alive[group.element_edges[keep.to(device)].reshape(-1)] = True
    assert torch.equal(group.edges[alive].cpu(), fresh.edges)
    torch.testing.assert_close(args[-1][alive].cpu(), fresh.edge_k, rtol=0, atol=1e-13 * scale)
    assert bool((~alive).any()) and bool((args[-1][~alive] == 0).all())  # emptied edges: exactly 0


@pytest.mark.parametrize("device", DEVICES)
def test_refresh_nodes_equals_its_reference_and_a_fresh_model_bitwise(device):
    mesh, model, group = prepared("tet", 3, device)
    n = mesh.elements.shape[0]
    rows = some_rows(n, n // 2, device, seed=11)
    removed = flagged(model, rows)
    outs = []
    for fn in (library.op("topology_refresh_nodes"), topology._ref_topology_refresh_nodes):
        mass, counts = model.mass.clone(), model.node_elements.clone()
        fn(group.elements, rows.to(group.elements.dtype), model.node_slots, model.element_share, removed, mass, counts)
        outs.append((mass, counts))
    assert torch.equal(outs[0][0], outs[1][0]) and torch.equal(outs[0][1], outs[1][1])
    mass, counts = outs[0]
    keep = ~removed.cpu()
    fresh = tm.TensorMass(tm.TetMesh(mesh.vertices, mesh.elements[keep], check=False), material_of(n, keep),
                          form="tensor")
    assert torch.equal(mass.cpu(), fresh.lumped_mass())
    isolated = counts == 0
    assert bool(isolated.any()) and bool((mass[isolated] == 0).all())
    assert torch.equal(counts.cpu(), torch.bincount(mesh.elements[keep].reshape(-1), minlength=mesh.num_vertices)
                       .to(torch.int32))


@pytest.mark.parametrize("device", DEVICES)
def test_write_edges_equals_its_reference_bitwise(device):
    _, model, group = prepared("tet", 3, device)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    index, force_index, _ = library.plan_indices(group.plan)
    edge_k = group.edge_k * 3.0
    edge_ids = some_rows(edge_k.shape[0], 50, device).repeat(2)
    rows = torch.randperm(model.num_nodes).to(device=device, dtype=index.dtype)
    row_of = torch.empty_like(rows)
    row_of[rows.long()] = torch.arange(rows.numel(), device=device, dtype=rows.dtype)
    for by_rows in (None, row_of):
        got, want = node_k.clone(), node_k.clone()
        library.op("node_graph_write_edges")(edge_ids, index, force_index, edge_k, got, by_rows)
        node_graph._ref_node_graph_write_edges(edge_ids, index, force_index, edge_k, want, by_rows)
        assert torch.equal(got, want)
        assert not torch.equal(got, node_k)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_equals_cpu_and_repeats_itself():
    results = []
    for device in ("cpu", "cuda", "cuda"):
        mesh, model, group = prepared("tet", 3, device)
        rows = some_rows(mesh.elements.shape[0], 60, device, seed=2)
        args = edge_args(model, group, rows, flagged(model, rows))
        library.op("topology_refresh_hooke_edges")(*args)
        results.append(args[-1].cpu())
    assert torch.equal(results[1], results[2])
    torch.testing.assert_close(results[1], results[0], rtol=0, atol=1e-13 * float(results[0].abs().max()))


def test_bad_arguments_raise_naming_them_and_write_nothing():
    _, model, group = prepared("tet", 3, "cpu")
    rows = torch.tensor([0, 5])
    removed = flagged(model, rows)
    args = list(edge_args(model, group, rows, removed))
    before = args[-1].clone()
    other, name = (torch.int64, "Long") if group.elements.dtype == torch.int32 else (torch.int32, "Int")
    for position, bad, message in [(6, removed.to(torch.uint8), "removed must be bool"),
                                   (2, rows.to(other), f"rows is {name}"),
                                   (8, group.young[:-1], "young has shape"),
                                   (4, group.edge_slots[:, :-1].contiguous(), "edge_slots has shape")]:
        wrong = list(args)
        wrong[position] = bad
        with pytest.raises(RuntimeError, match=message):
            library.op("topology_refresh_hooke_edges")(*wrong)
    assert torch.equal(args[-1], before)
    mass, counts = model.mass.clone(), model.node_elements.clone()
    rows = rows.to(group.elements.dtype)
    with pytest.raises(RuntimeError, match="node_elements must be int32"):
        library.op("topology_refresh_nodes")(group.elements, rows, model.node_slots, model.element_share, removed,
                                             mass, counts.long())
    with pytest.raises(RuntimeError, match="element_share is"):
        library.op("topology_refresh_nodes")(group.elements, rows, model.node_slots, model.element_share.float(),
                                             removed, mass, counts)
    assert torch.equal(mass, model.mass) and torch.equal(counts, model.node_elements)
