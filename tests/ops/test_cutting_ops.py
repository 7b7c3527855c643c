"""The cutting op (``ops.cutting``: ``cutting_cut_mesh``, ``cut_mesh``) computes what
``mesh.cutting.cut`` computes, bit for bit (elements, parents, the pairs cut, the slit): on
tetrahedra and membranes in 3-D, float64 and float32, int32 and int64 elements, cuts through a
section and partial ones, with removed elements, a second cut after the first's slit, random blades,
deformed positions, blades laid exactly through nodes and centroids (where the rounding of each
step decides), a large mesh whose reach the op must measure twice, and the SOFA beam; whatever the
number of threads and the build of torch's kernels. A blade that misses returns the mesh as it
was; bad arguments raise naming them; ``opcheck`` passes; ``cut_mesh`` brings CUDA results back
to CUDA. Pairs that share no face are ignored (where ``cut`` may take one for another pair).

The table edits of a cut in place (``cutting_edit_element_tables``, ``cutting_edit_edge_tables``,
``edit_cut_tables``) equal their references (the Python that planned cuts before them) bit for
bit, every result and every table they write: on tetrahedra and membranes, every model and form,
int64 and int32 tables, with removed elements and slits, through sequences of cuts (the model cut
in place between them holds the same tables), on the SOFA beam at a small size; an edge pool
exactly full, one row short (nothing written) and grown; a plan with no room writes nothing and
raises CapacityError; bad arguments raise naming them; the edits bump the tables' versions."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.errors import CapacityError, MeshError
from tensormass_torch.mesh import cutting
from tensormass_torch.ops import cutting as ops_cutting
from tensormass_torch.ops import library, topology
from tensormass_torch.physics.groups import _edge_pool

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")
FIELDS = ("elements", "parents", "cut_first", "cut_second", "slit")
DTYPES = [torch.float64, torch.float32]
DTYPE_IDS = ["float64", "float32"]


def op(*args):
    return library.op("cutting_cut_mesh")(*args)


def tet_mesh():
    return tm.beam_mesh(5, 3, 3, size=(1.0, 0.6, 0.6), dtype=torch.float64)


def membrane():
    return tm.beam_tri_mesh(8, 5, size=(1.0, 0.6), dim=3, dtype=torch.float64)


MESHES = {"tet": tet_mesh, "tet_uniform": lambda: tm.beam_mesh(4, 3, 2, size=(1.0, 0.6, 0.4), cut="uniform",
                                                                dtype=torch.float64),
          "membrane": membrane}


def plane_blade(x, y_high=2.0, z=(-1.0, 2.0)):
    """The plane x = const for y <= y_high (a partial cut below 1)."""
    return cutting.Blade.swept((x, -1, z[0]), (x, y_high, z[0]), (x, -1, z[1]), (x, y_high, z[1]))


def random_blade(gen, center_scale=(1.0, 0.6, 0.6)):
    """A quad through a random point of the box, randomly oriented, of random size."""
    rand = lambda *s: torch.rand(*s, generator=gen, dtype=torch.float64)
    c = rand(3) * torch.tensor(center_scale, dtype=torch.float64)
    n = torch.nn.functional.normalize(rand(3) - 0.5, dim=0)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(n, rand(3) - 0.5), dim=0)
    t2 = torch.linalg.cross(n, t1)
    s1, s2 = 0.2 + float(rand(())), 0.2 + float(rand(()))
    p = [c - s1 * t1 - s2 * t2, c + s1 * t1 - s2 * t2, c + s1 * t1 + s2 * t2, c - s1 * t1 + s2 * t2]
    return cutting.Blade.swept(p[0].tolist(), p[1].tolist(), p[3].tolist(), p[2].tolist())


def deformed(vertices, gen, amount=0.02):
    """The vertices randomly moved by up to amount / 2 per axis (below a fifth of the cells: no
    element inverts)."""
    return vertices + amount * (torch.rand(vertices.shape, generator=gen, dtype=torch.float64) - 0.5)


def reference(elements, num_nodes, x, blade, removed=None, slit=None):
    """mesh.cutting.cut, the oracle (its split assigns int64 ids into the elements: it takes int64
    elements only; the op keeps int32 ones int32), or None where it raises."""
    try:
        return cutting.cut(elements.long(), num_nodes, x, blade, removed, slit)
    except MeshError:
        return None


def assert_same(got, want):
    for field in FIELDS:
        a, b = getattr(got, field), getattr(want, field)
        if field == "elements":
            assert a.dtype in (torch.int32, torch.int64)
            b = b.to(a.dtype)
        assert a.dtype == b.dtype, field
        assert torch.equal(a, b), f"{field} differs"
    assert got.num_old_nodes == want.num_old_nodes


def near_mask(elements, x, blade, removed=None, slit=None):
    """What the simulator passes as ``alive`` on a GPU: the elements near the cut, not removed."""
    alive = ops_cutting.near_elements(elements, x, blade, slit)
    return alive if removed is None else alive & ~removed


def check(elements, num_nodes, x, blade, removed=None, slit=None):
    """The op (through cut_mesh) against the reference, and again with its host pass restricted
    to ``near_elements`` (as on a GPU); returns the reference's result (None where the blade
    misses, and then the op raises the same)."""
    want = reference(elements, num_nodes, x, blade, removed, slit)
    near = near_mask(elements, x, blade, removed, slit)
    if want is None:
        with pytest.raises(MeshError, match="crosses no interior face"):
            ops_cutting.cut_mesh(elements, num_nodes, x, blade, removed, slit)
        with pytest.raises(MeshError, match="crosses no interior face"):
            ops_cutting.cut_mesh(elements, num_nodes, x, blade, removed, slit, alive=near)
        return None
    got = ops_cutting.cut_mesh(elements, num_nodes, x, blade, removed, slit)
    assert_same(got, want)
    assert got.elements.dtype == elements.dtype
    assert_same(ops_cutting.cut_mesh(elements, num_nodes, x, blade, removed, slit, alive=near), want)
    return want


@pytest.mark.parametrize("index", [torch.int64, torch.int32], ids=["int64", "int32"])
@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("kind", list(MESHES))
def test_cuts_through_a_section_and_partial_ones_equal_the_reference(kind, dtype, index):
    mesh = MESHES[kind]()
    x = mesh.vertices.to(dtype)
    elements = mesh.elements.to(index)
    full = check(elements, mesh.num_vertices, x, plane_blade(0.51))
    assert full is not None and full.new_nodes > 0
    partial = check(elements, mesh.num_vertices, x, plane_blade(0.51, y_high=0.25))
    assert partial is not None and 0 < partial.new_nodes < full.new_nodes
    # a slit: a blade ending inside the body, oblique so that faces stay joined along its front
    slanted = cutting.Blade.swept((0.53, -1, -1), (0.47, 0.33, -1), (0.53, -1, 2), (0.47, 0.33, 2))
    check(elements, mesh.num_vertices, x, slanted)


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("kind", list(MESHES))
def test_removed_elements_slits_and_successive_cuts_equal_the_reference(kind, dtype):
    mesh = MESHES[kind]()
    gen = torch.Generator().manual_seed(5)
    n = mesh.elements.shape[0]
    removed = torch.rand(n, generator=gen) < 0.15
    x = deformed(mesh.vertices, gen).to(dtype)
    elements, num_nodes, slit, cuts = mesh.elements, mesh.num_vertices, None, 0
    # a scalpel going down in strips: each cut with the previous one's elements and slit
    for step in range(6):
        top = 0.62 - 0.1 * step
        blade = cutting.Blade.swept((0.55, top, -1), (0.55, top, 2), (0.45, top - 0.12, -1), (0.45, top - 0.12, 2))
        want = check(elements, num_nodes, x, blade, removed, slit)
        if want is None:
            continue
        cuts += 1
        elements, slit = want.elements, want.slit
        x = x[want.parents]
        num_nodes = x.shape[0]
    assert cuts >= 3


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("kind", list(MESHES))
def test_random_blades_on_deformed_meshes_equal_the_reference(kind, dtype):
    mesh = MESHES[kind]()
    gen = torch.Generator().manual_seed(11)
    crossed = 0
    for trial in range(40):
        x = deformed(mesh.vertices, gen).to(dtype)
        removed = (torch.rand(mesh.elements.shape[0], generator=gen) < 0.1) if trial % 3 == 0 else None
        elements, num_nodes, slit = mesh.elements.to(torch.int32 if trial % 2 else torch.int64), mesh.num_vertices, None
        for _ in range(2):
            want = check(elements, num_nodes, x, random_blade(gen), removed, slit)
            if want is None:
                continue
            crossed += 1
            elements, slit = want.elements.to(elements.dtype), want.slit
            x = x[want.parents]
            num_nodes = x.shape[0]
    assert crossed >= 30


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_blades_through_nodes_and_centroids_equal_the_reference(dtype):
    """Planes laid exactly through grid nodes and element centroids: segments that end on the
    blade or run along its edges, where each step's rounding decides (the cross products and
    norms round as torch's kernels do)."""
    mesh = tm.beam_mesh(6, 3, 3, size=(1.2, 0.6, 0.6), dtype=torch.float64)
    x = mesh.vertices.to(dtype)
    centroid_planes = torch.unique(x[mesh.elements].mean(1)[:, 0]).tolist()[:8]
    crossed = 0
    for px in [0.2 * i for i in range(7)] + centroid_planes:
        for y_high in (0.6, 0.3, 0.2, 0.1):
            for z in ((-1.0, 2.0), (0.0, 0.6), (0.2, 0.4)):
                for blade in (plane_blade(px, y_high, z),
                              cutting.Blade.swept((px, y_high, z[0]), (px, y_high, z[1]), (px - 0.2, y_high - 0.2, z[0]),
                                                  (px - 0.2, y_high - 0.2, z[1]))):
                    crossed += check(mesh.elements, mesh.num_vertices, x, blade) is not None
    assert crossed > 200


def test_a_large_mesh_whose_reach_is_measured_again_equals_the_reference():
    """A mesh large enough that the op guesses the reach (the largest node-to-centroid distance)
    from a sample of its elements: with every sampled element removed, or one node pulled far
    away, the guess falls short and the op looks at the elements again."""
    mesh = tm.beam_mesh(16, 6, 6, size=(1.6, 0.6, 0.6), dtype=torch.float64)
    n = mesh.elements.shape[0]
    gen = torch.Generator().manual_seed(2)
    sampled = torch.arange(n) % (n // 512) == 0  # the op's sample: every (N // 512)-th element
    pulled = mesh.vertices.clone()
    pulled[mesh.elements[7, 1]] += torch.tensor([0.0, 0.9, 0.4], dtype=torch.float64)
    crossed = 0
    for x, removed in ((mesh.vertices, sampled), (pulled, None), (deformed(mesh.vertices, gen), None)):
        for dtype in DTYPES:
            for px in (0.05, 0.43, 0.97, 1.52):
                for top in (0.62, 0.3):
                    blade = cutting.Blade.swept((px, top, -1), (px, top, 2), (px + 0.02, top - 0.2, -1),
                                                (px, top - 0.2, 2))
                    crossed += check(mesh.elements, mesh.num_vertices, x.to(dtype), blade, removed) is not None
    assert crossed >= 40


@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_node_ids_past_21_bits_equal_the_reference(kind):
    """Node ids of 2**21 and more (the op's face keys no longer fit in one word)."""
    mesh = MESHES[kind]()
    offset = 2**21
    x = torch.zeros((offset + mesh.num_vertices, 3), dtype=torch.float32)
    x[offset:] = mesh.vertices.float()
    elements = (mesh.elements + offset).to(torch.int32)
    first = check(elements, x.shape[0], x, plane_blade(0.51, 0.25))
    assert first is not None and first.new_nodes > 0
    check(first.elements, first.parents.shape[0], x[first.parents], plane_blade(0.71), slit=first.slit)


def test_the_sofa_beam_strip_equals_the_reference():
    from tensormass_torch.sim import builtin

    mesh = builtin.sofa_beam().simulator.bodies[0].mesh  # float32, 101,250 tetrahedra
    blade = cutting.Blade.swept((9.55, 8.0, -3), (9.55, 8.0, 3), (9.55, 7.73, -3), (9.55, 7.73, 3))
    want = check(mesh.elements, mesh.num_vertices, mesh.vertices, blade)
    assert want is not None and want.cut_first.numel() > 10
    near = ops_cutting.near_elements(mesh.elements, mesh.vertices, blade)
    assert int(near.sum()) < mesh.elements.shape[0] // 20  # the host pass reads a few elements
    # the reference (no extension) takes the same mask
    assert_same(ops_cutting.cut_mesh(mesh.elements, mesh.num_vertices, mesh.vertices, blade, alive=near,
                                     native=False), want)


def test_the_result_does_not_depend_on_the_number_of_threads():
    mesh = tm.beam_mesh(16, 6, 6, size=(1.6, 0.6, 0.6), dtype=torch.float64)
    x = deformed(mesh.vertices, torch.Generator().manual_seed(4))
    alive = torch.ones(mesh.elements.shape[0], dtype=torch.bool)
    blade = plane_blade(0.83, 0.35)
    args = (mesh.elements, alive, x, blade.vertices, blade.triangles, torch.zeros((0, 2), dtype=torch.int64))
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = op(*args)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, op(*args)):
        assert torch.equal(a, b)


def test_the_cut_follows_the_rounding_of_torchs_default_kernels():
    """With ATEN_CPU_CAPABILITY=default torch's cross products and norms round each product (its
    vectorised builds fuse them): the op asks torch which, and still equals the reference."""
    code = ("import sys, torch; sys.path.insert(0, {tests!r}); import test_cutting_ops as t;"
            "t.test_blades_through_nodes_and_centroids_equal_the_reference(torch.float64);"
            "t.test_blades_through_nodes_and_centroids_equal_the_reference(torch.float32)")
    env = dict(os.environ, ATEN_CPU_CAPABILITY="default")
    done = subprocess.run([sys.executable, "-c", code.format(tests=os.path.dirname(__file__))], env=env,
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.parametrize("kind", list(MESHES))
def test_a_blade_that_misses_returns_the_mesh_unchanged(kind):
    mesh = MESHES[kind]()
    n = mesh.elements.shape[0]
    first, second, _ = cutting.interior_faces(mesh.elements)
    removed = torch.zeros(n, dtype=torch.bool)
    removed[second[1]] = True
    slit = torch.stack([first[:3], second[:3]], 1)  # a removed element in the second row
    alive = ~removed
    far = plane_blade(5.0)
    out = op(mesh.elements, alive, mesh.vertices, far.vertices, far.triangles, slit)
    assert torch.equal(out[0], mesh.elements) and out[0].data_ptr() != mesh.elements.data_ptr()
    assert torch.equal(out[1], torch.arange(mesh.num_vertices))
    assert out[2].shape == (0,) and out[3].shape == (0,) and out[2].dtype == torch.int64
    kept = alive[slit].all(1)
    assert not bool(kept.all()) and torch.equal(out[4], slit[kept])  # the alive rows (which share their face)
    with pytest.raises(MeshError, match="crosses no interior face"):
        ops_cutting.cut_mesh(mesh.elements, mesh.num_vertices, mesh.vertices, far, removed, slit)
    with pytest.raises(MeshError, match="crosses no interior face"):
        cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, far, removed, slit)


def test_pairs_that_share_no_face_are_ignored():
    """A slit row whose elements share no face parts nothing: the op's result is the cut without
    it. (mesh.cutting.cut looks the parted faces up by the rows' positions among the elements
    around the cut, where such a row can stand for another pair: here it splits a fifth node.)"""
    mesh = tm.beam_mesh(4, 3, 3, size=(1.0, 0.6, 0.6), dtype=torch.float64)
    blade = plane_blade(0.3, 0.1)
    strangers = torch.tensor([[12, 26]])  # no node in common
    got = ops_cutting.cut_mesh(mesh.elements, mesh.num_vertices, mesh.vertices, blade, slit=strangers)
    without = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blade)
    for field in ("elements", "parents", "cut_first", "cut_second"):
        assert torch.equal(getattr(got, field), getattr(without, field))
    assert got.new_nodes == 4 and got.slit.shape == (0, 2)
    assert cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blade, slit=strangers).new_nodes == 5


def _args(dtype=torch.float64):
    mesh = tet_mesh()
    blade = plane_blade(0.51)
    return dict(elements=mesh.elements, alive=torch.ones(mesh.elements.shape[0], dtype=torch.bool),
                x=mesh.vertices.to(dtype), blade_vertices=blade.vertices.to(dtype), blade_triangles=blade.triangles,
                slit=torch.zeros((0, 2), dtype=torch.int64))


@pytest.mark.parametrize("change,message", [
    (dict(elements=lambda a: a["elements"].float()), "elements must be int64 or int32"),
    (dict(elements=lambda a: a["elements"][:, :2].contiguous()), r"elements must be \[N, 4\]"),
    (dict(elements=lambda a: a["elements"].t().contiguous().t()), "elements must be contiguous"),
    (dict(elements=lambda a: torch.where(a["elements"] == 7, 10**6, a["elements"])), "elements: alive element .* outside"),
    (dict(alive=lambda a: a["alive"].int()), "alive must be bool"),
    (dict(alive=lambda a: a["alive"][1:]), "alive has shape"),
    (dict(x=lambda a: a["x"][:, :2].contiguous()), r"x must be \[V, 3\]"),
    (dict(x=lambda a: a["x"].half()), "x must be float32 or float64"),
    (dict(x=lambda a: a["x"][:-1]), "elements: alive element .* outside"),
    (dict(blade_vertices=lambda a: a["blade_vertices"].float()), "blade_vertices is Float but x is Double"),
    (dict(blade_vertices=lambda a: a["blade_vertices"][:, :2].contiguous()), r"blade_vertices must be \[B >= 1, 3\]"),
    (dict(blade_triangles=lambda a: a["blade_triangles"].int()), "blade_triangles must be int64"),
    (dict(blade_triangles=lambda a: a["blade_triangles"][:0]), r"blade_triangles must be \[T >= 1, 3\]"),
    (dict(blade_triangles=lambda a: a["blade_triangles"] + 2), "blade_triangles holds 4, outside the 4 blade_vertices"),
    (dict(slit=lambda a: torch.tensor([[0, 1]], dtype=torch.int32)), "slit must be int64"),
    (dict(slit=lambda a: torch.tensor([0, 1])), r"slit must be \[S, 2\]"),
    (dict(slit=lambda a: torch.tensor([[0, 10**6]])), "slit holds element 1000000, outside the 270 elements"),
])
def test_bad_arguments_raise_naming_them(change, message):
    args = _args()
    for name, make in change.items():
        args[name] = make(args)
    with pytest.raises(RuntimeError, match=message):
        op(*args.values())


def test_cut_mesh_refuses_positions_of_the_wrong_shape():
    mesh = tet_mesh()
    for x in (mesh.vertices[:, :2], mesh.vertices[:-1]):
        with pytest.raises(MeshError, match=r"positions must be \[96, 3\]"):
            ops_cutting.cut_mesh(mesh.elements, mesh.num_vertices, x, plane_blade(0.51))
    alive = torch.ones(mesh.elements.shape[0] - 1, dtype=torch.bool)
    with pytest.raises(MeshError, match=r"alive must be \[%d\]" % mesh.elements.shape[0]):
        ops_cutting.cut_mesh(mesh.elements, mesh.num_vertices, mesh.vertices, plane_blade(0.51), alive=alive)


def test_opcheck_on_the_example():
    d = library.REGISTRY["cutting_cut_mesh"]
    for dtype in DTYPES:
        args, kwargs = d.example("cpu", dtype)
        torch.library.opcheck(library.op("cutting_cut_mesh"), args, kwargs)
        got = op(*args)
        want = d.reference(*args)
        assert got[2].numel() > 0 and got[4].numel() > 0  # the example cuts and leaves a slit
        for a, b in zip(got, want):
            assert torch.equal(a, b)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_cut_mesh_brings_cuda_inputs_back_to_cuda():
    mesh = tet_mesh()
    device = torch.device("cuda")
    removed = torch.zeros(mesh.elements.shape[0], dtype=torch.bool)
    removed[3] = True
    got = ops_cutting.cut_mesh(mesh.elements.to(device), mesh.num_vertices, mesh.vertices.float().to(device),
                               plane_blade(0.51, 0.25).to(mesh.vertices.to(device)), removed.to(device))
    want = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices.float(), plane_blade(0.51, 0.25), removed)
    for field in FIELDS:
        assert getattr(got, field).device.type == "cuda", field
        assert torch.equal(getattr(got, field).cpu(), getattr(want, field)), field



# ---------------------------------------------------------------------------------------------
# The table edits of a cut in place
# ---------------------------------------------------------------------------------------------

WRITTEN = ("elements", "force_index", "incidences", "node_items", "node_slots")
EDGE_WRITTEN = ("edges", "edge_slots", "element_edges")
TABLES = WRITTEN + EDGE_WRITTEN + ("element_row",)
TABLE_CASES = [("tet", "hooke", "tensor"), ("tet", "stvk", "tensor"), ("tet", "hooke", "stress"),
               ("tet", "stvk", "stress"), ("tet", "corotational", "stress"), ("membrane", "hooke", "tensor"),
               ("membrane", "stvk", "tensor"), ("membrane", "corotational", "stress")]
TABLE_CASE_IDS = ["-".join(case) for case in TABLE_CASES]
INDEX = [torch.int64, torch.int32]
INDEX_IDS = ["int64", "int32"]


def table_model(mesh, kind, model_name, form, spare, pool_nodes=None, reserve=True):
    """A model of ``mesh`` with ``spare`` spare rows (where cuts put their new nodes) and, where
    ``reserve``, room for cuts (slots, and a pool of edges for ``pool_nodes`` new nodes)."""
    rest = torch.cat([mesh.vertices, mesh.vertices[:1].expand(spare, 3)])
    material = tm.Material(model=model_name, young=2e4, poisson=0.3, density=800.0, rotation="polar")
    model = tm.TensorMass.packed(rest, [(mesh.elements, material, kind)], form=form)
    if reserve:
        model.reserve_slots(spare_nodes=spare if pool_nodes is None else pool_nodes)
    model._prepare_removals()
    return model


def host_tables(model, index=None):
    """Copies of the host tables a cut of the model's one group edits (``ElementGroup.cut_tables``
    and the model's ``node_slots``, ``element_row``), of ``index`` dtype where given."""
    tables = dict(model.groups[0].cut_tables())
    model_tables = model._cut_tables()
    tables.update(node_slots=model_tables["node_slots"], element_row=model_tables["element_row"])
    return {k: (v.clone() if index is None else v.to(index).clone()).contiguous() for k, v in tables.items()}


def op_call(tables, ids, nodes, removed, edge_rows_used):
    """The op and its arguments for a cut re-pointing model elements ``ids`` to ``nodes``, as
    ``TensorMass.repoint_elements`` passes them."""
    rows = tables["element_row"][ids]
    nodes = nodes.to(tables["elements"].dtype).contiguous()
    head = [tables[k] for k in WRITTEN]
    if "edges" not in tables:
        return ops_cutting.ELEMENT_TABLES, head + [rows, ids, nodes]
    return ops_cutting.EDGE_TABLES, head + [tables[k] for k in EDGE_WRITTEN] + [
        rows, ids, nodes, tables["element_row"], removed, edge_rows_used]


def assert_identical(got, want, what):
    assert got.dtype == want.dtype, f"{what}: {got.dtype} != {want.dtype}"
    assert got.shape == want.shape, f"{what}: {tuple(got.shape)} != {tuple(want.shape)}"
    assert torch.equal(got, want), f"{what} differs"


def assert_same_tables(got, want):
    assert set(got) == set(want)
    for name in got:
        assert_identical(got[name], want[name], name)


def check_table_edit(model, ids, nodes, index=None, edge_rows_used=None):
    """The op on copies of the model's tables against its reference on other copies: every
    result and every table bit for bit. Returns (results by name, the op's tables)."""
    removed = model.removed_host().clone()
    used = getattr(model.groups[0], "edge_rows_used", 0) if edge_rows_used is None else edge_rows_used
    native, reference = host_tables(model, index), host_tables(model, index)
    name, args = op_call(native, ids, nodes, removed, used)
    _, ref_args = op_call(reference, ids, nodes, removed, used)
    got = library.op(name)(*args)
    want = library.REGISTRY[name].reference(*ref_args)
    names = ops_cutting.EDGE_RESULTS if name == ops_cutting.EDGE_TABLES else ops_cutting.ELEMENT_RESULTS
    assert len(got) == len(want) == len(names)
    for result, a, b in zip(names, got, want):
        assert_identical(a, b, result)
    assert_same_tables(native, reference)
    return dict(zip(names, got)), native


def run_cuts(model, mesh, blades, index=None, removals=((3, 11, 20), (5,))):
    """Cuts along ``blades`` one after another (with the previous cuts' slit), each checked by
    check_table_edit and then made in the model (``repoint_elements``), whose own tables then hold
    what the op wrote on its copies; elements removed before the first cut and the second.
    Returns the number of cuts whose new nodes split elements."""
    count = mesh.elements.shape[0]
    elements, vertices, slit = mesh.elements.clone(), mesh.vertices, None
    alive = torch.ones(count, dtype=torch.bool)
    split = 0
    for k, blade in enumerate(blades):
        if k < len(removals):
            gone = torch.tensor([r for r in removals[k] if r < count and bool(alive[r])], dtype=torch.int64)
            model.remove_elements(gone)
            alive[gone] = False
        used = vertices.shape[0]
        result = cutting.cut(elements, used, vertices, blade, ~alive, slit)
        ids = torch.nonzero((result.elements != elements).any(1)).flatten()
        nodes = result.elements[ids]
        results, edited = check_table_edit(model, ids, nodes, index)
        if ids.numel():
            split += 1
            model.repoint_elements(ids, nodes, torch.arange(used, result.parents.shape[0]), result.parents[used:])
            if index is None:
                assert_same_tables(host_tables(model), edited)
        elements, vertices, slit = result.elements, vertices[result.parents], result.slit
    return split


def blades_of(kind):
    """Through the body, a partial cut (a slit, oblique: faces stay joined along its front) and
    one more through the body beside them."""
    if kind == "tet":
        return [plane_blade(0.51),
                cutting.Blade.swept((0.33, -1, -1), (0.27, 0.33, -1), (0.33, -1, 2), (0.27, 0.33, 2)),
                plane_blade(0.73, y_high=0.45)]
    return [plane_blade(0.51, y_high=0.3),
            cutting.Blade.swept((0.33, -1, -1), (0.27, 0.5, -1), (0.33, -1, 2), (0.27, 0.5, 2)),
            plane_blade(0.76)]


@pytest.mark.parametrize("index", INDEX, ids=INDEX_IDS)
@pytest.mark.parametrize("kind,model_name,form", TABLE_CASES, ids=TABLE_CASE_IDS)
def test_table_edits_of_every_model_and_form_equal_the_reference(kind, model_name, form, index):
    mesh = MESHES[kind]()
    model = table_model(mesh, "tet" if kind == "tet" else "tri", model_name, form, spare=90)
    assert run_cuts(model, mesh, blades_of(kind), index) == 3


@pytest.mark.parametrize("model_name,form", [("hooke", "tensor"), ("corotational", "stress")])
def test_the_sofa_beam_at_a_small_size_equals_the_reference(model_name, form):
    from tensormass_torch.sim import builtin

    mesh = builtin.sofa_beam(model=model_name, scale=5).simulator.bodies[0].mesh  # 15 x 3 x 3 cells, float32
    model = table_model(mesh, "tet", model_name, form, spare=64)

    def section(x, y_low):
        return cutting.Blade.swept((x, 11, -3), (x, 11, 3), (x, y_low, -3), (x, y_low, 3))

    assert run_cuts(model, mesh, [section(6.0137, 8.9), section(9.525, 5.9), section(6.33, 5.9),
                                  section(12.7, 7.1)]) == 4


def first_cut(mesh, kind):
    """The elements a cut through the body re-points (model ids) and their new nodes."""
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blades_of(kind)[0])
    ids = torch.nonzero((result.elements != mesh.elements).any(1)).flatten()
    return ids, result.elements[ids]


def trimmed(tables, rows):
    """The tables with their edge rows cut to ``rows`` (the pool's past them)."""
    tables = dict(tables)
    for name in ("edges", "force_index"):
        tables[name] = tables[name][:rows].contiguous()
    tables["edge_slots"] = tables["edge_slots"][:, :rows].contiguous()
    return tables


@pytest.mark.parametrize("index", INDEX, ids=INDEX_IDS)
@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_an_edge_pool_exactly_full_edits_and_one_row_short_writes_nothing(kind, index):
    mesh = MESHES[kind]()
    model = table_model(mesh, "tet" if kind == "tet" else "tri", "hooke", "tensor", spare=40)
    model.remove_elements([2, 9])
    ids, nodes = first_cut(mesh, kind)
    used = model.groups[0].edge_rows_used
    removed = model.removed_host()
    status = library.REGISTRY[ops_cutting.EDGE_TABLES].reference(*op_call(host_tables(model, index), ids, nodes,
                                                                          removed, used)[1])[0]
    count = int(status[1])
    assert int(status[2]) == 1 and count > 0
    for rows, edits in ((used + count, True), (used + count - 1, False)):
        before = trimmed(host_tables(model, index), rows)
        native, reference = ({k: v.clone() for k, v in before.items()} for _ in range(2))
        name, args = op_call(native, ids, nodes, removed, used)
        got = library.op(name)(*args)
        want = library.REGISTRY[name].reference(*op_call(reference, ids, nodes, removed, used)[1])
        for result, a, b in zip(ops_cutting.EDGE_RESULTS, got, want):
            assert_identical(a, b, result)
        assert_same_tables(native, reference)
        assert bool(got[0][2]) == edits and int(got[0][1]) == count
        if not edits:
            assert_same_tables(native, before)
            assert all(t.numel() == 0 for t in got[1:])


def grower(tables, sink):
    """grow_pool for edit_cut_tables, as ElementGroup's: at least an eighth more rows."""
    def grow(rows):
        capacity = tables["edges"].shape[0]
        tables["edges"], tables["force_index"], tables["edge_slots"] = _edge_pool(
            tables["edges"], tables["force_index"], tables["edge_slots"], max(rows - capacity, capacity // 8), sink)
    return grow


@pytest.mark.parametrize("index", INDEX, ids=INDEX_IDS)
@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_an_edge_pool_too_small_grows_and_the_edit_equals_the_reference(kind, index):
    mesh = MESHES[kind]()
    model = table_model(mesh, "tet" if kind == "tet" else "tri", "hooke", "tensor", spare=40, pool_nodes=0)
    ids, nodes = first_cut(mesh, kind)
    group = model.groups[0]
    used, sink = group.edge_rows_used, group.plan.num_slots - 1
    assert group.edges.shape[0] == used  # no pool
    done = []
    for native in (True, False):
        tables = host_tables(model, index)
        node_slots = tables.pop("node_slots")
        results, rows_used = ops_cutting.edit_cut_tables(tables, node_slots, tables["element_row"][ids], ids, nodes,
                                                         tables["element_row"], model.removed_host(), used,
                                                         grower(tables, sink), native=native)
        assert tables["edges"].shape[0] >= rows_used > used
        done.append((results, rows_used, dict(tables, node_slots=node_slots)))
    (got, got_used, got_tables), (want, want_used, want_tables) = done
    assert got_used == want_used and list(got) == list(want) == list(ops_cutting.EDGE_RESULTS[1:])
    for name in got:
        assert_identical(got[name], want[name], name)
    assert_same_tables(got_tables, want_tables)
    # the model grows its pool the same way
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blades_of(kind)[0])
    model.repoint_elements(ids, nodes, torch.arange(mesh.num_vertices, result.parents.shape[0]),
                           result.parents[mesh.num_vertices:])
    if index == group.elements.dtype:
        assert_same_tables(host_tables(model), got_tables)
        assert group.edge_rows_used == got_used


@pytest.mark.parametrize("native", [True, False], ids=["op", "reference"])
@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_a_plan_with_no_room_writes_nothing_and_raises(kind, native):
    """No slots reserved: the plan's last slot, which the edges a cut empties would take, is a
    node's. The op writes nothing and says why; edit_cut_tables and repoint_elements raise
    CapacityError with every table as it was."""
    mesh = MESHES[kind]()
    model = table_model(mesh, "tet" if kind == "tet" else "tri", "hooke", "tensor", spare=40, reserve=False)
    ids, nodes = first_cut(mesh, kind)
    group = model.groups[0]
    used, removed = group.edge_rows_used, model.removed_host()
    before = host_tables(model)
    tables = host_tables(model)
    name, args = op_call(tables, ids, nodes, removed, used)
    call = library.op(name) if native else library.REGISTRY[name].reference
    status = call(*args)[0]
    assert int(status[2]) == 0 and int(status[0]) > group.plan.num_slots - 1
    assert_same_tables(tables, before)
    node_slots = tables.pop("node_slots")
    with pytest.raises(CapacityError, match=f"the plan has room for {group.plan.num_slots - 1}"):
        ops_cutting.edit_cut_tables(tables, node_slots, tables["element_row"][ids], ids, nodes, tables["element_row"],
                                    removed, used, grower(tables, 0), native=native)
    assert_same_tables(dict(tables, node_slots=node_slots), before)
    result = cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blades_of(kind)[0])
    with pytest.raises(CapacityError, match="room for"):
        model.repoint_elements(ids, nodes, torch.arange(mesh.num_vertices, result.parents.shape[0]),
                               result.parents[mesh.num_vertices:])
    assert_same_tables(host_tables(model), before)
    assert group.edge_rows_used == used


@pytest.mark.parametrize("name", [ops_cutting.ELEMENT_TABLES, ops_cutting.EDGE_TABLES])
def test_the_table_edits_equal_the_reference_on_their_examples_and_bump_versions(name):
    d = library.REGISTRY[name]
    args, _ = d.example("cpu", torch.float64)
    native = [a.clone() if isinstance(a, torch.Tensor) else a for a in args]
    reference = [a.clone() if isinstance(a, torch.Tensor) else a for a in args]
    got, want = library.op(name)(*native), d.reference(*reference)
    for a, b in zip(got, want):
        assert_identical(a, b, name)
    written = [i for i, a in enumerate(library.op(name)._schema.arguments) if a.alias_info is not None]
    for i in written:
        assert_identical(native[i], reference[i], library.op(name)._schema.arguments[i].name)
    assert all(not torch.equal(native[i], args[i]) for i in written)  # the example edits every table
    # through edit_cut_tables, the op's writes bump the tables' versions (caches keyed on them)
    tables = dict(zip(WRITTEN + EDGE_WRITTEN, [a.clone() for a in args[:len(written)]]))
    node_slots = tables.pop("node_slots")
    versions = [t._version for t in tables.values()] + [node_slots._version]
    rows, ids, nodes = args[len(written):len(written) + 3]
    edge = name == ops_cutting.EDGE_TABLES
    ops_cutting.edit_cut_tables(tables, node_slots, rows, ids, nodes, *(args[-3:] if edge else ()))
    assert all(t._version > v for t, v in zip(list(tables.values()) + [node_slots], versions))


def _table_args():
    args, _ = library.REGISTRY[ops_cutting.EDGE_TABLES].example("cpu", torch.float64)
    return dict(zip([a.name for a in library.op(ops_cutting.EDGE_TABLES)._schema.arguments], args))


@pytest.mark.parametrize("change,message", [
    (dict(force_index=lambda a: a["force_index"].long()), "force_index is Long; expected Int"),
    (dict(elements=lambda a: a["elements"][:, :2].contiguous()), r"elements must be \[N, 4\]"),
    (dict(node_items=lambda a: a["node_items"][:, 1:]), r"node_items has shape \[.*\]; expected"),
    (dict(edge_slots=lambda a: a["edge_slots"].t().contiguous().t()), "edge_slots must be contiguous"),
    (dict(ids=lambda a: a["ids"].int()), "ids is Int; expected Long"),
    (dict(rows=lambda a: a["rows"] + 10**6), "rows holds 10000"),
    (dict(nodes=lambda a: a["nodes"] + 10**6), "nodes holds 10000"),
    (dict(removed=lambda a: a["removed"][1:]), "removed has shape"),
    (dict(edge_rows_used=lambda a: 10**7), "edge_rows_used is 10000000"),
    (dict(edge_rows_used=lambda a: 0), "element_edges: row .* outside the 0 edge rows in use"),
])
def test_bad_table_arguments_raise_naming_them_and_write_nothing(change, message):
    args = _table_args()
    for name, make in change.items():
        args[name] = make(args)
    before = {k: v.clone() for k, v in args.items() if isinstance(v, torch.Tensor)}
    with pytest.raises(RuntimeError, match=message):
        library.op(ops_cutting.EDGE_TABLES)(*args.values())
    for k, v in before.items():
        assert torch.equal(args[k], v), k


# ---------------------------------------------------------------------------------------------
# The cut on the device
# ---------------------------------------------------------------------------------------------

DEVICE_SPARE = 300


def small_blade(gen):
    """A random quad of side 0.1-0.5 inside the beam's box: cuts that end inside the body (slits)."""
    rand = lambda *s: torch.rand(*s, generator=gen, dtype=torch.float64)
    c = rand(3) * torch.tensor([1.0, 0.6, 0.6], dtype=torch.float64)
    n = torch.nn.functional.normalize(rand(3) - 0.5, dim=0)
    t1 = torch.nn.functional.normalize(torch.linalg.cross(n, rand(3) - 0.5), dim=0)
    t2 = torch.linalg.cross(n, t1)
    s1, s2 = 0.05 + 0.2 * float(rand(())), 0.05 + 0.2 * float(rand(()))
    p = [c - s1 * t1 - s2 * t2, c + s1 * t1 - s2 * t2, c + s1 * t1 + s2 * t2, c - s1 * t1 + s2 * t2]
    return cutting.Blade.swept(p[0].tolist(), p[1].tolist(), p[3].tolist(), p[2].tolist())


def device_cuts(mesh, blades, removed=(), index=torch.int64, dtype=torch.float64, device="cpu", native=True,
                gen=None):
    """Cuts ``blades`` in turn with ``ops.cutting.cut_on_device`` and with ``mesh.cutting.cut``
    (the oracle, fed its own slit), the positions deformed by ``gen`` (a generator, or None); after
    each: the same elements, new nodes' parents, pairs crossed and slit (the parted faces still
    shared). Returns the nodes added."""
    num_nodes, n = mesh.num_vertices, mesh.elements.shape[1]
    elements = mesh.elements.to(device=device, dtype=index)
    rest = mesh.vertices if gen is None else deformed(mesh.vertices, gen)
    x = torch.cat([rest, rest[:1].expand(DEVICE_SPARE, 3)]).to(device=device, dtype=dtype)
    alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
    alive[list(removed)] = False
    faces = ops_cutting.face_table(elements)
    parents = torch.arange(num_nodes + DEVICE_SPARE, device=device)
    element_ids = torch.arange(elements.shape[0], dtype=index, device=device).repeat_interleave(n)
    want_elements, slit, used, scratch = mesh.elements.clone(), None, num_nodes, {}
    for blade in blades:
        want = reference(want_elements, used, x[:used].cpu(), blade, ~alive.cpu(), slit)
        node_slots = topology.incidence_table(elements.reshape(-1).long(), element_ids, num_nodes + DEVICE_SPARE)
        limits = torch.tensor([used, num_nodes + DEVICE_SPARE - used], device=device)
        crossed, total = ops_cutting.cut_on_device(x, elements, node_slots, alive, faces, blade.vertices.to(x),
                                                   blade.triangles.to(device), limits, parents, scratch,
                                                   native=native)
        pairs = faces[0].long().cpu()
        if want is None:
            assert int(total) == 0 and not bool(crossed.any())
            continue
        total = int(total)
        assert torch.equal(elements.cpu().long(), want.elements)
        assert torch.equal(parents[used:used + total].cpu(), want.parents[used:])
        assert set(map(tuple, pairs[crossed.cpu()].tolist())) == set(
            map(tuple, torch.stack([want.cut_first, want.cut_second], 1).sort(1).values.tolist()))
        a, b = elements.cpu().long()[pairs[:, 0]], elements.cpu().long()[pairs[:, 1]]
        shared = (a[:, :, None] == b[:, None, :]).sum((1, 2)) == n - 1
        still = faces[2].cpu() & shared & alive.cpu()[pairs].all(1)
        assert set(map(tuple, pairs[still].tolist())) == set(map(tuple, want.slit.sort(1).values.tolist()))
        x[used:used + total] = x[parents[used:used + total]]
        want_elements, slit, used = want.elements, want.slit, used + total
    return used - num_nodes


@pytest.mark.parametrize("native", [True, False], ids=["op", "reference"])
@pytest.mark.parametrize("index,dtype", [(torch.int64, torch.float64), (torch.int32, torch.float32)],
                         ids=["int64-float64", "int32-float32"])
@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_the_cut_on_the_device_equals_the_reference_through_sequences_of_cuts(kind, index, dtype, native):
    mesh = MESHES[kind]()
    gen = torch.Generator().manual_seed(5)
    partial = plane_blade(0.51, 0.3) if kind == "tet" else cutting.Blade.swept((0.51, -1, -1), (0.51, 0.3, -1),
                                                                                (0.51, -1, 1), (0.51, 0.3, 1))
    blades = [partial, plane_blade(0.51), plane_blade(0.33, 0.35)] + [small_blade(gen) for _ in range(8)]
    added = device_cuts(mesh, blades, removed=(3, 11, 20), index=index, dtype=dtype, native=native, gen=gen)
    assert added > 10


def test_random_small_blades_leave_slits_and_equal_the_reference():
    gen = torch.Generator().manual_seed(3)
    for _ in range(3):
        device_cuts(tet_mesh(), [small_blade(gen) for _ in range(8)], removed=(7, 30))


def test_a_cut_on_the_device_with_no_room_changes_no_element():
    mesh = tet_mesh()
    elements = mesh.elements.clone()
    faces = ops_cutting.face_table(elements)
    node_slots = topology.incidence_table(elements.reshape(-1), torch.arange(elements.shape[0]).repeat_interleave(4),
                                          mesh.num_vertices + 4)
    x = torch.cat([mesh.vertices, mesh.vertices[:4]])
    parents = torch.arange(mesh.num_vertices + 4)
    alive = torch.ones(elements.shape[0], dtype=torch.bool)
    blade = plane_blade(0.51)
    crossed, total = ops_cutting.cut_on_device(x, elements, node_slots, alive, faces, blade.vertices, blade.triangles,
                                               torch.tensor([mesh.num_vertices, 4]), parents)
    assert int(total) > 4 and bool(crossed.any())
    assert torch.equal(elements, mesh.elements) and torch.equal(parents, torch.arange(mesh.num_vertices + 4))


def test_the_face_table_lists_each_interior_face_once_and_marks_a_slit_parted():
    mesh = tet_mesh()
    first, second, _ = cutting.interior_faces(mesh.elements)
    face_elements, element_faces, parted = ops_cutting.face_table(mesh.elements, torch.stack([second, first], 1)[:3])
    assert torch.equal(face_elements, torch.stack([first, second], 1))
    assert int(parted.sum()) == 3 and bool(parted[:3].all())
    for f, (a, b) in enumerate(face_elements.tolist()):
        assert f in element_faces[a].tolist() and f in element_faces[b].tolist()
        k = element_faces[a].tolist().index(f)  # the face opposite local node k of a: shared by b
        assert mesh.elements[a, k] not in mesh.elements[b].tolist()
    assert int((element_faces >= 0).sum()) == 2 * face_elements.shape[0]


def _device_args(name):
    args, _ = library.REGISTRY[name].example("cpu", torch.float64)
    return dict(zip([a.name for a in library.op(name)._schema.arguments], args))


@pytest.mark.parametrize("name,change,message", [
    (ops_cutting.CROSS_FACES, dict(alive=lambda a: a["alive"][1:]), "alive has shape"),
    (ops_cutting.CROSS_FACES, dict(blade_triangles=lambda a: a["blade_triangles"].int()), "blade_triangles is Int"),
    (ops_cutting.CROSS_FACES, dict(face_elements=lambda a: a["face_elements"].long()), "face_elements is Long"),
    (ops_cutting.SPLIT_STARS, dict(node_slots=lambda a: torch.cat([a["node_slots"]] * 20)), "at most 64 elements"),
    (ops_cutting.SPLIT_STARS, dict(group=lambda a: a["group"].long()), "group is Long; expected Int"),
    (ops_cutting.SPLIT_STARS, dict(parted=lambda a: a["parted"][1:]), "parted has shape"),
    (ops_cutting.REPOINT_STARS, dict(node_slots=lambda a: torch.cat([a["node_slots"]] * 20)), "at most 64 elements"),
    (ops_cutting.MOVE_LISTS, dict(node_slots=lambda a: torch.cat([a["node_slots"]] * 20)), "at most 64 elements"),
    (ops_cutting.REPOINT_STARS, dict(limits=lambda a: a["limits"][:1]), r"limits has shape \[1\]"),
    (ops_cutting.REPOINT_STARS, dict(elements=lambda a: a["elements"][:, :2].contiguous()), r"elements must be"),
    (ops_cutting.COUNT_NEW_NODES, dict(rows=lambda a: torch.zeros(3, dtype=torch.int64)), r"rows has shape \[3\]"),
    (ops_cutting.CLOSE_CUT, dict(incidences=lambda a: a["incidences"].long()), "incidences is Long"),
    (ops_cutting.CLOSE_CUT, dict(chunk_start=lambda a: a["chunk_start"].int()), "chunk_start is Int"),
])
def test_bad_arguments_of_the_device_passes_raise_naming_them_and_write_nothing(name, change, message):
    args = _device_args(name)
    for key, make in change.items():
        args[key] = make(args)
    before = {k: v.clone() for k, v in args.items() if isinstance(v, torch.Tensor)}
    with pytest.raises(RuntimeError, match=message):
        library.op(name)(*args.values())
    for k, v in before.items():
        assert torch.equal(args[k], v), k


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("room,chunk_slots", [(6, 11), (7, 11), (7, 10), (0, 100)])
def test_the_cut_is_counted_and_closed_as_the_references(device, room, chunk_slots):
    """Where the new nodes fit (or not), where a chunk holds more slots than given (or not), and
    with no chunk at all: the ops write what their references write."""
    incidences = torch.tensor([3, 4, 2, 5, 6], dtype=torch.int32, device=device)
    for chunk_start in (torch.tensor([0, 3, 5], device=device), torch.zeros(1, dtype=torch.int64, device=device)):
        written = []
        for count, close in [(library.op(ops_cutting.COUNT_NEW_NODES), library.op(ops_cutting.CLOSE_CUT)),
                             (ops_cutting._ref_cutting_count_new_nodes, ops_cutting._ref_cutting_close_cut)]:
            limits = torch.tensor([20, room], device=device)
            rows, outcome = torch.zeros(2, dtype=torch.int64, device=device), torch.zeros(2, dtype=torch.int64,
                                                                                          device=device)
            status = torch.zeros(1, dtype=torch.int32, device=device)
            count(torch.tensor([0, 2, 2, 3, 7], device=device), limits, rows, status)
            close(rows, incidences, chunk_start, chunk_slots, limits, status, outcome)
            written.append((rows, limits, status, outcome))
        for ours, want in zip(*written):
            assert torch.equal(ours, want)
        fits = room >= 7
        assert written[0][0].tolist() == [20, 7 if fits else 0]
        assert written[0][3].tolist() == [27 if fits else 20, int(not fits or (chunk_slots < 11 and chunk_start.numel() > 1))]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
@pytest.mark.parametrize("kind", ["tet", "membrane"])
def test_the_cut_on_cuda_equals_the_reference(kind):
    gen = torch.Generator().manual_seed(11)
    blades = [plane_blade(0.51, 0.3), plane_blade(0.51)] + [small_blade(gen) for _ in range(6)]
    for index, dtype in [(torch.int64, torch.float64), (torch.int32, torch.float32)]:
        device_cuts(MESHES[kind](), blades, removed=(3, 11), index=index, dtype=dtype, device="cuda", gen=gen)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_the_cut_on_cuda_runs_in_a_captured_graph():
    """The three passes and the prefix sum captured once, replayed for two blades (written into
    the captured blade buffer): the same elements as eager cuts."""
    mesh, device = tet_mesh(), torch.device("cuda")
    num_nodes, spare = mesh.num_vertices, 64

    def setup():
        elements = mesh.elements.to(device)
        x = torch.cat([mesh.vertices, mesh.vertices[:1].expand(spare, 3)]).to(device)
        node_slots = topology.incidence_table(elements.reshape(-1), torch.arange(
            elements.shape[0], device=device).repeat_interleave(4), num_nodes + spare)
        return dict(x=x, elements=elements, node_slots=node_slots,
                    alive=torch.ones(elements.shape[0], dtype=torch.bool, device=device),
                    faces=ops_cutting.face_table(elements), limits=torch.tensor([num_nodes, spare], device=device),
                    parents=torch.arange(num_nodes + spare, device=device))

    blades = [plane_blade(0.51, 0.3), plane_blade(0.71, 0.25)]
    eager, captured = setup(), setup()
    for blade in blades:
        ops_cutting.cut_on_device(**eager, blade_vertices=blade.vertices.to(device),
                                  blade_triangles=blade.triangles.to(device))
    vertices, triangles = blades[0].vertices.to(device).clone(), blades[0].triangles.to(device)
    scratch = {}
    ops_cutting.cut_on_device(**setup(), blade_vertices=vertices, blade_triangles=triangles, scratch=scratch)
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        ops_cutting.cut_on_device(**captured, blade_vertices=vertices, blade_triangles=triangles, scratch=scratch)
    for blade in blades:  # the node slots are not edited here: the second blade cuts elsewhere
        vertices.copy_(blade.vertices.to(device))
        graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(captured["elements"], eager["elements"])
    assert torch.equal(captured["parents"], eager["parents"])
