"""Inverted-element detection (tets, membranes, 2-D triangles) against an independent numpy
oracle; the Simulator's check_inversion modes; and what a minimal scene allocates against a
full-featured one (issue 6)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import boundary_faces
from tensormass_torch.sim.diagnostics import InversionCheck, allocations, depth_inside, inversion_report
from tensormass_torch.sim.simulator import InvertedElementsWarning

DT = torch.float64


def kabsch(rest: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The proper rotation R ``[3, 3]`` minimising sum |R (X - cX) - (x - cx)|^2 (numpy)."""
    a, b = rest - rest.mean(0), x - x.mean(0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def oracle_ratios(rest: np.ndarray, x: np.ndarray, elements: np.ndarray) -> np.ndarray:
    """Signed measure ratios ``[N]`` (numpy) of one object: det for tets; for triangles the
    current area vector projected on the rest unit normal turned by the object's best-fit
    rotation, over the rest area."""
    if elements.shape[1] == 4:
        def vol(p):
            q = p[elements]
            return np.linalg.det(np.stack([q[:, k] - q[:, 0] for k in (1, 2, 3)], axis=1)) / 6.0
        return vol(x) / vol(rest)
    r, q = rest[elements], x[elements]
    rest_area = np.cross(r[:, 1] - r[:, 0], r[:, 2] - r[:, 0])
    used = np.unique(elements)
    normal = rest_area / np.linalg.norm(rest_area, axis=1, keepdims=True) @ kabsch(rest[used], x[used]).T
    area = 0.5 * np.einsum("na,na->n", np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), normal)
    return area / (0.5 * np.linalg.norm(rest_area, axis=1))


def three_bodies():
    """A tet beam, a membrane (3-D triangles, tilted) and a 2-D triangle sheet, in one simulator."""
    tet = tm.beam_mesh(3, 2, 2, size=(1.0, 0.5, 0.4), dtype=DT)
    sheet = tm.beam_tri_mesh(3, 2, size=(1.0, 0.6), dim=3, dtype=DT)
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.6, 0.8], [0.0, -0.8, 0.6]], dtype=DT)
    membrane = tm.TriMesh(sheet.vertices @ tilt.T + 2.0, sheet.elements)
    planar = tm.beam_tri_mesh(2, 3, size=(0.5, 0.8), dim=2, dtype=DT)
    mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk")
    bodies = [tm.Body(tet, mat, name="beam"), tm.Body(membrane, mat, name="membrane"), tm.Body(planar, mat)]
    return tm.Simulator(bodies, dt=0.01, gravity=(0.0, 0.0, 0.0), dtype=DT)


def test_inversion_matches_the_numpy_oracle():
    sim = three_bodies()
    rest = sim.model.rest
    check = InversionCheck.for_simulator(sim)
    at_rest = check(rest)
    assert at_rest.inverted.tolist() == [0, 0, 0]
    torch.testing.assert_close(at_rest.volume_ratio, torch.ones(3, dtype=DT), rtol=1e-12, atol=0)
    torch.testing.assert_close(at_rest.min_ratio, torch.ones(3, dtype=DT), rtol=1e-12, atol=0)

    gen = torch.Generator().manual_seed(3)
    x = rest + 0.25 * torch.randn(rest.shape, generator=gen, dtype=DT)  # large enough to invert some
    report = check(x)
    rest_np, x_np = rest.numpy(), x.numpy()
    for b, body in enumerate(sim.bodies):
        nodes = slice(sim.ptr[b], sim.ptr[b + 1])
        ratios = oracle_ratios(rest_np[nodes], x_np[nodes], body.mesh.elements.numpy())
        inverted = np.flatnonzero(ratios <= 0)
        assert 0 < inverted.size < ratios.size, (b, inverted.size)  # the draw tests both outcomes
        assert int(report.inverted[b]) == inverted.size
        np.testing.assert_allclose(report.element_ratios[b].numpy(), ratios, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(float(report.min_ratio[b]), ratios.min(), rtol=1e-10)
        worst = inverted[np.argsort(ratios[inverted])][:5].tolist()
        assert report.worst(5)[b] == worst
    # volume (area) ratio: sum of signed measures over the rest sum, for every kind
    for b, body in enumerate(sim.bodies):
        nodes = slice(sim.ptr[b], sim.ptr[b + 1])
        e = body.mesh.elements.numpy()
        ratios = oracle_ratios(rest_np[nodes], x_np[nodes], e)
        rest_measure = oracle_measures(rest_np[nodes], e)
        expected = float((ratios * rest_measure).sum() / rest_measure.sum())
        assert abs(float(report.volume_ratio[b]) - expected) < 1e-12 * max(1.0, abs(expected))


def oracle_measures(rest: np.ndarray, elements: np.ndarray) -> np.ndarray:
    q = rest[elements]
    if elements.shape[1] == 4:
        return np.abs(np.linalg.det(np.stack([q[:, k] - q[:, 0] for k in (1, 2, 3)], axis=1))) / 6.0
    return 0.5 * np.linalg.norm(np.cross(q[:, 1] - q[:, 0], q[:, 2] - q[:, 0]), axis=1)


def test_mirror_inverts_tets_but_a_turned_over_sheet_is_not_inverted():
    sim = three_bodies()
    rest = sim.model.rest
    mirrored = rest * torch.tensor([-1.0, 1.0, 1.0], dtype=DT)  # a reflection inverts every tet
    report = inversion_report(sim, mirrored)
    assert int(report.inverted[0]) == sim.bodies[0].mesh.num_elements
    assert abs(float(report.volume_ratio[0]) + 1.0) < 1e-12
    # a flat sheet mirrored is the same sheet turned over (a rotation): nothing is inverted
    for b in (1, 2):
        assert int(report.inverted[b]) == 0
        assert abs(float(report.volume_ratio[b]) - 1.0) < 1e-12
    stretched = rest.clone()
    stretched[sim.ptr[2]:sim.ptr[3]] *= 2.0
    assert abs(float(inversion_report(sim, stretched).volume_ratio[2]) - 4.0) < 1e-12


def test_folded_sheet_inverts_the_folded_half():
    """A 2-D sheet folded in its plane along y = 0.6 (its upper quarter mirrored onto the rest):
    the folded quarter's triangles are inverted, the others are not. (Folded exactly in half,
    either half could be the inverted one: a sheet turned over is a rotated sheet.)"""
    sheet = tm.beam_tri_mesh(2, 4, size=(0.5, 0.8), dim=2, dtype=DT)
    sim = tm.Simulator([tm.Body(sheet, tm.Material(young=1e5, poisson=0.3))], dtype=DT)
    x = sim.model.rest.clone()
    upper = x[:, 1] > 0.6
    x[upper, 1] = 1.2 - x[upper, 1]
    report = inversion_report(sim, x)
    centroid_y = sim.model.rest[sheet.elements][:, :, 1].mean(1)
    expected = torch.nonzero(centroid_y > 0.6).flatten()
    assert int(report.inverted[0]) == expected.numel() == sheet.num_elements // 4
    assert sorted(report.worst(k=100)[0]) == expected.tolist()


def squashing_scene(check: str, push_to: float = -0.6):
    """A hooke beam clamped at x = 0 whose far end is pushed through the clamp (to x = push_to)
    in one step: elements must invert."""
    mesh = tm.beam_mesh(2, 1, 1, size=(1.0, 0.3, 0.3), dtype=DT)
    far = mesh.vertices[:, 0] >= 1.0 - 1e-9
    goal = mesh.vertices[far].clone()
    goal[:, 0] = push_to
    body = tm.Body(mesh, tm.Material(young=1e4, poisson=0.3, density=1000.0, model="hooke"),
                   fixed=mesh.vertices[:, 0] <= 1e-9, prescribed=far, motion=lambda t: goal, name="beam")
    return tm.Simulator([body], dt=0.01, gravity=(0.0, 0.0, 0.0), dtype=DT, check_inversion=check)


def oracle_count(sim) -> int:
    mesh = sim.bodies[0].mesh
    return int((oracle_ratios(mesh.vertices.numpy(), sim.x.numpy(), mesh.elements.numpy()) <= 0).sum())


def test_check_inversion_off_costs_nothing():
    sim = squashing_scene("off")
    assert sim._inversion is None
    report = sim.step()
    assert report.inverted is None and sim.last_inversion is None
    assert oracle_count(sim) > 0  # the scene does invert: "off" did not look


def test_check_inversion_warn_records_counts():
    sim = squashing_scene("warn")
    with pytest.warns(InvertedElementsWarning, match=r"object 0 \(beam\): \d+ inverted elements, worst \d+"):
        report = sim.step()
    expected = oracle_count(sim)
    assert expected > 0
    assert report.inverted.tolist() == [expected]
    assert sim.last_inversion.inverted.tolist() == [expected] and sim.steps_done == 1


def test_check_inversion_warn_is_quiet_without_inversion():
    sim = squashing_scene("warn", push_to=0.95)
    with warnings.catch_warnings():
        warnings.simplefilter("error", InvertedElementsWarning)
        report = sim.step()
    assert report.inverted.tolist() == [0] and oracle_count(sim) == 0


def test_check_inversion_error_keeps_the_state():
    sim = squashing_scene("error")
    x, v = sim.x.clone(), sim.v.clone()
    with pytest.raises(tm.SolverError, match=r"inverts elements \(object 0 \(beam\): \d+ inverted") as info:
        sim.step()
    assert info.value.status == ["inverted"]
    assert info.value.report.inverted.tolist()[0] > 0
    assert torch.equal(sim.x, x) and torch.equal(sim.v, v) and sim.time == 0.0 and sim.steps_done == 0


def test_bad_options_are_refused():
    mesh = tm.beam_mesh(2, 1, 1, dtype=DT)
    body = tm.Body(mesh, tm.Material(young=1e4, poisson=0.3), fixed=mesh.vertices[:, 0] <= 1e-9)
    with pytest.raises(tm.SceneError, match="check_inversion"):
        tm.Simulator([body], check_inversion="yes")
    for bad in (-1, 1.5, True, 11):
        with pytest.raises(tm.SceneError, match="substeps_on_failure"):
            tm.Simulator([body], substeps_on_failure=bad)


# --------------------------------------------------------------- leave out what a scene does not need

#: Buffers a hooke tensor-form tet group may hold (the vertex tensors may or may not be stored).
HOOKE_TENSOR_BUFFERS = {"elements", "measure", "edges", "edge_k", "vertex_k", "plan.index", "plan.force_index",
                        "plan.incidences", "native.index", "native.force_index", "native.incidences"}


def minimal_scene():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.3, 0.3), dtype=DT)
    return tm.Simulator([tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke"))],
                        dt=0.01, dtype=DT)


def full_scene():
    mesh = tm.beam_mesh(4, 2, 2, size=(1.0, 0.3, 0.3), dtype=DT)
    sheet = tm.beam_tri_mesh(4, 2, size=(1.0, 0.5), dim=3, dtype=DT)
    sheet = tm.TriMesh(sheet.vertices + torch.tensor([0.0, 0.0, 1.0], dtype=DT), sheet.elements)
    far = mesh.vertices[:, 0] >= 1.0 - 1e-9
    goal = mesh.vertices[far].clone()
    bodies = [
        tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk"),
                fixed=mesh.vertices[:, 0] <= 1e-9, prescribed=far, motion=lambda t: goal + 0.01 * t),
        tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="corotational")),
        tm.Body(sheet, tm.Material(young=1e5, poisson=0.3, density=1000.0, model="corotational", thickness=0.01)),
    ]
    return tm.Simulator(bodies, dt=0.01, dtype=DT, rayleigh_mass=0.1, rayleigh_stiffness=0.01,
                        planes=[tm.Plane((0.0, 0.0, 1.0), -0.5, 1e4)])


def buffers_of(names, prefix):
    return {n[len(prefix) + 1:] for n in names if n.startswith(prefix + ".")}


def test_minimal_scene_allocates_only_what_it_needs():
    sim = minimal_scene()
    sim.step(2)
    names = allocations(sim)
    assert [(g.kind, g.model, g.form) for g in sim.model.groups] == [("tet", "hooke", "tensor")]
    group = buffers_of(names, "group0.tet.hooke.tensor")
    assert group <= HOOKE_TENSOR_BUFFERS, group - HOOKE_TENSOR_BUFFERS
    assert {"edges", "edge_k"} <= group
    assert sim.system.planes is None and sim.system.free is None
    for forbidden in ("tensor_b", "tensor_c", "tensor_d", "rest_elements", "rest_normals", "projector", "planes",
                      "node_stiffness", "shape_vectors", ".tri.", "solver.refine"):
        assert not any(forbidden in n for n in names), forbidden
    # no linearisation state for a model whose stiffness does not depend on x
    assert all(s is None for m in sim.system._matvecs.values() for s in m.states)
    # the solver holds one matvec (no damping: one coefficient pair) and one CG
    assert len(sim.system._matvecs) == 1


def test_full_scene_holds_what_the_minimal_one_leaves_out():
    """The names the minimal-scene test looks for do appear when the features are on (so that
    test can fail)."""
    sim = full_scene()
    sim.step(2)
    names = allocations(sim)
    kinds = {(g.kind, g.model) for g in sim.model.groups}
    assert kinds == {("tet", "stvk"), ("tet", "corotational"), ("tri", "corotational")}
    for wanted in ("projector", "rest_normals", "system.planes.normals", "node_stiffness", "system.free",
                   ".tri.", "shape_vectors"):
        assert any(wanted in n for n in names), wanted


def test_a_mixed_precision_scene_lists_its_float32_copy():
    """precision="mixed": the float32 copy of the model and its CG's buffers are in the
    allocations (so allocation_summary counts them)."""
    mesh = tm.beam_mesh(4, 1, 1, size=(1.0, 0.25, 0.25), dtype=torch.float64)
    body = tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0), fixed=mesh.vertices[:, 0] == 0)
    sim = tm.Simulator([body], dt=0.01, precision="mixed", cg_tol=1e-4)
    sim.step(2)
    names = allocations(sim)
    (refinement,) = [kept[2] for kept in sim.system._refinements.values()]
    floats = [t for _, t in refinement.system32.model.named_buffers() if t.is_floating_point()]
    assert floats and all(t.dtype == torch.float32 for t in floats)
    assert any(n.startswith("solver.refine0.model.") for n in names) and "solver.refine0.cg.x" in names


def _cubes(offsets, sizes=None, contact=None):
    """Cubes of 4^3 cells (edge ``size``, default 0.1 m) at ``offsets``, float64."""
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    bodies = []
    for k, offset in enumerate(offsets):
        size = 0.1 if sizes is None else sizes[k]
        mesh = tm.beam_mesh(4, 4, 4, size=(size, size, size), dtype=torch.float64)
        bodies.append(tm.Body(tm.TetMesh(mesh.vertices + torch.tensor(offset, dtype=torch.float64), mesh.elements),
                              material))
    return tm.Simulator(bodies, dt=0.01, dtype=torch.float64, contact=contact)


def test_interpenetration_is_the_deepest_vertex_inside_another_body():
    assert _cubes([(0, 0, 0), (0, 0, 0.2)]).interpenetration().tolist() == [0.0, 0.0]
    # overlapping by 2 cm along z: each body's face vertices are 2 cm inside the other
    torch.testing.assert_close(_cubes([(0, 0, 0), (0, 0, 0.08)]).interpenetration(),
                               torch.tensor([0.02, 0.02], dtype=torch.float64))
    # a corner 3 cm into the other body along each axis: 3 cm from its nearest face
    torch.testing.assert_close(_cubes([(0, 0, 0), (0.03, 0.03, 0.07)]).interpenetration(),
                               torch.tensor([0.03, 0.03], dtype=torch.float64))


def test_interpenetration_sees_a_body_that_went_through_another():
    # a 2 cm cube wholly inside a 10 cm one: its surface vertex at (5, 5, 5) cm is 5 cm from every
    # face of the big one. The contact's pairs reach no further than the search (a mean edge);
    # the diagnostic sees it all
    sim = _cubes([(0, 0, 0), (0.03, 0.04, 0.05)], sizes=[0.1, 0.02], contact=tm.Contact())
    torch.testing.assert_close(sim.interpenetration(), torch.tensor([0.0, 0.05], dtype=torch.float64))
    assert float(sim.contact_report().body_penetration.max()) < 0.05


def test_interpenetration_agrees_with_the_contact_report_within_reach():
    sim = _cubes([(0, 0, 0), (0.01, 0.02, 0.095)], contact=tm.Contact())
    torch.testing.assert_close(sim.interpenetration(), sim.contact_report().body_penetration)
    assert float(sim.interpenetration().min()) > 0


def test_interpenetration_of_many_bodies_is_each_bodys_own_query():
    """All bodies at once (one batched query) = each body measured alone against the surface
    vertices of the bodies whose boxes meet its box (``depth_inside``, the per-body form): nine
    cubes of three sizes dropped into each other at random, one far from all."""
    gen = torch.Generator().manual_seed(3)
    offsets = (torch.rand(9, 3, generator=gen, dtype=torch.float64) * 0.15).tolist()
    offsets[4] = [2.0, 0.0, 0.0]
    sizes = [0.1, 0.06, 0.12] * 3
    sim = _cubes(offsets, sizes=sizes)
    sim.x = sim.x + 0.004 * torch.randn(sim.x.shape, generator=gen, dtype=torch.float64)  # not axis-aligned
    faces = sim.surface_triangles()
    surface = {i: torch.unique(f) for i, f in faces.items()}
    expected = torch.zeros(sim.num_bodies, dtype=torch.float64)
    for k in faces:
        others = torch.cat([surface[j] for j in faces if j != k])
        nodes, inside = depth_inside(sim.x, others, faces[k])
        expected.scatter_reduce_(0, sim.segments.node_object[nodes], inside, "amax")
    depth = sim.interpenetration()
    torch.testing.assert_close(depth, expected, rtol=0, atol=1e-12)
    assert int((depth > 0).sum()) >= 6 and float(depth[4]) == 0.0


def test_packed_surfaces_are_the_bodies_own():
    """Simulator.surfaces (one boundary_faces over every body) = each body's boundary_faces, in its
    order, after a removal changed one body's surface."""
    sim = _cubes([(0, 0, 0), (0.3, 0, 0), (0.6, 0, 0)])
    sim.remove_elements(1, torch.arange(10))
    triangles, body = sim.surfaces()
    for i in range(3):
        own = boundary_faces(sim.mesh(i).elements) + sim.ptr[i]
        assert torch.equal(triangles[body == i], own)
        assert torch.equal(sim.surface_triangles()[i], own)
