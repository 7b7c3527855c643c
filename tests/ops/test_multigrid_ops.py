"""The multigrid op family (csrc/multigrid/, ops/multigrid.py): the block-sparse product and the
Chebyshev step against their pure-torch references and a dense product (float64), for every
block shape and on rows of many and of few blocks (the lane groups of the CUDA kernel), on the
CPU extension and CUDA; deterministic; the aliasing rules and bad inputs. The heavy-edge matching
against its reference, its clusters within their size; the rigid transfers against the dense
basis."""
import numpy as np
import pytest
import scipy.sparse as sp
import torch

from tensormass_torch import _backend
from tensormass_torch.ops import library
from tensormass_torch.ops.multigrid import (
    BsrMatrix,
    bsr_gemv,
    chebyshev,
    incident_lists,
    match_clusters,
    rigid_prolong,
    rigid_restrict,
)

BLOCKS = [(6, 6), (3, 6), (6, 3), (3, 3), (2, 3), (3, 2), (2, 2), (1, 1)]
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def native(device):
    if not (_backend.use_extension(torch.device(device)) and library.ensure_registered()):
        pytest.skip(f"the extension does not serve {device}")
    return torch.ops.tensormass


def random_bsr(block, block_rows, block_cols, per_row, seed, device, dtype=torch.float64):
    """A random BSR matrix with about ``per_row`` blocks a block row (some rows empty)."""
    rng = np.random.default_rng(seed)
    density = min(1.0, per_row / block_cols)
    pattern = sp.random(block_rows, block_cols, density=density, random_state=rng, format="csr")
    pattern.data[:] = 1.0
    pattern = pattern.tolil()
    pattern[0, :] = 0  # an empty block row
    dense = sp.kron(pattern.tocsr(), np.ones(block)).toarray() * rng.standard_normal(
        (block_rows * block[0], block_cols * block[1]))
    matrix = sp.csr_matrix(dense)
    return BsrMatrix.from_scipy(matrix, block, dtype, device), torch.from_numpy(dense).to(device=device, dtype=dtype)


def vec(n, seed, device, dtype=torch.float64):
    gen = torch.Generator().manual_seed(seed)
    return torch.randn(n, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("block", BLOCKS)
@pytest.mark.parametrize("per_row", [2, 6, 40])
def test_gemv_matches_the_dense_product_and_the_reference(device, block, per_row):
    ops = native(device)
    matrix, dense = random_bsr(block, 37, 45, per_row, seed=per_row, device=device)
    x, y = vec(45 * block[1], 1, device), vec(37 * block[0], 2, device)
    out = torch.full_like(y, float("nan"))
    ops.multigrid_bsr_gemv(*matrix.arrays(), x, y, -1.5, 0.25, out)
    expected = -1.5 * dense @ x + 0.25 * y
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    ref = torch.empty_like(y)
    library.REGISTRY["multigrid_bsr_gemv"].reference(*matrix.arrays(), x, y, -1.5, 0.25, ref)
    torch.testing.assert_close(out, ref, rtol=1e-12, atol=1e-12)
    # without y; the same inputs give the same bits (fixed order of sums)
    again = torch.empty_like(y)
    ops.multigrid_bsr_gemv(*matrix.arrays(), x, None, 2.0, 0.0, again)
    torch.testing.assert_close(again, 2.0 * dense @ x, rtol=1e-12, atol=1e-12)
    twice = torch.empty_like(y)
    ops.multigrid_bsr_gemv(*matrix.arrays(), x, None, 2.0, 0.0, twice)
    assert torch.equal(again, twice)


@pytest.mark.parametrize("device", DEVICES)
def test_gemv_adds_in_place_and_float32(device):
    ops = native(device)
    matrix, dense = random_bsr((3, 6), 20, 8, 3, seed=4, device=device)
    e, x = vec(48, 5, device), vec(60, 6, device)
    expected = x + dense @ e
    ops.multigrid_bsr_gemv(*matrix.arrays(), e, x, 1.0, 1.0, x)  # out is y: x += P e
    torch.testing.assert_close(x, expected, rtol=1e-12, atol=1e-12)
    single = BsrMatrix(matrix.values.float(), matrix.block_cols, matrix.row_ptr, matrix.block_rows, matrix.shape)
    out = torch.empty(60, dtype=torch.float32, device=device)
    ops.multigrid_bsr_gemv(*single.arrays(), e.float(), None, 1.0, 0.0, out)
    torch.testing.assert_close(out, (dense @ e).float(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("block", [(6, 6), (3, 3), (2, 2), (1, 1)])
def test_chebyshev_step_matches_its_definition(device, block):
    """r = b - A x (the matrix, or its product given, or x = 0), step = a step + c D^-1 r,
    x_out = x + step; the op equals its reference."""
    ops = native(device)
    matrix, dense = random_bsr(block, 30, 30, 12, seed=7, device=device)
    n = 30 * block[0]
    b, x, dinv, old = vec(n, 8, device), vec(n, 9, device), vec(n, 10, device).abs(), vec(n, 11, device)
    a, c = 0.4, 0.9
    expected_step = a * old + c * dinv * (b - dense @ x)
    for how in ("matrix", "product", "zero"):
        step, x_out = old.clone(), torch.full_like(b, float("nan"))
        if how == "matrix":
            ops.multigrid_chebyshev(*matrix.arrays(), None, b, dinv, x, step, x_out, a, c)
            want_step, want_x = expected_step, x + expected_step
        elif how == "product":
            ops.multigrid_chebyshev(None, None, None, dense @ x, b, dinv, x, step, x_out, a, c)
            want_step, want_x = expected_step, x + expected_step
        else:  # the first step from x = 0: step's old values are not read (a = 0)
            step.fill_(float("nan"))
            ops.multigrid_chebyshev(None, None, None, None, b, dinv, None, step, x_out, 0.0, c)
            want_step = c * dinv * b
            want_x = want_step
        torch.testing.assert_close(step, want_step, rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(x_out, want_x, rtol=1e-12, atol=1e-12)
    # the group-level call with the product updates x in place
    step, x_in = old.clone(), x.clone()
    chebyshev(b, dinv, step, x_in, a, c, x=x_in, product=dense @ x)
    torch.testing.assert_close(x_in, x + expected_step, rtol=1e-12, atol=1e-12)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_the_cpu():
    for block, per_row in (((6, 6), 50), ((3, 6), 4), ((6, 3), 100)):
        outs = []
        for device in ("cpu", "cuda"):
            native(device)
            matrix, _ = random_bsr(block, 60, 70, per_row, seed=12, device=device)
            x = vec(70 * block[1], 13, device)
            outs.append(bsr_gemv(matrix, x).cpu())
        torch.testing.assert_close(outs[1], outs[0], rtol=1e-12, atol=1e-12)


def test_bad_inputs_raise_naming_the_argument():
    ops = native("cpu")
    matrix, _ = random_bsr((3, 3), 4, 4, 2, seed=1, device="cpu")
    x, out = vec(12, 1, "cpu"), torch.zeros(12, dtype=torch.float64)
    with pytest.raises(RuntimeError, match="block_cols"):
        ops.multigrid_bsr_gemv(matrix.values, matrix.block_cols.long(), matrix.row_ptr, x, None, 1.0, 0.0, out)
    with pytest.raises(RuntimeError, match="out must not be x"):
        ops.multigrid_bsr_gemv(*matrix.arrays(), x, None, 1.0, 0.0, x)
    with pytest.raises(RuntimeError, match="out has shape"):
        ops.multigrid_bsr_gemv(*matrix.arrays(), x, None, 1.0, 0.0, torch.zeros(9, dtype=torch.float64))
    with pytest.raises(RuntimeError, match="values is Float"):
        ops.multigrid_bsr_gemv(matrix.values.float(), matrix.block_cols, matrix.row_ptr, x, None, 1.0, 0.0, out)
    odd, _ = random_bsr((3, 3), 4, 4, 2, seed=1, device="cpu")
    with pytest.raises(RuntimeError, match="unsupported block shape 4 x 3"):
        ops.multigrid_bsr_gemv(torch.zeros(odd.values.shape[0], 4, 3, dtype=torch.float64), odd.block_cols,
                               odd.row_ptr, x, None, 1.0, 0.0, torch.zeros(16, dtype=torch.float64))
    step = torch.zeros(12, dtype=torch.float64)
    with pytest.raises(RuntimeError, match="x_out must not be x"):
        ops.multigrid_chebyshev(*matrix.arrays(), None, x, x.abs(), x, step, x, 0.5, 0.5)
    with pytest.raises(RuntimeError, match="not both"):
        ops.multigrid_chebyshev(*matrix.arrays(), x, x, x.abs(), x, step, out, 0.5, 0.5)
    with pytest.raises(RuntimeError, match="without x"):
        ops.multigrid_chebyshev(None, None, None, x, x, x.abs(), None, step, out, 0.5, 0.5)
    with pytest.raises(RuntimeError, match="inverse_diagonal has shape"):
        ops.multigrid_chebyshev(None, None, None, None, x, x[:6].abs(), None, step, out, 0.0, 0.5)


def spd_blocks(n, d, seed, device, dtype):
    """``[n, d, d]`` symmetric blocks, every fifth one not positive definite (its negative)."""
    gen = torch.Generator().manual_seed(seed)
    half = torch.randn(n, d, d, generator=gen, dtype=torch.float64)
    blocks = half @ half.transpose(-1, -2) + 0.05 * torch.eye(d, dtype=torch.float64)
    blocks[::5] = -blocks[::5]
    return blocks.to(device=device, dtype=dtype)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_block_cholesky_matches_its_reference_and_factors_the_blocks(device, d, dtype):
    """S = L^-T, S^T and S^-1 = L^T of each block: the reference's (to rounding), S^T B S = I and
    S S^-1 = I where the block is positive definite, the identity where it is not."""
    ops = native(device)
    blocks = spd_blocks(50, d, seed=d, device=device, dtype=dtype)
    outputs = [torch.full_like(blocks, float("nan")) for _ in range(3)]
    ops.multigrid_block_cholesky(blocks, *outputs)
    expected = [torch.empty_like(blocks) for _ in range(3)]
    library.REGISTRY["multigrid_block_cholesky"].reference(blocks, *expected)
    tol = dict(rtol=1e-5, atol=1e-5) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    for ours, theirs in zip(outputs, expected):
        torch.testing.assert_close(ours, theirs, **tol)
    scale, scale_t, inverse = (t.double() for t in outputs)
    eye = torch.eye(d, dtype=torch.float64, device=device).expand(50, d, d)
    positive = torch.ones(50, dtype=torch.bool, device=device)
    positive[::5] = False
    torch.testing.assert_close(scale_t, scale.transpose(-1, -2))
    torch.testing.assert_close((scale_t @ blocks.double() @ scale)[positive], eye[positive], **tol)
    torch.testing.assert_close(scale @ inverse, eye, **tol)
    for t in (scale, scale_t, inverse):
        assert torch.equal(t[~positive], eye[~positive])


@pytest.mark.parametrize("device", DEVICES)
def test_block_cholesky_bad_arguments_raise_naming_them_and_write_nothing(device):
    ops = native(device)
    blocks = spd_blocks(6, 3, seed=1, device=device, dtype=torch.float64)
    outputs = [torch.full_like(blocks, -7.0) for _ in range(3)]
    for args, match in [((blocks[:, :2], *outputs), "blocks"),
                        ((spd_blocks(6, 4, 1, device, torch.float64), *outputs), "blocks"),
                        ((blocks, outputs[0][:5], *outputs[1:]), "scale"),
                        ((blocks, outputs[0], outputs[1].float(), outputs[2]), "scale_t"),
                        ((blocks, outputs[0], outputs[1], outputs[0]), "different"),
                        ((blocks, blocks, *outputs[1:]), "different")]:
        with pytest.raises(RuntimeError, match=match):
            ops.multigrid_block_cholesky(*args)
    assert all(bool((t == -7.0).all()) for t in outputs)


def random_graph(nodes, edges, seed, device, loops=True):
    """(keys ``[E]``, ends ``[E, 2]``) of a random graph with distinct keys, with a few edges from a
    node to itself (which never join) and repeated weights (ties broken by the keys' low bits)."""
    gen = torch.Generator().manual_seed(seed)
    ends = torch.randint(0, nodes, (edges, 2), generator=gen)
    if loops:
        ends[::17, 1] = ends[::17, 0]
    weights = torch.randint(0, 4, (edges,), generator=gen)
    keys = weights * (1 << 31) + torch.randperm(edges, generator=gen)
    return keys.to(device), ends.to(device)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("most", [2, 5, 32])
def test_match_clusters_matches_its_reference_and_keeps_the_size(device, most):
    """The op's clusters are the reference's; each cluster holds at most ``most`` nodes, is labelled
    by its smallest node and is joined by the graph's edges; with rounds enough every edge
    between two clusters that fit beside each other has been taken."""
    native(device)
    for seed, (nodes, edges) in enumerate([(40, 60), (300, 1200), (1000, 2500)]):
        keys, ends = random_graph(nodes, edges, seed, device)
        label = match_clusters(keys, ends, nodes, most, rounds=12)
        ptr, incident = incident_lists(ends, nodes)
        expected = torch.full((nodes,), -1, dtype=torch.int64, device=device)
        library.REGISTRY["multigrid_match_clusters"].reference(keys, ends, ptr, incident, most, 12, expected, None)
        assert torch.equal(label, expected)
        size = torch.bincount(label, minlength=nodes)
        assert int(size.max()) <= most and int(size.sum()) == nodes
        smallest = torch.full((nodes,), nodes, device=device).scatter_reduce(0, label, torch.arange(nodes, device=device),
                                                                              "amin")
        assert torch.equal(smallest[label], label)
        assert int((size > 1).sum()) > 0
        done = match_clusters(keys, ends, nodes, most, rounds=200)
        cu, cv = done[ends[:, 0]], done[ends[:, 1]]
        grown = torch.bincount(done, minlength=nodes)
        assert not bool(((cu != cv) & (grown[cu] + grown[cv] <= most)).any())


def test_match_clusters_takes_the_heaviest_edges_first():
    """A path 0-1-2-3 whose middle edge is heaviest, clusters of two: {1, 2} and the ends alone."""
    native("cpu")
    ends = torch.tensor([[0, 1], [1, 2], [2, 3]])
    keys = torch.tensor([1, 5, 2]) * (1 << 31) + torch.arange(3)
    assert match_clusters(keys, ends, 4, 2, rounds=4).tolist() == [0, 1, 1, 3]
    assert match_clusters(keys, ends, 4, 4, rounds=4).tolist() == [0, 0, 0, 0]
    assert match_clusters(keys, ends, 4, 4, rounds=0).tolist() == [0, 1, 2, 3]
    assert match_clusters(keys[:0], ends[:0], 4, 4, rounds=4).tolist() == [0, 1, 2, 3]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_match_clusters_cuda_matches_the_cpu():
    labels = []
    for device in ("cpu", "cuda"):
        native(device)
        keys, ends = random_graph(5000, 20000, 3, device)
        labels.append(match_clusters(keys, ends, 5000, 32, rounds=12).cpu())
    assert torch.equal(labels[0], labels[1])


@pytest.mark.parametrize("device", DEVICES)
def test_match_clusters_bad_arguments_raise_naming_them_and_write_nothing(device):
    ops = native(device)
    keys, ends = random_graph(10, 20, 1, device)
    ptr, incident = incident_lists(ends, 10)
    label = torch.full((10,), -7, dtype=torch.int64, device=device)
    work = torch.zeros(6, 10, dtype=torch.int64, device=device)
    for args, match in [((keys.int(), ends, ptr, incident, 3, 4, label, work), "edge_keys"),
                        ((keys, ends[:5], ptr, incident, 3, 4, label, work), "edge_ends"),
                        ((keys, ends, ptr[:5], incident, 3, 4, label, work), "incident_ptr"),
                        ((keys, ends, ptr, incident[:5], 3, 4, label, work), "incident_edges"),
                        ((keys, ends, ptr, incident, 0, 4, label, work), "most"),
                        ((keys, ends, ptr, incident, 3, -1, label, work), "rounds"),
                        ((keys, ends, ptr, incident, 3, 4, label, work[:5]), "work"),
                        ((keys, ends, ptr, incident, 3, 4, label.float(), work), "label")]:
        with pytest.raises(RuntimeError, match=match):
            ops.multigrid_match_clusters(*args)
    assert bool((label == -7).all())


def rigid_nodes(bodies, seed, device, dtype=torch.float64):
    """(node_inverse ``[V, 3, 3]``, arm ``[V, 3]``, body_ptr ``[B + 1]`` int32, node_body ``[V]`` int32)
    for bodies of 0 to 60 nodes, the first body empty, a few nodes' N zero (fixed nodes)."""
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.randint(1, 60, (bodies,), generator=gen)
    lengths[0] = 0
    nodes = int(lengths.sum())
    node_inverse = torch.randn(nodes, 3, 3, generator=gen, dtype=torch.float64)
    node_inverse[::7] = 0.0
    arm = torch.randn(nodes, 3, generator=gen, dtype=torch.float64)
    body_ptr = torch.cat([torch.zeros(1, dtype=torch.int64), torch.cumsum(lengths, 0)]).int()
    node_body = torch.repeat_interleave(torch.arange(bodies), lengths).int()
    return (node_inverse.to(device, dtype), arm.to(device, dtype), body_ptr.to(device), node_body.to(device))


def dense_basis(node_inverse, arm, node_body, bodies):
    """Z' ``[3 V, 6 B]``: Z'_i = N_i [I | -[a_i]x] in body b's six columns."""
    nodes = arm.shape[0]
    ax, ay, az = arm.double().unbind(-1)
    zero, one = torch.zeros_like(ax), torch.ones_like(ax)
    z = torch.stack([torch.stack([one, zero, zero, zero, az, -ay], -1),
                     torch.stack([zero, one, zero, -az, zero, ax], -1),
                     torch.stack([zero, zero, one, ay, -ax, zero], -1)], 1)  # [V, 3, 6]
    local = node_inverse.double()[:, None, None] * z if node_inverse.dim() == 1 else node_inverse.double() @ z
    out = torch.zeros(3 * nodes, 6 * bodies, dtype=torch.float64, device=arm.device)
    for i in range(nodes):
        b = int(node_body[i])
        out[3 * i:3 * i + 3, 6 * b:6 * b + 6] = local[i]
    return out


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("form", ["blocks", "scalar"])
def test_rigid_transfers_are_the_dense_basis_products(device, dtype, form):
    """The restriction is Z'^T r and the prolongation r + w Z' c for the dense Z' (column k of a
    rotation: e_k x a), N_i a 3 x 3 block or a value a node (n_i I: the free mask's form, here with
    other values too), in both dtypes; the references agree."""
    native(device)
    node_inverse, arm, body_ptr, node_body = rigid_nodes(12, 3, device, dtype)
    if form == "scalar":
        node_inverse = node_inverse[:, 0, 0].contiguous()
    basis = dense_basis(node_inverse, arm, node_body, 12)
    r, c = vec(basis.shape[0], 4, device, dtype), vec(basis.shape[1], 5, device, dtype)
    tol = dict(rtol=1e-5, atol=1e-4) if dtype == torch.float32 else dict(rtol=1e-12, atol=1e-12)
    restricted = rigid_restrict(node_inverse, arm, body_ptr, r)
    torch.testing.assert_close(restricted.double(), basis.T @ r.double(), **tol)
    prolonged = rigid_prolong(node_inverse, arm, node_body, c, r, 0.5)
    torch.testing.assert_close(prolonged.double(), r.double() + 0.5 * basis @ c.double(), **tol)
    torch.testing.assert_close(rigid_prolong(node_inverse, arm, node_body, c).double(), basis @ c.double(), **tol)
    in_place = r.clone()
    rigid_prolong(node_inverse, arm, node_body, c, in_place, 0.5, out=in_place)
    torch.testing.assert_close(in_place, prolonged, rtol=0, atol=0)
    for name, args in (("multigrid_rigid_restrict", (node_inverse, arm, body_ptr, r)),
                       ("multigrid_rigid_prolong", (node_inverse, arm, node_body, c, r, 0.5))):
        out = torch.empty(restricted.shape if name.endswith("restrict") else prolonged.shape, dtype=dtype, device=device)
        library.REGISTRY[name].reference(*args, out)
        torch.testing.assert_close(out, restricted if name.endswith("restrict") else prolonged, **tol)


@pytest.mark.parametrize("device", DEVICES)
def test_rigid_transfers_bad_arguments_raise_naming_them_and_write_nothing(device):
    ops = native(device)
    node_inverse, arm, body_ptr, node_body = rigid_nodes(4, 1, device)
    nodes = arm.shape[0]
    r, c = vec(3 * nodes, 1, device), vec(24, 2, device)
    out_c, out_r = torch.full((24,), -7.0, dtype=torch.float64, device=device), torch.full_like(r, -7.0)
    for args, match in [((node_inverse[:, :2], arm, body_ptr, r, out_c), "node_inverse"),
                        ((node_inverse[:, :, 0], arm, body_ptr, r, out_c), "node_inverse"),
                        ((node_inverse, arm[:-1], body_ptr, r, out_c), "arm"),
                        ((node_inverse, arm, body_ptr.long(), r, out_c), "range_ptr"),
                        ((node_inverse, arm, body_ptr, r[:-1], out_c), "r"),
                        ((node_inverse, arm, body_ptr, r, out_c[:-6]), "out"),
                        ((node_inverse, arm.float(), body_ptr, r, out_c), "arm")]:
        with pytest.raises(RuntimeError, match=match):
            ops.multigrid_rigid_restrict(*args)
    for args, match in [((node_inverse, arm, node_body.long(), c, r, 0.5, out_r), "node_body"),
                        ((node_inverse, arm, node_body, c[:-1], r, 0.5, out_r), "coarse"),
                        ((node_inverse, arm, node_body, c, r[:-3], 0.5, out_r), "r"),
                        ((node_inverse, arm, node_body, c, r, 0.5, out_r[:-3]), "out")]:
        with pytest.raises(RuntimeError, match=match):
            ops.multigrid_rigid_prolong(*args)
    assert bool((out_c == -7.0).all()) and bool((out_r == -7.0).all())
