"""The differential of a stress-form group on the node graph (node_graph.tangent_node_k,
op stress_tangent_node_k): the element blocks H_ab = d f_a / d u_b summed onto edges once per
linearisation, so that the CG products of stvk and corotational run over the node graph
(hooke_node_system / hooke_node_cg / hooke_node_solve) instead of an element pass an iteration.

Oracles: the op's pure-torch reference (library.REGISTRY["stress_tangent_node_k"].reference, from the reference
element dforces along unit displacements), the element path's product (system_matvec without
node_k: the element dforces, themselves checked against autograd elsewhere) and autograd's
Jacobian-vector product of the forces; implicit steps with and without it agree to rounding."""
from __future__ import annotations

import pytest
import torch
from conftest import with_variants

import tensormass_torch as tm
from tensormass_torch import ops
from tensormass_torch.ops import library, native, node_graph, stress

pytestmark = pytest.mark.skipif(not library.ensure_registered()
                                or not hasattr(torch.ops.tensormass, "stress_tangent_node_k"),
                                reason="needs the extension with stress_tangent_node_k")
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
# (kind, model, rotation): tetrahedra, membranes (triangles in 3-D), planar triangles
CASES = [("tet", "stvk", None), ("tet", "stvk_definite", None), ("tet", "corotational", "qr"),
         ("tet", "corotational", "polar"), ("tri3d", "stvk", None), ("tri3d", "corotational", "polar"),
         ("tri2d", "stvk", None), ("tri2d", "corotational", "polar")]
IDS = ["-".join(x for x in case if x) for case in CASES]


def make_group(kind, model, rotation, dtype, device, seed=0):
    """(group, u): a small stress-form group and a displacement of ~5% of its size."""
    if kind == "tet":
        mesh = tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.2), dtype=dtype, device=device)
    else:
        mesh = tm.beam_tri_mesh(3, 2, size=(0.3, 0.2), dim=3 if kind == "tri3d" else 2, dtype=dtype, device=device)
    extra = {"rotation": rotation} if rotation else {"tangent": "exact"}
    if model == "stvk_definite":
        model, extra = "stvk", {"tangent": "definite"}
    material = tm.Material(young=1e4, poisson=0.3, density=1000.0, model=model, **extra)
    group = tm.TensorMass(mesh, material, form="stress").groups[0]
    gen = torch.Generator().manual_seed(seed)
    u = (0.05 * torch.randn(mesh.vertices.shape, generator=gen, dtype=dtype)).to(device)
    if kind == "tet":  # compress one end: stvk's stress gets negative eigenvalues (definite differs)
        u[:, 0] -= 0.2 * mesh.vertices[:, 0]
    return group, u


def reference(group, u, state):
    graph, _, incidences, _, slot_edge = node_graph.tangent_graph(group)
    index = library.plan_indices(group.plan)[0]
    m, vol, lam, mu, proj, model, _, rotations = stress.stress_args(group, u, state)
    op_reference = library.REGISTRY["stress_tangent_node_k"].reference
    return op_reference(u, index, m, vol, lam, mu, proj, model, rotations, graph.element_edges, graph.edge_slots,
                        graph.num_edge_slots, graph.edge_counts, slot_edge, incidences)


def used_slots(group):
    graph, _, incidences, _, _ = node_graph.tangent_graph(group)
    return torch.arange(graph.plan.num_slots, device=incidences.device)[:, None] < incidences[None, :].long()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("kind,model,rotation", CASES, ids=IDS)
def test_the_op_matches_its_reference(kind, model, rotation, dtype, device):
    group, u = make_group(kind, model, rotation, dtype, device)
    state = ops.linearize(group, u)
    got = node_graph.tangent_node_k(group, u, state)
    want = reference(group, u, state)
    used = used_slots(group)
    scale = float(want[used].abs().max())
    tol = 1e-13 if dtype == torch.float64 else 1e-5
    assert float((got - want)[used].abs().max()) <= tol * scale


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kind,model,rotation", CASES, ids=IDS)
def test_the_node_graph_product_is_the_element_product(kind, model, rotation, device):
    """system_matvec over the node graph (node_k given) against element by element, float64,
    with a free mask and node stiffnesses (contact) in the epilogue."""
    dtype = torch.float64
    group, u = make_group(kind, model, rotation, dtype, device)
    state = ops.linearize(group, u)
    gen = torch.Generator().manual_seed(1)
    p = torch.randn(u.shape, generator=gen, dtype=dtype).to(device)
    mass = torch.rand(u.shape[0], generator=gen, dtype=dtype).to(device) + 0.5
    free = (torch.rand(u.shape[0], generator=gen) > 0.2).to(dtype).to(device)
    d = u.shape[1]
    node_stiffness = torch.randn(u.shape[0], d, d, generator=gen, dtype=dtype).to(device)
    node_k = node_graph.tangent_node_k(group, u, state)
    for stiffness in (None, node_stiffness):
        want = native.system_matvec(group, u, p, mass, free, 1.3, 0.7, state, stiffness)
        got = native.system_matvec(group, u, p, mass, free, 1.3, 0.7, state, stiffness, node_k=node_k)
        for g, w in zip(got, want):
            assert float((g - w).abs().max()) <= 1e-12 * float(w.abs().max())


@pytest.mark.parametrize("kind", ["tet", "tri3d"])
def test_the_product_is_the_jacobian_of_the_forces(kind):
    """-c_stiff (dF/du) p from autograd's jvp of the forces (stvk: the exact tangent)."""
    group, u = make_group(kind, "stvk", None, torch.float64, "cpu")
    p = torch.randn(u.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    _, jvp = torch.autograd.functional.jvp(lambda v: ops.forces(group, v), u, p)  # reverse mode twice
    node_k = node_graph.tangent_node_k(group, u, None)
    zero_mass = torch.zeros(u.shape[0], dtype=torch.float64)
    ap, _ = native.system_matvec(group, u, p, zero_mass, None, 0.0, -1.0, None, None, node_k=node_k)
    assert float((ap - jvp).abs().max()) <= 1e-10 * float(jvp.abs().max())


def simulate(model, node_tangent, device, steps=4, **material):
    mesh = tm.beam_mesh(6, 2, 2, size=(0.6, 0.1, 0.1), dtype=torch.float64, device=device)
    body = tm.Body(mesh, tm.Material(young=2e4, poisson=0.35, density=1000.0, model=model, **material),
                   fixed=mesh.vertices[:, 0] < 1e-9)
    # the plane's penalty acts on the bottom nodes from the start: contact in the products and rhs
    sim = tm.Simulator([body], dt=0.02, gravity=(0, 0, -9.81), form="stress", cg_tol=1e-10, cg_max_iter=400,
                       planes=[tm.Plane((0.0, 0.0, 1.0), 0.001, 1e4)], device=device, dtype=torch.float64)
    with_variants(sim, node_tangent=node_tangent).step(steps)
    matvec = next(iter(sim.system._matvecs.values()))
    return sim, matvec


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("model,material", [("stvk", {}), ("corotational", {"rotation": "qr"}),
                                            ("corotational", {"rotation": "polar"})])
def test_steps_with_the_tangent_on_the_node_graph_match_the_element_path(model, material, device):
    with_graph, matvec = simulate(model, True, device, **material)
    assert matvec.tangents is not None, "the steps did not take the node graph"
    element, matvec = simulate(model, False, device, **material)
    assert matvec.tangents is None
    scale = float((element.x - element.system.model.rest).abs().max())
    assert scale > 1e-4  # the beam sags
    assert float((with_graph.x - element.x).abs().max()) <= 1e-8 * scale
    assert float((with_graph.v - element.v).abs().max()) <= 1e-8 * float(element.v.abs().max())


def test_no_tangent_where_a_gradient_is_wanted_or_for_hooke():
    group, u = make_group("tet", "stvk", None, torch.float64, "cpu")
    assert ops.node_tangent(group, u) is not None
    assert ops.node_tangent(group, u.clone().requires_grad_()) is None
    hooke = tm.TensorMass(tm.beam_mesh(2, 1, 1, dtype=torch.float64),
                          tm.Material(young=1e4, poisson=0.3, density=1e3, model="hooke"), form="stress").groups[0]
    assert ops.node_tangent(hooke, torch.zeros(hooke.num_nodes, 3, dtype=torch.float64)) is None


def test_the_tangent_is_written_into_the_buffer_given():
    group, u = make_group("tet", "stvk", None, torch.float64, "cpu")
    first = node_graph.tangent_node_k(group, u, None)
    again = node_graph.tangent_node_k(group, 2 * u, None, out=first)
    assert again is first
    used = used_slots(group)
    want = reference(group, 2 * u, None)[used]
    assert float((again[used] - want).abs().max()) < 1e-13 * float(want.abs().max())


@pytest.mark.parametrize("device", DEVICES)
def test_bad_inputs_are_rejected_with_nothing_changed(device):
    group, u = make_group("tet", "corotational", "qr", torch.float32, device)
    graph, _, incidences, _, slot_edge = node_graph.tangent_graph(group)
    plan = graph.plan
    index = library.plan_indices(group.plan)[0]
    m, vol, lam, mu, proj, model, _, rotations = stress.stress_args(group, u, None)
    node_k = torch.full((plan.num_slots, u.shape[0], 3, 3), 7.0, device=device)
    work = torch.zeros(graph.num_edge_slots, graph.edges.shape[0], 12, device=device)
    args = dict(u=u, elements=index, shape_vectors=m, measure=vol, lam=lam, mu=mu, projector=proj, model=model,
                rotations=rotations, element_edges=graph.element_edges, edge_slots=graph.edge_slots,
                num_edge_slots=graph.num_edge_slots, edge_counts=graph.edge_counts, slot_edge=slot_edge,
                incidences=incidences, node_k=node_k, edge_partial=work)
    cases = [(dict(rotations=None), "corotational tangent needs the rotations"),
             (dict(node_k=node_k[:, :-1]), "node_k has shape"),
             (dict(edge_partial=work[:-1]), "edge_partial has shape"),
             (dict(element_edges=graph.element_edges[:, :3].contiguous()), "element_edges has shape"),
             (dict(slot_edge=slot_edge.long()), "slot_edge is Long"),
             (dict(incidences=incidences[:-1]), "incidences has shape"),
             (dict(num_edge_slots=-1), "must be >= 0")]
    for change, message in cases:
        with pytest.raises(RuntimeError, match=message):
            torch.ops.tensormass.stress_tangent_node_k(**{**args, **change})
        assert bool((node_k == 7.0).all())
