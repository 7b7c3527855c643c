"""The two ops around an implicit Euler step's CG: hooke_node_step_rhs (the right-hand side, u and
the contact stiffness in one pass) against the composition it replaces (SystemMatvec.load +
forces_along + damping, float64), and euler_update (new state, per-object |v|^2, the summary and
its ring row) against the torch expressions of StepGraphs' fallback."""
from __future__ import annotations

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch import ops
from tensormass_torch.ops import cg as cg_ops
from tensormass_torch.ops.segments import ChunkPlan, Segments
from tensormass_torch.physics.contact import Planes
from tensormass_torch.solver.implicit_euler import DynamicsSystem

pytestmark = pytest.mark.skipif(cg_ops.native_ops_for(torch.zeros(1)) is None
                                or not hasattr(torch.ops.tensormass, "hooke_node_step_rhs"),
                                reason="needs the compiled extension")


def _system(dtype=torch.float64, planes=True, dim=3, fixed=True):
    if dim == 3:
        mesh = tm.beam_mesh(5, 2, 2, size=(0.5, 0.1, 0.1), dtype=dtype)
        gravity = [0.0, 0.0, -9.81]
    else:
        mesh = tm.beam_tri_mesh(6, 3, size=(0.6, 0.2), dtype=dtype)
        gravity = [0.0, -9.81]
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, model="hooke"), form="tensor")
    mass = model.lumped_mass()
    external = mass.unsqueeze(-1) * torch.tensor(gravity, dtype=dtype)
    plane_set = (Planes([tm.Plane((0.0, 0.0, 1.0), 0.03, 1e4), tm.Plane((1.0, 0.0, 1.0), 0.05, 3e3)], dtype, "cpu")
                 if planes else None)
    constrained = model.rest[:, 0] < 1e-9 if fixed else torch.zeros(model.num_nodes, dtype=torch.bool)
    system = DynamicsSystem(model, mass, external, Segments.from_lengths([model.num_nodes], "cpu"), constrained,
                            plane_set)
    gen = torch.Generator().manual_seed(11)
    x = model.rest + 0.04 * torch.randn(model.rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    v = torch.randn(model.rest.shape, generator=gen, dtype=torch.float64).to(dtype)
    return system, x, v


def _composed_rhs(system, x, v, h, r_m, r_k):
    """The reference: the composition load_step runs where the op does not serve."""
    matvec = system.system_matvec(1.0, 1e-4).load(x)
    rhs = matvec.forces_along((h + r_k) * v)
    if r_m:
        rhs = rhs - r_m * system.mass * v
    return h * rhs, matvec


@pytest.mark.parametrize("planes", [True, False])
@pytest.mark.parametrize("r_m", [0.0, 0.3])
def test_step_rhs_equals_composition(planes, r_m):
    system, x, v = _system(planes=planes)
    h, r_k = 0.01, 0.02
    expected, reference = _composed_rhs(system, x, v, h, r_m, r_k)
    fused = system.system_matvec(1.0, 2e-4)
    got = fused.load_step(x, v, h, r_m, h + r_k)  # (w_coef: backward Euler's h + r_K)
    assert got is fused._rhs  # the one op ran (its buffer), not the composition
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10 * float(expected.abs().max()))
    torch.testing.assert_close(fused.u, x - system.model.rest, rtol=0, atol=0)
    if planes:
        assert float(reference.node_stiffness.abs().sum()) > 0  # some nodes are in contact
        torch.testing.assert_close(fused.node_stiffness, reference.node_stiffness, rtol=1e-12, atol=1e-9)
    # what the CG reads afterwards is the composition's
    p = torch.randn_like(x)
    torch.testing.assert_close(fused(p)[0], reference.__class__(system, 1.0, 2e-4).load(x)(p)[0], rtol=1e-10,
                               atol=1e-9)


def test_step_rhs_planar_triangles():
    system, x, v = _system(planes=False, dim=2)
    expected, _ = _composed_rhs(system, x, v, 0.02, 0.1, 0.0)
    fused = system.system_matvec(1.0, 4e-4)
    got = fused.load_step(x, v, 0.02, 0.1, 0.02)
    assert got is fused._rhs
    torch.testing.assert_close(got, expected, rtol=1e-10, atol=1e-10 * float(expected.abs().max()))


def test_step_rhs_float32_close_to_float64():
    system64, x64, v64 = _system()
    expected, _ = _composed_rhs(system64, x64, v64, 0.01, 0.1, 0.01)
    system32, _, _ = _system(dtype=torch.float32)
    got = system32.system_matvec(1.0, 1e-4).load_step(x64.float(), v64.float(), 0.01, 0.1, 0.02)
    scale = float(expected.abs().max())
    assert float((got.double() - expected).abs().max()) < 1e-5 * scale


def _op_args(system, x, v, planes=True):
    model = system.model
    (group,) = model.groups
    from tensormass_torch.ops import node_graph

    neighbor, node_k, incidences, rows = node_graph.hooke_rows_graph(group)
    p = system.planes
    u, rhs = torch.zeros_like(x), torch.zeros_like(x)
    stiffness = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    plane_args = (p.normals, p.offsets, p.stiffness) if planes else (None, None, None)
    return [x, v, model.rest, neighbor, node_k, incidences, rows, model.lumped_mass(), system.external, *plane_args,
            0.01, 0.02, 0.1, u, rhs, stiffness if planes else None]


@pytest.mark.parametrize("bad,message", [
    (lambda a: a.__setitem__(1, a[1][:-1]), "v has shape"),
    (lambda a: a.__setitem__(8, a[8].float()), "external is"),
    (lambda a: a.__setitem__(15, a[15].t()), "u"),
    (lambda a: a.__setitem__(17, None), "node_stiffness"),
    (lambda a: a.__setitem__(10, a[10][:1]), "plane_offsets has shape"),
    (lambda a: a.__setitem__(4, a[4][:, :-1]), "node_k has shape"),
    (lambda a: a.__setitem__(6, a[6][:-1]), "row_node has shape"),
])
def test_step_rhs_bad_input_raises_and_writes_nothing(bad, message):
    system, x, v = _system()
    args = _op_args(system, x, v)
    bad(args)
    outputs = [t.clone() if isinstance(t, torch.Tensor) else t for t in args[15:]]
    with pytest.raises(RuntimeError, match=message):
        torch.ops.tensormass.hooke_node_step_rhs(*args)
    for before, after in zip(outputs, args[15:]):
        if isinstance(before, torch.Tensor) and before.shape == after.shape:
            assert torch.equal(before, after)


def test_step_rhs_planes_need_3d():
    system, x, v = _system(planes=False, dim=2)
    args = _op_args(system, x, v, planes=False)
    planes = Planes([tm.Plane((0.0, 0.0, 1.0), 0.0, 1e4)], torch.float64, "cpu")
    args[9:12] = [planes.normals, planes.offsets, planes.stiffness]
    args[17] = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype)
    with pytest.raises(RuntimeError, match="contact planes need 3-D"):
        torch.ops.tensormass.hooke_node_step_rhs(*args)


def test_step_rhs_not_served_for_other_models():
    mesh = tm.beam_mesh(3, 1, 1, dtype=torch.float64)
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, model="stvk"), form="tensor")
    x = model.rest.clone()
    out = torch.zeros_like(x)
    assert not ops.step_rhs(model.groups, x, x, model.rest, model.lumped_mass(), x, None, 0.01, 0.01, 0.0, out, out,
                            None)


# ------------------------------------------------------------------ euler_update


def _update_case(dtype=torch.float64, imposed=True, lengths=(40, 7, 300), chunk_nodes=16):
    gen = torch.Generator().manual_seed(3)
    segments = Segments.from_lengths(list(lengths), "cpu")
    plan = ChunkPlan.from_segments(segments, chunk_nodes)
    v_count, b = sum(lengths), len(lengths)
    rand = lambda *shape: torch.randn(*shape, generator=gen, dtype=torch.float64).to(dtype)  # noqa: E731
    case = dict(x=rand(v_count, 3), v=rand(v_count, 3), dv=rand(v_count, 3),
                dv_imposed=rand(v_count, 3) if imposed else None, plan=plan,
                status=torch.tensor([1, 4, 2], dtype=torch.int32)[:b],
                iterations=torch.tensor([7, 10, 3], dtype=torch.int32)[:b], rr=rand(b).abs(), rhs_sq=rand(b).abs())
    return case


def _run_update(c, h, ring=None, ring_pos=None, carry=False):
    b = c["plan"].segments.num_objects
    x, v = c["x"].clone(), c["v"].clone()
    x_new, v_new = torch.zeros_like(x), torch.zeros_like(x)
    norms = torch.zeros(b, dtype=x.dtype)
    summary = torch.zeros(5, b, dtype=torch.float64)
    scratch = torch.zeros(c["plan"].num_chunks, dtype=torch.float64)
    counter = torch.zeros(b + 1, dtype=torch.int32)
    torch.ops.tensormass.euler_update(x, v, c["dv"], c["dv_imposed"], h, x_new, v_new, *c["plan"].tensors(),
                                      c["status"], c["iterations"], c["rr"], c["rhs_sq"], norms, summary, scratch,
                                      counter, ring, ring_pos, carry)
    return x, v, x_new, v_new, norms, summary


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("imposed", [True, False])
def test_euler_update_equals_torch(dtype, imposed):
    c = _update_case(dtype, imposed)
    h = 0.04
    x, v, x_new, v_new, norms, summary = _run_update(c, h)
    expected_v = c["v"] + c["dv"]
    if imposed:
        expected_v = expected_v + c["dv_imposed"]
    assert torch.equal(v_new, expected_v)
    torch.testing.assert_close(x_new, torch.add(c["x"], expected_v, alpha=h), rtol=0,
                               atol=4 * torch.finfo(dtype).eps * float(x_new.abs().max()))
    # norms as cg_dot sums them (bitwise)
    plan = c["plan"]
    dots = torch.zeros_like(norms)
    torch.ops.tensormass.cg_dot(v_new, v_new, *plan.tensors(), dots, torch.zeros(plan.num_chunks, dtype=torch.float64),
                                torch.zeros(plan.segments.num_objects, dtype=torch.int32))
    assert torch.equal(norms, dots)
    expected_summary = torch.stack((c["status"].double(), c["iterations"].double(), c["rr"].double(),
                                    c["rhs_sq"].double(), norms.double()))
    assert torch.equal(summary, expected_summary)
    assert torch.equal(x, c["x"]) and torch.equal(v, c["v"])  # not carried


def test_euler_update_ring_and_carry():
    c = _update_case()
    b = c["plan"].segments.num_objects
    ring = torch.full((4, 5, b), -1.0, dtype=torch.float64)
    ring_pos = torch.tensor([2])
    x, v, x_new, v_new, _, summary = _run_update(c, 0.01, ring, ring_pos, carry=True)
    assert int(ring_pos) == 3
    assert torch.equal(ring[2], summary)
    assert bool((ring[[0, 1, 3]] == -1.0).all())
    assert torch.equal(x, x_new) and torch.equal(v, v_new)


def test_euler_update_bad_input_raises():
    c = _update_case()
    plan = c["plan"]
    b = plan.segments.num_objects
    x = c["x"].clone()
    args = [x, c["v"].clone(), c["dv"], None, 0.01, torch.zeros_like(x), torch.zeros_like(x), *plan.tensors(),
            c["status"], c["iterations"], c["rr"], c["rhs_sq"], torch.zeros(b, dtype=x.dtype),
            torch.zeros(5, b, dtype=torch.float64), torch.zeros(plan.num_chunks, dtype=torch.float64),
            torch.zeros(b, dtype=torch.int32), None, None, False]
    with pytest.raises(RuntimeError, match="counter has shape"):
        torch.ops.tensormass.euler_update(*args)
    args[17] = torch.zeros(b + 1, dtype=torch.int32)
    args[18] = torch.zeros(2, 5, b, dtype=torch.float64)
    with pytest.raises(RuntimeError, match="ring and ring_pos go together"):
        torch.ops.tensormass.euler_update(*args)
    assert torch.equal(x, c["x"])
