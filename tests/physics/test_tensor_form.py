"""Tensor form = stress form (docs/physics.md, sections 3 and 5), float64 on the CPU.

The tensor form evaluates the models from precomputed Tensor-Mass tensors (Cotin's K_ii, K_ij on
vertices and edges for hooke; Picinbono's B, C, D per element for stvk), the stress form from the
shape vectors through F, E, S, P. Both must agree to rounding. The tensors themselves are checked
against the formulas of docs/physics.md evaluated here from independently computed shape vectors, and
Cotin's vertex/edge assembly against the P1 FEM stiffness of conftest.fem_stiffness.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import FORMS, KINDS, MODELS, fem_stiffness, per_element, rel_err, shape_gradients

from tensormass_torch import Material, MaterialError, TensorMass
from tensormass_torch.ops.reference import stress_form
from tensormass_torch.physics.tensor_mass import AUTO_FORM

F64 = torch.float64
MODEL_KIND = [pytest.param(m, k, id=f"{m}-{k}") for m in MODELS for k in KINDS]
ALL = [pytest.param(m, f, k, id=f"{m}-{f}-{k}") for m in MODELS for f in FORMS for k in KINDS]


def t64(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a), dtype=F64)


def both_forms(scene, mat):
    return (TensorMass(scene.mesh, mat, form="stress"), TensorMass(scene.mesh, mat, form="tensor"))


def random_per_element_material(rng, model, n):
    return Material(young=t64(rng.uniform(1e3, 1e5, n)), poisson=t64(rng.uniform(0.05, 0.45, n)),
                    density=t64(rng.uniform(500, 2000, n)), model=model, thickness=t64(rng.uniform(0.02, 0.2, n)),
                    tangent="exact")


def lame_np(kind, young, poisson):
    mu = young / (2 * (1 + poisson))
    if kind == "tet":
        return young * poisson / ((1 + poisson) * (1 - 2 * poisson)), mu
    lam = young * poisson / (1 - poisson ** 2)  # plane stress
    return lam, mu


# ---------------------------------------------------------------------------------------------
# Tensor form = stress form
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_name,kind", MODEL_KIND)
@pytest.mark.parametrize("heterogeneous", [False, True], ids=["scalar", "per_element"])
def test_tensor_form_equals_stress_form(model_name, kind, heterogeneous, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    n = scene.elements.shape[0]
    mat = random_per_element_material(rng, model_name, n) if heterogeneous else make_material(model_name)
    stress, tensor = both_forms(scene, mat)
    assert rel_err(tensor.lumped_mass(), stress.lumped_mass()) == 0.0
    # Without a rigid motion the two agree to a few ulps; with one (rotation + shift of ~size),
    # the tensor form's polynomial in absolute displacements rounds a little worse (~1e-13; see
    # test_stvk_tensor_form_rounding_under_rigid_motion for small strains and far motions).
    states = [(deform(scene, rotate=False), 1e-13), (deform(scene, amplitude=(0.3, 0.3), rotate=False), 1e-13),
              (deform(scene), 1e-11), (deform(scene, amplitude=(0.3, 0.3)), 1e-11)]
    for x, tol in states:
        dx = t64(rng.standard_normal(x.shape))
        assert rel_err(tensor(x), stress(x)) < tol
        assert rel_err(tensor.energy(x), stress.energy(x)) < tol
        assert rel_err(tensor.dforce(x, dx), stress.dforce(x, dx)) < tol
    # at rest: zero forces and energy in both, equal stiffness
    for model in (stress, tensor):
        assert float(model(scene.rest).abs().max()) == 0.0
        assert float(model.energy(scene.rest)) == 0.0
    dx = t64(rng.standard_normal(scene.rest.shape))
    assert rel_err(tensor.dforce(scene.rest, dx), stress.dforce(scene.rest, dx)) < 1e-13


@pytest.mark.parametrize("model_name,kind", MODEL_KIND)
def test_forms_agree_over_many_random_states(model_name, kind, rng, make_scene, make_material, deform):
    """Fuzz: 20 random large deformations (no rigid part), forces and energies of both forms."""
    scene = make_scene(kind)
    stress, tensor = both_forms(scene, make_material(model_name))
    worst = 0.0
    for _ in range(20):
        x = deform(scene, amplitude=(0.05, 0.4), noise=float(rng.uniform(0, 0.1)), rotate=False)
        worst = max(worst, rel_err(tensor(x), stress(x)), rel_err(tensor.energy(x), stress.energy(x)))
    assert worst < 1e-13


# ---------------------------------------------------------------------------------------------
# The Tensor-Mass tensors against the formulas of docs/physics.md
# ---------------------------------------------------------------------------------------------


def design_polynomial_energy(m, vol, lam, mu, proj, u, model):
    """Per-element energies ``[N]`` of the Tensor-Mass formulas of docs/physics.md, evaluated here (numpy).

    hooke: W = 1/2 sum_jk u_j^T K_jk u_k, K_jk = V (lam m_j m_k^T + mu m_k m_j^T + mu (m_j.m_k) P).
    stvk:  W = sum u_j^T B_jk u_k + sum (u_j.u_k)(C_jkl.u_l) + sum D_jklm (u_j.u_k)(u_l.u_m) with
           B = K / 2, C_jkl = V (lam/2 (m_j.m_k) m_l + mu/2 ((m_l.m_j) m_k + (m_l.m_k) m_j)),
           D_jklm = V (lam/8 (m_j.m_k)(m_l.m_m) + mu/4 (m_j.m_m)(m_k.m_l))  (not symmetrised).
    P is the membrane's tangent projector (the formula is written with I: a membrane's linear strain sees no
    normal displacement), C and D need none.
    """
    dots = np.einsum("nja,nka->njk", m, m)
    L, M, V = lam[:, None, None, None, None], mu[:, None, None, None, None], vol[:, None, None, None, None]
    K = V * (L * np.einsum("nja,nkb->njkab", m, m) + M * np.einsum("nka,njb->njkab", m, m)
             + M * dots[:, :, :, None, None] * proj[:, None, None])
    quadratic = 0.5 * np.einsum("nja,njkab,nkb->n", u, K, u)
    if model == "hooke":
        return quadratic
    C = V * (0.5 * L * dots[:, :, :, None, None] * m[:, None, None, :, :]
             + 0.5 * M * (np.einsum("nlj,nka->njkla", dots, m) + np.einsum("nlk,nja->njkla", dots, m)))
    D = V * (L / 8 * np.einsum("njk,nlm->njklm", dots, dots) + M / 4 * np.einsum("njm,nkl->njklm", dots, dots))
    gram = np.einsum("nja,nka->njk", u, u)
    cubic = np.einsum("njk,njkla,nla->n", gram, C, u)
    quartic = np.einsum("njklm,njk,nlm->n", D, gram, gram)
    return quadratic + cubic + quartic


@pytest.mark.parametrize("model_name,kind", MODEL_KIND)
def test_design_tensor_formulas_equal_continuum_energy(model_name, kind, rng, make_scene, deform):
    """The polynomial of docs/physics.md (evaluated here from independent shape vectors) equals, element by
    element, the continuum energy V (lam/2 tr(E)^2 + mu tr(E^2)) of the stress form, and sums to
    the energy of both forms of the model."""
    scene = make_scene(kind)
    n_elem = scene.elements.shape[0]
    mat = random_per_element_material(rng, model_name, n_elem)
    m, area, proj = shape_gradients(scene)
    vol = area * (per_element(mat.thickness, n_elem) if kind != "tet" else 1.0)
    lam, mu = lame_np(kind, per_element(mat.young, n_elem), per_element(mat.poisson, n_elem))
    membrane = kind == "tri3d"
    for x in (deform(scene), deform(scene, amplitude=(0.3, 0.3), rotate=False)):
        u = (x - scene.rest).numpy()[scene.elements.numpy()]
        poly = design_polynomial_energy(m, vol, lam, mu, proj, u, model_name)
        cont = stress_form.ENERGIES[model_name](t64(u), t64(m), t64(vol), t64(lam), t64(mu),
                                               t64(proj) if membrane else None).numpy()
        assert rel_err(poly, cont) < 1e-11
        for model in both_forms(scene, mat):
            assert float(model.energy(x)) == pytest.approx(poly.sum(), rel=1e-11)


@pytest.mark.parametrize("kind", KINDS)
def test_stvk_tensor_symmetries(kind, make_scene, make_material):
    """B_jk = B_kj^T; C_jkl = C_kjl; D (as stored) symmetric in j<->k, l<->m, (jk)<->(lm)."""
    scene = make_scene(kind)
    (group,) = TensorMass(scene.mesh, make_material("stvk"), form="tensor").groups
    b, c, d = group.tensor_b, group.tensor_c, group.tensor_d
    n = scene.elements.shape[1]
    dim = scene.dim
    assert b.shape == (len(scene.elements), n, n, dim, dim)
    assert c.shape == (len(scene.elements), n, n, n, dim)
    assert d.shape == (len(scene.elements), n, n, n, n)
    scale_b, scale_c, scale_d = (float(t.abs().max()) for t in (b, c, d))
    assert float((b - b.permute(0, 2, 1, 4, 3)).abs().max()) <= 1e-14 * scale_b
    assert float((c - c.permute(0, 2, 1, 3, 4)).abs().max()) <= 1e-14 * scale_c
    for perm in ((0, 2, 1, 3, 4), (0, 1, 2, 4, 3), (0, 3, 4, 1, 2)):
        assert float((d - d.permute(*perm)).abs().max()) <= 1e-14 * scale_d
    # sum_j m_j = 0 makes every tensor sum to zero over any one node index (translation invariance)
    assert float(b.sum(1).abs().max()) <= 1e-12 * scale_b
    assert float(c.sum(3).abs().max()) <= 1e-12 * scale_c
    assert float(d.sum(4).abs().max()) <= 1e-12 * scale_d


@pytest.mark.parametrize("kind", KINDS)
def test_hooke_vertex_edge_tensors_assemble_to_fem_stiffness(kind, rng, make_scene):
    """Cotin's edge tensors K_ij (lower -> higher node), with the vertex tensors K_ii = -sum_j K_ij
    the forces use (rows of element blocks sum to zero), assemble to the P1 FEM stiffness matrix;
    the vertex tensors are symmetric; every mesh edge has exactly one tensor."""
    scene = make_scene(kind)
    n_elem = scene.elements.shape[0]
    mat = random_per_element_material(rng, "hooke", n_elem)
    (group,) = TensorMass(scene.mesh, mat, form="tensor").groups
    V, d = scene.rest.shape
    K = np.zeros((V * d, V * d))
    vk = np.zeros((V, d, d))
    for (i, j), kij in zip(group.edges.tolist(), group.edge_k.numpy()):
        assert i < j
        K[d * i:d * i + d, d * j:d * j + d] += kij
        K[d * j:d * j + d, d * i:d * i + d] += kij.T
        vk[i] -= kij
        vk[j] -= kij.T
    for i in range(V):
        K[d * i:d * i + d, d * i:d * i + d] = vk[i]
    expected = fem_stiffness(scene, mat.young, mat.poisson, mat.thickness)
    assert rel_err(K, expected) < 1e-12
    assert np.abs(vk - vk.transpose(0, 2, 1)).max() < 1e-12 * np.abs(vk).max()
    assert torch.equal(group.edges, scene.mesh.edges())


# ---------------------------------------------------------------------------------------------
# What each form stores, and the default
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_each_form_stores_only_what_it_needs(model_name, form, kind, make_scene, make_material):
    scene = make_scene(kind)
    model = TensorMass(scene.mesh, make_material(model_name), form=form)
    (group,) = model.groups
    assert (group.model, group.form) == (model_name, form)
    names = {name for name, b in group.named_buffers() if b is not None}
    tensors = {"vertex_k", "edges", "edge_k", "tensor_b", "tensor_c", "tensor_d"}
    assert "vertex_k" not in names  # the hooke tensor form works on differences: no vertex tensors
    if form == "stress":
        assert "shape_vectors" in names and not names & tensors
        assert (group.projector is not None) == (kind == "tri3d")
    elif model_name == "hooke":  # a hooke scene holds no C, D
        assert {"edges", "edge_k"} <= names
        assert not names & {"tensor_b", "tensor_c", "tensor_d", "shape_vectors"}
    else:
        assert {"tensor_b", "tensor_c", "tensor_d"} <= names
        assert not names & {"vertex_k", "edges", "edge_k", "shape_vectors"}
    assert model.buffer_bytes() > 0


@pytest.mark.parametrize("model_name", MODELS)
def test_auto_form_and_bad_form(model_name, make_scene, make_material):
    scene = make_scene("tet")
    mat = make_material(model_name)
    (group,) = TensorMass(scene.mesh, mat).groups
    assert group.form == AUTO_FORM[model_name] == TensorMass(scene.mesh, mat, form="auto").groups[0].form
    with pytest.raises(MaterialError):
        TensorMass(scene.mesh, mat, form="tensors")


@pytest.mark.parametrize("model_name,form,kind", ALL)
def test_bitwise_deterministic(model_name, form, kind, rng, make_scene, make_material, deform):
    scene = make_scene(kind)
    mat = make_material(model_name)
    model = TensorMass(scene.mesh, mat, form=form)
    model_material = lambda _: mat  # noqa: E731
    x = deform(scene)
    dx = t64(rng.standard_normal(x.shape))
    assert torch.equal(model(x), model(x))
    assert torch.equal(model.dforce(x, dx), model.dforce(x, dx))
    assert torch.equal(model.energy(x), model.energy(x))
    # and a second model built from the same inputs gives bitwise the same numbers
    twin = TensorMass(scene.mesh, model_material(model), form=form)
    assert torch.equal(twin(x), model(x)) and torch.equal(twin.dforce(x, dx), model.dforce(x, dx))


# ---------------------------------------------------------------------------------------------
# Rounding of the stvk tensor form under large rigid motions (a measured property)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", KINDS)
def test_stvk_tensor_form_rounding_under_rigid_motion(kind, rng, make_scene, make_material, deform):
    """The stvk tensor form is a quartic polynomial in the absolute nodal displacements u: a rigid
    motion of amplitude T cancels only in its sums, so its rounding is eps (T / h)^k (h the element
    size) where the stress form, which only sees grad U, has eps T / h. Two consequences, measured
    on these meshes (a property of the Tensor-Mass formulation, not a bug; the default form is
    "stress"):

    * far from the rest position: float64 tensor vs stress ~1e-14 at T = size, ~1e-11 at
      10 x size, ~3e-10 at 30 x size; float32 vs float64, stress form 1e-6 .. 2e-5 for
      T = 0 .. 30 x size, tensor form 1e-6, 9e-6, 2e-4, 6e-3, 0.2 for T = 0, 1, 3, 10, 30 x size:
      in float32 the stvk tensor form is only usable within ~a body size of the rest position.
    * small strain s under a large rotation: the energy, a difference of O(1) polynomial terms
      for an O(s^2) result, has relative error ~eps / s^2 in the tensor form (1e-10 at s = 1e-2,
      3e-6 at s = 1e-4 in float64) against ~eps / s in the stress form; forces ~eps / s in both.

    Asserted here with margins: what must hold for the form to be usable as documented.
    """
    scene = make_scene(kind)
    mat = make_material("stvk")
    stress, tensor = both_forms(scene, mat)
    x = deform(scene, rotate=False)
    direction = t64(rng.standard_normal(scene.dim))
    direction = direction / torch.linalg.norm(direction)
    for T in (1.0, 10.0, 30.0):
        y = x + T * scene.size * direction
        assert rel_err(tensor(y), stress(y)) < 1e-12 * T ** 3 + 1e-13
    s32 = TensorMass(scene.mesh.to(dtype=torch.float32), mat, form="stress")
    t32 = TensorMass(scene.mesh.to(dtype=torch.float32), mat, form="tensor")
    ref = stress(x)
    assert rel_err(t32(x.float()), ref) < 1e-5 and rel_err(s32(x.float()), ref) < 1e-5
    y = x + 10.0 * scene.size * direction
    assert rel_err(s32(y.float()), stress(y)) < 1e-4  # the stress form stays accurate far away
    # small strains, large rotation (+ shift), float64
    for strain in (1e-2, 1e-4):
        y = deform(scene, amplitude=(strain, strain), noise=0.0)
        dy = t64(rng.standard_normal(y.shape))
        assert rel_err(tensor(y), stress(y)) < 1e-13 / strain
        assert rel_err(tensor.dforce(y, dy), stress.dforce(y, dy)) < 1e-12
        assert rel_err(tensor.energy(y), stress.energy(y)) < 1e-12 / strain ** 2


@pytest.mark.parametrize("kind", KINDS)
def test_hooke_tensor_form_float32_is_translation_exact(kind, rng, make_scene):
    """The edges act on displacement differences: under a large rigid translation the float32
    forces of a small deformation keep their digits (the absolute form F_i = -K_ii u_i -
    sum_j K_ij u_j cancelled the translation term by term and lost ~1e-2 of the answer here)."""
    from tensormass_torch import ops

    scene = make_scene(kind)
    mat = random_per_element_material(rng, "hooke", scene.elements.shape[0])
    u32 = (50.0 + 1e-3 * torch.tensor(rng.standard_normal(scene.rest.shape))).float()
    (group64,) = TensorMass(scene.mesh, mat, form="tensor").groups
    (group32,) = TensorMass(scene.mesh.to(dtype=torch.float32), mat, form="tensor").groups
    exact = ops.forces(group64, u32.double())  # the same displacements, float64 arithmetic
    got = ops.forces(group32, u32)
    assert rel_err(got.double().numpy(), exact.numpy()) < 1e-4


@pytest.mark.parametrize("kind", ["tet", "tri3d"])
def test_hooke_edges_assembled_in_chunks_are_the_full_assembly_bitwise(kind, make_scene):
    """``assemble_hooke_edges`` makes the pair blocks a chunk of elements at a time and adds each
    chunk onto the edges before the next: the edges and their tensors are bitwise those of any
    other chunk size, and those of the full element tensors summed at once (``assemble_edges``)."""
    from tensormass_torch.ops.reference import tensor_form

    scene = make_scene(kind)
    (group,) = TensorMass(scene.mesh, Material(young=1e5, poisson=0.3), form="stress").groups
    elements, rest = group.elements.long(), scene.rest
    lam, mu = group.lame()
    args = (group.shape_vectors, group.measure, lam, mu, group.projector, elements, rest.shape[0])
    edges, edge_k = tensor_form.assemble_hooke_edges(*args, chunk=elements.shape[0])
    for chunk in (1, 3, 7):
        chunked_edges, chunked_k = tensor_form.assemble_hooke_edges(*args, chunk=chunk)
        assert torch.equal(chunked_edges, edges) and torch.equal(chunked_k, edge_k)
    full = tensor_form.element_stiffness(*args[:5])
    full_edges, full_k = tensor_form.assemble_edges(full, elements, rest.shape[0])
    assert torch.equal(full_edges, edges)
    torch.testing.assert_close(full_k, edge_k, rtol=1e-6, atol=1e-6 * float(edge_k.abs().max()))


@pytest.mark.parametrize("form", FORMS)
def test_index_tensors_are_int32_where_they_fit_and_exact_past_46341_nodes(form):
    """A group keeps its elements, plans and edges as int32 where the sizes fit (half the index
    bytes, and the kernels' own dtype: no second copy), whatever the mesh's int64 ids. With more
    than 46,341 nodes an edge key ``a * V + b`` passes 2^31: here the elements sit past 50,000
    unused nodes, and the model equals the one of the same elements without them."""
    from tensormass_torch import TetMesh, beam_mesh

    compact = beam_mesh(4, 2, 2, size=(1.0, 0.5, 0.5), dtype=F64)
    offset = 50_000
    far = torch.cat([torch.zeros(offset, 3, dtype=F64), compact.vertices])
    mesh = TetMesh(far, compact.elements + offset)
    assert mesh.num_vertices ** 2 > 2**31 and mesh.elements.dtype == torch.int64
    mat = Material(young=1e4, poisson=0.3, density=1000.0, model="hooke")
    (group,) = TensorMass(mesh, mat, form=form).groups
    (near,) = TensorMass(compact, mat, form=form).groups
    index_tensors = [group.elements, group.plan.index, group.plan.force_index, group.plan.incidences]
    assert all(t.dtype == torch.int32 for t in index_tensors)
    assert torch.equal(group.elements.long(), mesh.elements)
    if form == "tensor":
        assert group.edges.dtype == torch.int32
        assert torch.equal(group.edges.long(), mesh.edges())
        assert torch.equal(group.edges.long() - offset, near.edges.long())
        assert torch.equal(group.edge_k, near.edge_k)
    u = 1e-3 * torch.randn(compact.num_vertices, 3, dtype=F64, generator=torch.Generator().manual_seed(5))
    far_u = torch.cat([torch.zeros(offset, 3, dtype=F64), u])
    model, near_model = TensorMass(mesh, mat, form=form), TensorMass(compact, mat, form=form)
    torch.testing.assert_close(model.displacement_forces(far_u)[offset:], near_model.displacement_forces(u),
                               rtol=0, atol=1e-15)
    assert not bool(model.displacement_forces(far_u)[:offset].any())
