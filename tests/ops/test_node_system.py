"""The node-centric CG matvec of the hooke tensor form: ``tensormass::hooke_node_system``.

One kernel, one thread per node, over the node graph's slot-major arrays (``node_graph.hooke_node_graph``:
neighbor [N_n, V], node_k [N_n, V, d, d]) in place of kernel 1 (padded partial forces) + kernel 2
(``gather_system``).

    1. the node graph: the plan's slots, K_e on an edge's first node and K_e^T on its second;
       cached, rebuilt when edge_k changes
    2. the op = the padded two-kernel path BITWISE (tets, 2-D triangles, 3-D membranes; float32 and
       float64; int32 and int64 indices; with and without free mask and node stiffness), = its
       float64 reference, = the composed matvec of ops.system_matvec under TENSORMASS_BACKEND=torch;
       unused slots are never read
    3. ops.system_matvec takes the node path by default, the padded one on request
       (``KernelVariants(hooke_matvec="padded")``), bitwise equal;
       gradients fall back to the differentiable path
    4. a Simulator run with the node layout = with the padded layout, bitwise
    5. input checks, no gradient, opcheck
    6. on CUDA (skipped without one; ``TENSORMASS_GPU_TEST_DEVICE=cpu`` dry-runs them on the CPU):
       node = padded bitwise on the device, = the CPU within rounding, run-to-run deterministic,
       capturable in a CUDA graph
    7. benchmarks/studies/node_system_bench.py --quick runs on the CPU

Skipped when the extension is not built with ``hooke_node_system``.
"""
from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import DTYPES, KINDS, build_scene, load_native, reference, rel, tol, with_variants

import tensormass_torch as tm
from tensormass_torch import Material, TensorMass, ops
from tensormass_torch.ops import library, node_graph, solve
from tensormass_torch.ops.variants import DEFAULT, KernelVariants

native = load_native("hooke_node_system", "gather_system", "tensor_hooke_partial_forces")
pytestmark = pytest.mark.skipif(native is None, reason="tensormass_torch._C (with hooke_node_system) is not built")

C_MASS, C_STIFF = 1.03, 0.0123
INDEX_DTYPES = (torch.int64, torch.int32)
#: the hooke tensor form's CG product over the node graph, and the padded two-kernel path
NODE, PADDED = KernelVariants(hooke_matvec="node"), KernelVariants(hooke_matvec="padded")
# (free mask, node stiffness)
EPILOGUES = [pytest.param(f, k, id=f"{'free' if f else 'all-free'}-{'nodek' if k else 'no-nodek'}")
             for f in (False, True) for k in (False, True)]


@pytest.fixture(autouse=True)
def _extension_backend(monkeypatch):
    """These tests check which path runs: the default dispatch even under TENSORMASS_BACKEND=torch."""
    monkeypatch.setenv("TENSORMASS_BACKEND", "auto")


def make_case(seed, kind, dtype, device="cpu"):
    """A hooke tensor-form group on a jittered small mesh, with p, mass, free mask, node stiffness."""
    rng = np.random.default_rng(seed)
    scene = build_scene(rng, kind)
    n = scene.elements.shape[0]
    mat = Material(young=torch.tensor(rng.uniform(1.0, 3.0, n)), poisson=torch.tensor(rng.uniform(0.1, 0.45, n)),
                   density=1.0, model="hooke", thickness=0.1)
    model = TensorMass(scene.mesh.to(dtype=dtype), mat, form="tensor").to(device)
    group = model.groups[0]
    assert group.form == "tensor" and group.model == "hooke"
    shape = tuple(scene.rest.shape)
    p = torch.tensor(rng.standard_normal(shape), dtype=dtype, device=device)
    mass = torch.tensor(rng.uniform(0.5, 2.0, shape[0]), dtype=dtype, device=device)
    free = torch.tensor(rng.uniform(size=shape[0]) > 0.3, dtype=dtype, device=device)
    normal = torch.tensor(rng.standard_normal(shape), dtype=dtype)
    k = torch.tensor(rng.uniform(size=shape[0]) * (rng.uniform(size=shape[0]) > 0.5), dtype=dtype)
    stiffness = (k[:, None, None] * normal[:, :, None] * normal[:, None, :]).to(device)  # contact-like k n n^T
    return group, p, mass, free, stiffness


def plan_arrays(group, index_dtype):
    plan = group.plan
    return tuple(t.to(index_dtype).contiguous() for t in (plan.index, plan.force_index, plan.incidences))


def padded_matvec(group, p, mass, free, stiffness, index_dtype):
    """The two-kernel path: tensor_hooke_partial_forces (kernel 1) + gather_system (kernel 2)."""
    index, force_index, incidences = plan_arrays(group, index_dtype)
    T = torch.ops.tensormass
    partial = T.tensor_hooke_partial_forces(p, index, force_index, group.plan.num_slots, group.edge_k.contiguous())
    return T.gather_system(partial, incidences, p, mass, free, C_MASS, C_STIFF, stiffness)


def node_matvec(group, p, mass, free, stiffness, index_dtype, by_rows=True):
    """The op over the group's graph by rows (node_graph.hooke_rows_graph), or in node order."""
    if by_rows:
        neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group)
        rows = None if rows is None else rows.to(index_dtype)
    else:
        (neighbor, node_k), incidences, rows = node_graph.hooke_node_graph(group), group.plan.incidences, None
    return torch.ops.tensormass.hooke_node_system(p, neighbor.to(index_dtype), node_k,
                                                  incidences.to(index_dtype).contiguous(), rows, mass, free, C_MASS,
                                                  C_STIFF, stiffness)


# --------------------------------------------------------------------- the node graph


@pytest.mark.parametrize("kind", KINDS)
def test_node_graph_holds_the_plan_slots(kind):
    group, *_ = make_case(1, kind, torch.float64)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    plan, edges, edge_k = group.plan, group.edges, group.edge_k
    d = edge_k.shape[-1]
    assert neighbor.shape == (plan.num_slots, plan.num_nodes) and neighbor.dtype == library.plan_indices(plan)[0].dtype
    assert node_k.shape == (plan.num_slots, plan.num_nodes, d, d) and node_k.dtype == edge_k.dtype
    expected_neighbor = torch.zeros(plan.num_slots, plan.num_nodes, dtype=torch.int64)
    expected_k = torch.zeros(plan.num_slots, plan.num_nodes, d, d, dtype=edge_k.dtype)
    seen = torch.zeros(plan.num_slots, plan.num_nodes, dtype=torch.int64)
    for e in range(edges.shape[0]):  # the definition, one edge at a time (small mesh)
        i, j = int(edges[e, 0]), int(edges[e, 1])
        si, sj = int(plan.force_index[e, 0]), int(plan.force_index[e, 1])
        expected_neighbor[si, i], expected_k[si, i] = j, edge_k[e]
        expected_neighbor[sj, j], expected_k[sj, j] = i, edge_k[e].T
        seen[si, i] += 1
        seen[sj, j] += 1
    used = torch.arange(plan.num_slots)[:, None] < plan.incidences[None, :]
    assert torch.equal(seen, used.long())  # every used slot exactly once, no other
    assert torch.equal(neighbor.long(), expected_neighbor)
    assert torch.equal(node_k, expected_k)


def test_node_graph_is_cached_and_rebuilt_when_edge_k_changes():
    group, *_ = make_case(2, "tet", torch.float64)
    first = node_graph.hooke_node_graph(group)
    again = node_graph.hooke_node_graph(group)
    assert first[0] is again[0] and first[1] is again[1]
    with torch.no_grad():
        group.edge_k.mul_(2.0)  # in place: a new version
    rebuilt = node_graph.hooke_node_graph(group)
    assert rebuilt[1] is not first[1]
    assert torch.equal(rebuilt[1], 2.0 * first[1]) and torch.equal(rebuilt[0], first[0])
    group.edge_k = group.edge_k.clone()  # a new tensor
    assert node_graph.hooke_node_graph(group)[1] is not rebuilt[1]


# --------------------------------------------------------------------- the graph's rows


def test_rows_sort_each_window_of_each_object_by_slot_count():
    counts = torch.tensor([5, 11, 5, 11, 7, 3, 3, 9, 2, 8, 8, 1], dtype=torch.int32)
    starts = (0, 5, 12)  # objects [0, 5) and [5, 12)
    rows = node_graph.node_graph_rows(counts, starts, window=3)
    # windows: [0, 3) [3, 5) of object 0, [5, 8) [8, 11) [11, 12) of object 1; most slots first,
    # ties in node order
    assert rows.tolist() == [1, 0, 2, 3, 4, 7, 5, 6, 9, 10, 8, 11]
    assert node_graph.node_graph_rows(counts, starts, window=1) is None
    assert node_graph.node_graph_rows(counts, starts, window=0) is None
    one_object = node_graph.node_graph_rows(counts, (0, 12), window=128)
    assert torch.equal(one_object, torch.sort(-counts.long(), stable=True).indices)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_rows_change_no_value(kind, dtype):
    group, p, mass, free, stiffness = make_case(12, kind, dtype)
    neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group)
    assert rows is not None and not torch.equal(rows.long(), torch.arange(p.shape[0]))  # a real permutation
    assert torch.equal(torch.sort(rows.long()).values, torch.arange(p.shape[0]))
    counts = group.plan.incidences
    assert torch.equal(incidences.long(), counts[rows.long()].long())
    assert bool((incidences[1:] <= incidences[:-1]).all())  # one window, one object: decreasing
    for index_dtype in INDEX_DTYPES:
        by_rows = node_matvec(group, p, mass, free, stiffness, index_dtype)
        by_node = node_matvec(group, p, mass, free, stiffness, index_dtype, by_rows=False)
        assert torch.equal(by_rows[0], by_node[0]) and torch.equal(by_rows[1], by_node[1])
    ref = reference("hooke_node_system")(p, neighbor, node_k, incidences, rows, mass, free, C_MASS, C_STIFF,
                                                stiffness)
    assert rel(by_rows[0], ref[0]) < tol(dtype) and rel(by_rows[1], ref[1]) < tol(dtype)


def test_rows_keep_to_their_object():
    mesh = tm.beam_mesh(3, 1, 1, size=(0.3, 0.1, 0.1), dtype=torch.float64)
    mat = tm.Material(young=2e4, poisson=0.3, density=1000.0, model="hooke")
    sim = tm.Simulator([tm.Body(mesh, mat), tm.Body(mesh, mat), tm.Body(mesh, mat)], dt=0.01, form="tensor")
    group = sim.system.model.groups[0]
    rows = node_graph.hooke_rows_graph(group)[3].long()
    per_object = mesh.vertices.shape[0]
    row_object = torch.arange(rows.numel()) // per_object
    assert torch.equal(rows // per_object, row_object)  # each object's rows are its own nodes
    assert not torch.equal(rows, torch.arange(rows.numel()))
    node_graph.set_objects(sim.system.model, sim.segments.ptr)  # the same objects again: fine
    with pytest.raises(ValueError, match="need a model of their own"):
        node_graph.set_objects(sim.system.model, [0, 3 * per_object])
    assert node_graph.hooke_rows_graph(group)[3] is not None and torch.equal(node_graph.hooke_rows_graph(group)[3].long(), rows)


# --------------------------------------------------------------------- the op


@pytest.mark.parametrize("with_free,with_node_k", EPILOGUES)
@pytest.mark.parametrize("index_dtype", INDEX_DTYPES, ids=["i64", "i32"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_op_equals_padded_path_bitwise(kind, dtype, index_dtype, with_free, with_node_k):
    group, p, mass, free, stiffness = make_case(3, kind, dtype)
    free = free if with_free else None
    stiffness = stiffness if with_node_k else None
    ap, dot = node_matvec(group, p, mass, free, stiffness, index_dtype)
    assert ap.shape == p.shape and dot.shape == (p.shape[0],) and ap.dtype == dtype and dot.dtype == dtype
    pad_ap, pad_dot = padded_matvec(group, p, mass, free, stiffness, index_dtype)
    assert torch.equal(ap, pad_ap) and torch.equal(dot, pad_dot)
    if with_free:
        assert bool((ap[free == 0] == 0).all())


@pytest.mark.parametrize("with_free,with_node_k", EPILOGUES)
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_op_equals_reference_and_composed_matvec(monkeypatch, kind, dtype, with_free, with_node_k):
    group, p, mass, free, stiffness = make_case(4, kind, dtype)
    free = free if with_free else None
    stiffness = stiffness if with_node_k else None
    ap, dot = node_matvec(group, p, mass, free, stiffness, torch.int64)
    # the float64 reference on the same graph
    neighbor, node_k = node_graph.hooke_node_graph(group)
    incidences = group.plan.incidences
    f64 = [None if t is None else t.double() for t in (p, node_k, mass, free, stiffness)]
    ref_ap, ref_dot = reference("hooke_node_system")(f64[0], neighbor, f64[1], incidences, None, f64[2],
                                                             f64[3], C_MASS, C_STIFF, f64[4])
    assert rel(ap, ref_ap) < tol(dtype) and rel(dot, ref_dot) < tol(dtype)
    # the composed matvec (mass term - K p with K p from the torch reference of dforces)
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    t_ap, t_dot = ops.system_matvec([group], torch.zeros_like(p), p, mass, free, C_MASS, C_STIFF,
                                    node_stiffness=stiffness)
    assert rel(ap, t_ap) < tol(dtype, group) and rel(dot, t_dot) < tol(dtype, group)


def test_unused_slots_are_never_read():
    group, p, mass, free, stiffness = make_case(5, "tet", torch.float64)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    incidences = group.plan.incidences.to(neighbor.dtype)
    unused = torch.arange(neighbor.shape[0])[:, None] >= incidences[None, :]
    assert bool(unused.any())
    # garbage where no slot is used: a far out-of-range neighbour and NaN tensors
    bad_neighbor = torch.where(unused, torch.full_like(neighbor, 2**30), neighbor)
    bad_k = torch.where(unused[..., None, None], torch.full_like(node_k, float("nan")), node_k)
    T = torch.ops.tensormass
    got = T.hooke_node_system(p, bad_neighbor, bad_k, incidences, None, mass, free, C_MASS, C_STIFF, stiffness)
    want = T.hooke_node_system(p, neighbor, node_k, incidences, None, mass, free, C_MASS, C_STIFF, stiffness)
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    ref = reference("hooke_node_system")(p, bad_neighbor, bad_k, incidences, None, mass, free, C_MASS,
                                                C_STIFF, stiffness)
    assert rel(got[0], ref[0]) < 1e-12 and bool(torch.isfinite(ref[0]).all())


# --------------------------------------------------------------------- dispatch


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_system_matvec_uses_the_node_layout(monkeypatch, kind, dtype):
    group, p, mass, free, stiffness = make_case(6, kind, dtype)
    u = torch.zeros_like(p)
    calls = []
    real = node_graph.hooke_rows_graph
    monkeypatch.setattr(node_graph, "hooke_rows_graph", lambda g, *window: calls.append(1) or real(g, *window))
    ap, dot = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF, node_stiffness=stiffness)
    assert calls, "ops.system_matvec did not take the node layout"
    pad = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, None, stiffness, variants=PADDED)
    assert len(calls) == 1
    assert torch.equal(ap, pad[0]) and torch.equal(dot, pad[1])
    # the benchmarks' switch: the variants of TENSORMASS_HOOKE_MATVEC=padded, passed down explicitly
    padded = KernelVariants.from_env({"TENSORMASS_HOOKE_MATVEC": "padded"})
    assert padded == PADDED
    ap2, dot2 = ops.system_matvec([group], u, p, mass, free, C_MASS, C_STIFF, node_stiffness=stiffness,
                                  variants=padded)
    assert len(calls) == 1 and torch.equal(ap, ap2) and torch.equal(dot, dot2)
    with pytest.raises(ValueError, match="unknown layout 'ell'"):
        KernelVariants(hooke_matvec="ell")


def test_gradients_take_the_differentiable_path():
    group, p, mass, _, _ = make_case(7, "tet", torch.float64)
    u = torch.zeros_like(p)
    with torch.no_grad():
        plain_ap, plain_dot = ops.system_matvec([group], u, p, mass, None, C_MASS, C_STIFF)
    p = p.clone().requires_grad_(True)
    ap, dot = ops.system_matvec([group], u, p, mass, None, C_MASS, C_STIFF)
    assert dot.requires_grad
    (g,) = torch.autograd.grad(dot.sum(), p)
    assert rel(g, 2 * plain_ap) < 1e-12  # d(p . A p)/dp = 2 A p, A symmetric
    assert rel(ap.detach(), plain_ap) < 1e-14 and rel(dot.detach(), plain_dot) < 1e-14


# --------------------------------------------------------------------- the solver


def run_beam(dtype, contact=False, **variants):
    """4 steps of a hooke beam (tensor form) with the kernel variants ``KernelVariants(**variants)``."""
    mesh = tm.beam_mesh(4, 1, 1, size=(0.4, 0.1, 0.1), dtype=dtype)
    mat = tm.Material(young=2e4, poisson=0.3, density=1000.0, model="hooke")
    fixed = mesh.vertices[:, 0] < 1e-9
    planes = [tm.Plane((0.0, 0.0, 1.0), 0.02, 1e4)] if contact else []
    sim = tm.Simulator([tm.Body(mesh, mat, fixed=fixed)], dt=0.01, gravity=(0, 0, -9.81), rayleigh_mass=0.2,
                       rayleigh_stiffness=0.02, cg_tol=1e-10 if dtype == torch.float64 else 1e-5, cg_max_iter=500,
                       form="tensor", planes=planes)
    with_variants(sim, **variants).step(4)
    return sim.x.clone(), sim.v.clone()


@pytest.mark.parametrize("contact", [False, True], ids=["free-fall", "contact"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
def test_simulator_node_layout_equals_padded_bitwise(monkeypatch, dtype, contact):
    # the matvecs are compared here: the step's right-hand side is composed in both runs (its one
    # op, hooke_node_step_rhs, only serves the node layout; tests/ops/test_step_ops.py checks it)
    no_rhs_op = lambda group, inputs=(), variants=DEFAULT: False
    monkeypatch.setattr(node_graph, "step_rhs_serves", no_rhs_op)
    monkeypatch.setattr(solve, "step_rhs_serves", no_rhs_op)  # nor the solve's (hooke_node_steps, GPU)
    calls = []
    real = node_graph.hooke_rows_graph
    monkeypatch.setattr(node_graph, "hooke_rows_graph", lambda g, *window: calls.append(1) or real(g, *window))
    x_rows, v_rows = run_beam(dtype, contact)
    assert calls, "the solver did not use the node layout"
    # with the graph's rows in node order every sum is taken in the padded path's order; rows
    # sorted by slot count (the default) change only the order of the CG's p . Ap sums
    x, v = run_beam(dtype, contact, node_graph_window=0)
    # the padded variant's products never run over the node graph (the elastic forces may: they
    # are not the CG product, and both layouts give them bitwise)
    padded_graphs = []
    real_graph_of = node_graph.node_graph_of

    def graph_of(group, variants, *args, **kwargs):
        graph = real_graph_of(group, variants, *args, **kwargs)
        if variants.hooke_matvec == "padded":
            padded_graphs.append(graph)
        return graph

    monkeypatch.setattr(node_graph, "node_graph_of", graph_of)
    monkeypatch.setattr(native, "node_graph_of", graph_of)
    monkeypatch.setattr(solve, "node_graph_of", graph_of)
    x_p, v_p = run_beam(dtype, contact, hooke_matvec="padded", node_graph_window=0)
    assert padded_graphs and all(graph is None for graph in padded_graphs)
    assert torch.equal(x, x_p) and torch.equal(v, v_p)
    # both solved to the CG tolerance (1e-10 in float64; with the stiff penalty, k = 1e4 on a light
    # beam, the velocities differ by ~1e-10 there)
    t = (1e-8 if contact else 1e-10) if dtype == torch.float64 else 1e-4
    assert rel(x_rows, x) < t and rel(v_rows, v) < t
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    x_t, v_t = run_beam(dtype, contact, hooke_matvec="padded", node_graph_window=0)
    # the torch path is other arithmetic solved to the CG tolerance (with the penalty: ~2e-10)
    assert rel(x, x_t) < t and rel(v, v_t) < t


# --------------------------------------------------------------------- checks, autograd, opcheck


@pytest.mark.parametrize("index_dtype", INDEX_DTYPES, ids=["i64", "i32"])
@pytest.mark.parametrize("seed", [0, 1])
def test_rebuilt_rows_equal_their_reference_on_a_beam_with_removed_elements(seed, index_dtype):
    """``node_graph_rebuild_hooke_rows`` on a beam of 270 tetrahedra with a fifth of them removed,
    a third of its rows touched, in windowed row order: neighbours (first met over the alive
    elements in list order), blocks and counts as its reference's; rows with more neighbours than
    ``max_slots`` are left as they were and set the status, the others written."""
    from tensormass_torch.ops.topology import incidence_table

    gen = torch.Generator().manual_seed(seed)
    mesh = tm.beam_mesh(3, 3, 3, dtype=torch.float64)
    rest = mesh.vertices + 0.02 * torch.randn(mesh.vertices.shape, generator=gen, dtype=torch.float64)
    elements = mesh.elements.to(index_dtype).contiguous()
    num_nodes, num_elements = rest.shape[0], elements.shape[0]
    node_slots = incidence_table(elements.reshape(-1).long(), torch.arange(
        num_elements, dtype=index_dtype).repeat_interleave(4), num_nodes)
    alive = torch.rand(num_elements, generator=gen) > 0.2
    touched = (torch.rand(num_nodes, generator=gen) < 0.35).to(torch.uint8)
    row_of = torch.randperm(num_nodes, generator=gen).to(index_dtype)
    a, b, c, d = (rest[elements[:, k].long()] for k in range(4))
    volume = torch.linalg.det(torch.stack([b - a, c - a, d - a], 1)).abs() / 6
    pair_k = node_graph.hooke_pair_tensors(rest, elements, volume, torch.full_like(volume, 3.0),
                                           torch.full_like(volume, 0.3))
    slots = 30
    fits = None  # the rows whose rebuilt neighbours fit max_slots
    for max_slots in (slots, 9):
        outputs = []
        for rebuild in (library.op_or_reference("node_graph_rebuild_hooke_rows", torch.device("cpu")),
                        node_graph._ref_node_graph_rebuild_hooke_rows):
            neighbor = torch.full((slots, num_nodes), -7, dtype=index_dtype)
            node_k = torch.full((slots, num_nodes, 3, 3), 0.5, dtype=torch.float64)
            incidences = torch.full((num_nodes,), 3, dtype=index_dtype)
            status = torch.zeros(1, dtype=torch.int32)
            firsts = torch.full(node_slots.shape, 5, dtype=torch.int32)  # (scratch)
            rebuild(pair_k, elements, node_slots, alive, touched, row_of, max_slots, neighbor, node_k, incidences,
                    status, firsts)
            outputs.append((neighbor, node_k, incidences, status))
        (neighbor, node_k, incidences, status), want = outputs
        assert torch.equal(incidences, want[2]) and torch.equal(status, want[3])
        assert bool((incidences[row_of[touched.bool()].long()] != 3).any())  # rows were written
        if fits is None:
            counts = incidences.clone()
        fits = (counts <= max_slots) | ~touched.bool()[torch.argsort(row_of.long())]  # by row
        used = torch.arange(slots)[:, None] < incidences.long()[None, :]  # the slots the rows use
        assert torch.equal(neighbor[used], want[0][used])
        used &= fits[None, :]  # (a row that does not fit may have its old slots' blocks written: unused)
        torch.testing.assert_close(node_k[used], want[1][used], rtol=1e-14, atol=1e-14)
        assert int(status) == (0 if max_slots == slots else 1) and not bool(fits.all()) == bool(status)


def test_input_checks():
    group, p, mass, free, stiffness = make_case(8, "tet", torch.float64)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    inc = group.plan.incidences.to(neighbor.dtype)
    H = torch.ops.tensormass.hooke_node_system

    def call(**kw):
        args = dict(p=p, neighbor=neighbor, node_k=node_k, incidences=inc, row_node=None, mass=mass, free=free,
                    c_mass=1.0, c_stiff=1.0, node_stiffness=None)
        args.update(kw)
        return H(*args.values())

    cases = [
        (dict(node_k=node_k[:, :, :2]), "node_k has shape"),
        (dict(node_k=node_k[:-1]), "node_k has shape"),
        (dict(node_k=node_k.float()), "node_k is Float but p is Double"),
        (dict(node_k=node_k.transpose(2, 3)), "node_k must be contiguous"),
        (dict(neighbor=neighbor.double()), "neighbor must be int64 or int32"),
        (dict(neighbor=neighbor[:, :-1]), "neighbor has shape"),
        (dict(neighbor=neighbor[0]), r"neighbor must be \[N_n, V\]"),
        (dict(incidences=inc.long() if inc.dtype == torch.int32 else inc.int()), "incidences is"),
        (dict(row_node=torch.arange(p.shape[0] - 1, dtype=inc.dtype)), "row_node has shape"),
        (dict(row_node=torch.arange(p.shape[0], dtype=torch.int64 if inc.dtype == torch.int32 else torch.int32)),
         "row_node is"),
        (dict(incidences=inc[:-1]), "incidences has shape"),
        (dict(mass=mass[:-1]), "mass has shape"),
        (dict(free=free.float()), "free is Float but p is Double"),
        (dict(node_stiffness=stiffness[:, :2]), "node_stiffness has shape"),
        (dict(p=p[:, :2].contiguous()), "node_k has shape"),
        (dict(p=p.reshape(-1)), r"p must be \[V, d\]"),
        (dict(p=p.int()), "p must be float32 or float64"),
        (dict(p=torch.zeros(p.shape[0], 4, dtype=p.dtype)), "unsupported dimension 4"),
    ]
    for kw, message in cases:
        with pytest.raises(RuntimeError, match=message):
            call(**kw)


def test_op_has_no_gradient():
    group, p, mass, free, _ = make_case(9, "tri2d", torch.float64)
    p = p.clone().requires_grad_(True)
    ap, _ = node_matvec(group, p, mass, free, None, torch.int64)
    with pytest.raises(RuntimeError, match="not differentiable"):
        ap.sum().backward()


def test_opcheck():
    group, p, mass, free, stiffness = make_case(10, "tri3d", torch.float64)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    inc = group.plan.incidences.to(neighbor.dtype)
    for fr in (None, free):
        for k in (None, stiffness):
            torch.library.opcheck(torch.ops.tensormass.hooke_node_system.default,
                                  (p, neighbor, node_k, inc, None, mass, fr, C_MASS, C_STIFF, k),
                                  test_utils=("test_schema", "test_faketensor", "test_aot_dispatch_static"))


# --------------------------------------------------------------------- CUDA

DEVICE = os.environ.get("TENSORMASS_GPU_TEST_DEVICE", "cuda")


def _device_extension() -> bool:
    if native is None or (DEVICE == "cuda" and not torch.cuda.is_available()):
        return False
    return DEVICE != "cuda" or bool(importlib.import_module("tensormass_torch._C").has_cuda())


needs_device = pytest.mark.skipif(not _device_extension(), reason="needs a CUDA device and the extension built "
                                  "with CUDA (TENSORMASS_GPU_TEST_DEVICE=cpu: a dry run on the CPU)")
needs_cuda = pytest.mark.skipif(DEVICE != "cuda", reason="dry run on the CPU: no graphs")


def sync():
    if DEVICE == "cuda":
        torch.cuda.synchronize()


@needs_device
@pytest.mark.parametrize("with_free,with_node_k", EPILOGUES)
@pytest.mark.parametrize("index_dtype", INDEX_DTYPES, ids=["i64", "i32"])
@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind", KINDS)
def test_cuda_node_equals_padded_and_cpu(kind, dtype, index_dtype, with_free, with_node_k):
    group, p, mass, free, stiffness = make_case(11, kind, dtype, device=DEVICE)
    free = free if with_free else None
    stiffness = stiffness if with_node_k else None
    ap, dot = node_matvec(group, p, mass, free, stiffness, index_dtype)
    pad_ap, pad_dot = padded_matvec(group, p, mass, free, stiffness, index_dtype)
    sync()
    assert ap.device.type == DEVICE
    assert torch.equal(ap, pad_ap) and torch.equal(dot, pad_dot)  # the same terms in the same order
    ap2, dot2 = node_matvec(group, p, mass, free, stiffness, index_dtype)
    assert torch.equal(ap, ap2) and torch.equal(dot, dot2)  # run to run
    cpu_group, *cpu_rest = make_case(11, kind, dtype)
    cpu_free = cpu_rest[2] if with_free else None
    cpu_k = cpu_rest[3] if with_node_k else None
    cpu_ap, cpu_dot = node_matvec(cpu_group, cpu_rest[0], cpu_rest[1], cpu_free, cpu_k, index_dtype)
    assert rel(ap.cpu(), cpu_ap) < tol(dtype) and rel(dot.cpu(), cpu_dot) < tol(dtype)


@needs_device
def test_cuda_larger_beam_bitwise_and_deterministic():
    """A beam of a few thousand nodes (many blocks), float32 as on the GPU."""
    mesh = tm.beam_mesh(30, 8, 8, size=(3.0, 0.8, 0.8), dtype=torch.float32)
    model = TensorMass(mesh, Material(young=1e5, poisson=0.3, density=1000.0, model="hooke"),
                       form="tensor").to(DEVICE)
    group = model.groups[0]
    g = torch.Generator().manual_seed(3)
    p = torch.randn(mesh.vertices.shape, generator=g).to(DEVICE)
    mass = (torch.rand(p.shape[0], generator=g) + 0.5).to(DEVICE)
    free = (torch.rand(p.shape[0], generator=g) > 0.1).float().to(DEVICE)
    u = torch.zeros_like(p)
    node = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, variants=NODE)
    pad = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, variants=PADDED)
    again = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, variants=NODE)
    sync()
    for a, b, c in zip(node, pad, again):
        assert torch.equal(a, b) and torch.equal(a, c)


@needs_device
@needs_cuda
def test_cuda_graph_replays_the_node_matvec():
    group, p, mass, free, stiffness = make_case(12, "tet", torch.float32, device=DEVICE)
    u = torch.zeros_like(p)
    eager = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, None, stiffness)  # builds the graph
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, None, stiffness)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        captured = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, None, stiffness)
    graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(captured[0], eager[0]) and torch.equal(captured[1], eager[1])
    p.mul_(2.0)
    graph.replay()
    torch.cuda.synchronize()
    twice = native.system_matvec(group, u, p, mass, free, C_MASS, C_STIFF, None, stiffness)
    assert torch.equal(captured[0], twice[0])


# --------------------------------------------------------------------- the benchmark script


def test_benchmark_script_quick(tmp_path, capsys):
    sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks" / "studies"))
    import node_system_bench

    rows = node_system_bench.main(["--quick", "--device", "cpu", "--repeat", "1", "--warmup", "1",
                                   "--out", str(tmp_path)])
    assert {r["layout"] for r in rows} == {"padded", "node"} and len(rows) == 6
    assert all(r["bitwise"] == "yes" and r["us"] > 0 for r in rows)
    assert "| sofa_beam |" in (tmp_path / "node_system_bench.md").read_text()


@pytest.mark.parametrize("kind", KINDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_forces_through_the_node_graph_equal_padded_forces(kind, dtype):
    """native.forces of the hooke tensor form runs the node op (c_M = 0, c_K = -1 gives K u):
    bitwise the padded kernel 1 + gather; with a gradient wanted it keeps the differentiable op."""
    group, u, *_ = make_case(11, kind, dtype)
    real = torch.ops.tensormass.hooke_node_system
    index, force_index, incidences = library.plan_indices(group.plan)
    padded = torch.ops.tensormass.tensor_hooke_forces(u, index, force_index, group.plan.num_slots, incidences,
                                                      group.edge_k.contiguous())
    got = native.forces(group, u, variants=NODE)
    assert torch.equal(got, padded)
    neighbor, node_k = node_graph.hooke_node_graph(group)
    no_mass = torch.zeros(u.shape[0], dtype=dtype)
    assert torch.equal(real(u, neighbor, node_k, incidences, None, no_mass, None, 0.0, -1.0, None)[0], got)
    u_grad = u.clone().requires_grad_(True)
    f = native.forces(group, u_grad, variants=NODE)
    assert f.requires_grad and torch.equal(f.detach(), padded)
