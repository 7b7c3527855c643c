"""Precomputation of the paper's Algorithm 1: index, ForceIndex, N_n, CSR node lists."""
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh import topology
from tensormass_torch.mesh.topology import GatherPlan, expand_ranges, incidence_slots, node_element_lists, padded_sum
from tensormass_torch.ops.reference.gather import node_gather, scatter_partial_forces


def test_force_index_gives_each_incidence_its_own_slot():
    mesh = tm.beam_mesh(3, 2, 2)
    plan = GatherPlan.build(mesh.elements, mesh.num_vertices)
    pairs = plan.force_index * mesh.num_vertices + plan.index
    assert torch.unique(pairs).numel() == pairs.numel()  # no two writes to one slot: no atomics
    counts = torch.bincount(mesh.elements.reshape(-1), minlength=mesh.num_vertices)
    assert plan.num_slots == int(counts.max())
    assert torch.equal(plan.incidences, counts)
    # slots of node i are exactly 0 .. count_i - 1
    for node in (0, 5, mesh.num_vertices - 1):
        assert sorted(plan.force_index[plan.index == node].tolist()) == list(range(int(counts[node])))


def test_incidence_slots_follow_item_order():
    targets = torch.tensor([2, 0, 2, 1, 2, 0])
    slots, num_slots, counts = incidence_slots(targets, 4)
    assert slots.tolist() == [0, 0, 1, 0, 2, 1]
    assert num_slots == 3 and counts.tolist() == [2, 1, 3, 0]


def test_gather_equals_scatter_add():
    mesh = tm.beam_mesh(2, 3, 2, dtype=torch.float64)
    plan = GatherPlan.build(mesh.elements, mesh.num_vertices)
    partial = torch.randn(mesh.num_elements, 4, 3, dtype=torch.float64)
    total = node_gather(partial, plan.index, plan.force_index, plan.num_slots, plan.num_nodes)
    expected = torch.zeros(mesh.num_vertices, 3, dtype=torch.float64).index_add_(
        0, mesh.elements.reshape(-1), partial.reshape(-1, 3))
    torch.testing.assert_close(total, expected)
    padded = scatter_partial_forces(partial, plan.index, plan.force_index, plan.num_slots, plan.num_nodes)
    assert padded.shape == (plan.num_slots, mesh.num_vertices, 3)
    values = torch.randn(10, 2, dtype=torch.float64)
    targets = torch.tensor([0, 1, 1, 3, 3, 3, 0, 2, 2, 1])
    slots, n_slots, _ = incidence_slots(targets, 4)
    torch.testing.assert_close(padded_sum(values, targets, slots, n_slots, 4),
                               torch.zeros(4, 2, dtype=torch.float64).index_add_(0, targets, values))


def test_padded_sum_in_parts_is_the_sum_at_once_bitwise():
    """Items summed a part at a time into one ``out`` (parts in item order): a target's items
    are still added in slot order, so the sums are bitwise those of one call."""
    gen = torch.Generator().manual_seed(3)
    values = torch.randn(1000, 3, generator=gen, dtype=torch.float32) * 10 ** torch.randint(-3, 4, (1000, 1),
                                                                                             generator=gen)
    targets = torch.randint(0, 17, (1000,), generator=gen)
    slots, n_slots, _ = incidence_slots(targets, 17)
    at_once = padded_sum(values, targets, slots, n_slots, 17)
    total = torch.zeros(17, 3)
    for start in range(0, 1000, 97):
        part = slice(start, start + 97)
        assert padded_sum(values[part], targets[part], slots[part], n_slots, 17, out=total) is total
    assert torch.equal(total, at_once)


def test_node_element_lists():
    mesh = tm.beam_mesh(2, 2, 1)
    ptr, element_ids, local_ids = node_element_lists(mesh.elements, mesh.num_vertices)
    assert ptr[-1] == mesh.num_elements * 4
    for node in range(mesh.num_vertices):
        entries = slice(int(ptr[node]), int(ptr[node + 1]))
        assert torch.all(mesh.elements[element_ids[entries], local_ids[entries]] == node)
        assert torch.all(element_ids[entries][1:] > element_ids[entries][:-1])


def test_boundary_faces_of_a_beam():
    mesh = tm.beam_mesh(2, 1, 1)
    faces = topology.boundary_faces(mesh.elements)
    # 2 * (2*1 + 1*1 + 2*1) square faces on the boundary, 2 triangles each
    assert faces.shape == (20, 3)
    # outward: the divergence theorem gives the volume from the oriented boundary faces
    x = mesh.vertices.double()[faces]
    volume = (torch.linalg.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]) * x[:, 0]).sum() / 6
    assert volume.item() == pytest.approx(1.0, rel=1e-12)


def test_add_at_sums_the_same_every_run_with_threads():
    """add_at: the sums of values at repeated indices, equal to a float64 sum, and the same bits
    in every run with several threads (the CPU's index_put_ accumulation changed with its
    threads' timing: two runs of one pile parted after 20 steps)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(max(threads, 2))
    try:
        gen = torch.Generator().manual_seed(0)
        index = torch.randint(0, 5000, (200_000,), generator=gen)
        values = torch.randn(200_000, 9, generator=gen)
        runs = [topology.add_at(torch.zeros(5000, 9), index, values) for _ in range(10)]
    finally:
        torch.set_num_threads(threads)
    assert all(torch.equal(runs[0], run) for run in runs[1:])
    exact = torch.zeros(5000, 9, dtype=torch.float64).index_add_(0, index, values.double())
    torch.testing.assert_close(runs[0].double(), exact, rtol=0, atol=1e-4)


def test_expand_ranges_packs_each_range_in_turn():
    owner, item = expand_ranges(torch.tensor([5, 0, 9, 2]), torch.tensor([2, 0, 3, 1]))
    assert owner.tolist() == [0, 0, 2, 2, 2, 3]
    assert item.tolist() == [5, 6, 9, 10, 11, 2]
