"""Where a node-graph CG matvec's time goes on an irregular graph: a standalone probe (CuPy,
NVRTC), one matvec kernel (Ap along r + 0.5 p, as the persistent CG's M phase reads it) per
variant, timed per launch, over the paper beam's node graph (``--graph``: an .npz of neighbor,
slot_edge, incidences, edges; its nodes alternate 10 and 26 slots) or a 14-neighbour stencil:

    layout     "blocks"  node_k [N_n, V, 3, 3] (the library's), "edges48" each edge's block once
               (48-byte rows, read through slot_edge, transposed for the edge's second node)
    lanes      threads per node (its slots split among them, the sums shuffled together)
    batch      slots whose loads a thread has in flight at once
    rows       (sort_slots, by_degree, permuted) orders: each node's slots by neighbour index; the
               threads of each 256-node block on its nodes by slot count; the slot arrays stored
               in that order (sliced ELL sorted by degree: the library's rows since session 9)
    persist    node_k marked persisting in L2 (driver API access policy window)

Each variant is checked against a float64 product in NumPy before it is timed. A probe for
deciding what to build, not a library path.

    python benchmarks/probes/node_k_layout_probe.py --graph paper_beam_graph.npz [--out FILE.json]   # GPU, cupy

The .npz comes from the CPU: node_graph.hooke_node_graph of step_bench.paper_beam("hooke", "cpu")'s
group (neighbor, incidences), and slot_edge / edges from its plan (index, force_index).
"""
from __future__ import annotations

import argparse
import json

import numpy as np

KERNEL = r"""
extern "C" __global__ void __launch_bounds__(256) matvec(
    const int* __restrict__ neighbor, const int* __restrict__ count, const float* __restrict__ node_k,
    const int* __restrict__ slot_edge, const float* __restrict__ p, const float* __restrict__ r,
    float* __restrict__ out, const int* __restrict__ order, int V) {
  const int t = blockIdx.x * blockDim.x + threadIdx.x;
  const int lane = t % LANES;
  const bool own = t / LANES < V;
  const int i = own ? __ldg(order + t / LANES) : V;
  const int row = ROWS_PERMUTED ? t / LANES : i;  // where the node's slots are stored
  const int n = own ? __ldg(count + row) : 0;
  float pi[3] = {0.f, 0.f, 0.f}, acc[3] = {0.f, 0.f, 0.f};
  if (own) for (int a = 0; a < 3; ++a) pi[a] = DIRECTION ? r[i * 3 + a] + 0.5f * p[i * 3 + a] : p[i * 3 + a];
  for (int s0 = lane; s0 < n; s0 += LANES * BATCH) {
    int j[BATCH], code[BATCH];
    float k[BATCH][9], pj[BATCH][3];
#pragma unroll
    for (int q = 0; q < BATCH; ++q) {
      const int s = s0 + q * LANES;
      j[q] = s < n ? __ldg(neighbor + (long)s * V + row) : i;
      code[q] = EDGES && s < n ? __ldg(slot_edge + (long)s * V + row) : 0;
    }
#pragma unroll
    for (int q = 0; q < BATCH; ++q) {
      const int s = s0 + q * LANES;
      if (s < n) {
#if EDGES == 48
        const bool first = code[q] >= 0;
        const float4* blk = reinterpret_cast<const float4*>(node_k + (long)(first ? code[q] : ~code[q]) * 12);
        const float4 v0 = __ldg(blk), v1 = __ldg(blk + 1), v2 = __ldg(blk + 2);
        const float v[9] = {v0.x, v0.y, v0.z, v0.w, v1.x, v1.y, v1.z, v1.w, v2.x};
#pragma unroll
        for (int a = 0; a < 3; ++a)
#pragma unroll
          for (int b = 0; b < 3; ++b) k[q][a * 3 + b] = first ? v[a * 3 + b] : v[b * 3 + a];
#elif EDGES == 36
        const bool first = code[q] >= 0;
        const float* blk = node_k + (long)(first ? code[q] : ~code[q]) * 9;
        float v[9];
#pragma unroll
        for (int e = 0; e < 9; ++e) v[e] = __ldg(blk + e);
#pragma unroll
        for (int a = 0; a < 3; ++a)
#pragma unroll
          for (int b = 0; b < 3; ++b) k[q][a * 3 + b] = first ? v[a * 3 + b] : v[b * 3 + a];
#else
#pragma unroll
        for (int e = 0; e < 9; ++e) {
#if PLANES
          k[q][e] = __ldg(node_k + ((long)s * 9 + e) * V + row);
#else
          k[q][e] = __ldg(node_k + ((long)s * V + row) * 9 + e);
#endif
        }
#endif
      }
#pragma unroll
      for (int a = 0; a < 3; ++a) pj[q][a] = DIRECTION ? r[j[q] * 3 + a] + 0.5f * p[j[q] * 3 + a] : p[j[q] * 3 + a];
    }
#pragma unroll
    for (int q = 0; q < BATCH; ++q) {
      if (s0 + q * LANES >= n) break;
      float w[3];
      for (int a = 0; a < 3; ++a) w[a] = pj[q][a] - pi[a];
#pragma unroll
      for (int a = 0; a < 3; ++a) acc[a] -= k[q][a * 3] * w[0] + k[q][a * 3 + 1] * w[1] + k[q][a * 3 + 2] * w[2];
    }
  }
#pragma unroll
  for (int o = LANES / 2; o > 0; o >>= 1)
    for (int a = 0; a < 3; ++a) acc[a] += __shfl_xor_sync(0xffffffffu, acc[a], o);
  if (own && lane == 0) for (int a = 0; a < 3; ++a) out[i * 3 + a] = acc[a];
}
"""


def grid_graph(nx=17, ny=17, nz=201):
    """A 14-neighbour stencil graph: neighbor and slot_edge [S, V] int32 (slot-major; slot_edge
    g, or ~g where the node is the edge's second), incidences [V], edges [E, 2]."""
    offsets = [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)]
    V = nx * ny * nz
    idx = np.arange(V).reshape(nz, ny, nx)
    z, y, x = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    edges = []
    for dx, dy, dz in offsets:
        ok = (x + dx < nx) & (y + dy < ny) & (z + dz < nz)
        edges.append(np.stack([idx[ok], idx[np.minimum(z + dz, nz - 1), np.minimum(y + dy, ny - 1),
                                            np.minimum(x + dx, nx - 1)][ok]], 1))
    return slots_of(np.concatenate(edges).astype(np.int32), V)


def slots_of(edges, V):
    S = int(np.bincount(edges.ravel(), minlength=V).max())
    neighbor = np.full((S, V), -1, np.int32)
    slot_edge = np.zeros((S, V), np.int32)
    count = np.zeros(V, np.int32)
    for e, (a, b) in enumerate(edges):
        neighbor[count[a], a], slot_edge[count[a], a] = b, e
        count[a] += 1
        neighbor[count[b], b], slot_edge[count[b], b] = a, ~e
        count[b] += 1
    return dict(neighbor=neighbor, slot_edge=slot_edge, incidences=count, edges=edges)


def main():

    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None)
    ap.add_argument("--graph", default=None, help="an .npz of neighbor, slot_edge, incidences, edges (else the stencil)")
    ap.add_argument("--repeats", type=int, default=300)
    args = ap.parse_args()
    g = dict(np.load(args.graph)) if args.graph else grid_graph()
    records = []
    orders = [(False, False, False, False), (False, True, False, False), (False, True, True, False),
              (True, True, True, False), (False, False, False, True)]
    for sort_slots, by_degree, permuted, persist in orders:
        records += run(g, sort_slots, by_degree, args.repeats, persist=persist, permuted=permuted)
    if args.out:
        with open(args.out, "w") as f:
            json.dump(records, f, indent=1)


def persisting_window(stream, buffer, nbytes):
    """Marks ``nbytes`` of ``buffer`` (a CuPy array) as persisting in L2 for kernels on ``stream``
    (driver API: the L2 set-aside at its maximum, an access policy window on the stream);
    nbytes = 0 resets. Returns (set-aside bytes, window bytes, hit ratio)."""
    import ctypes

    import cupy as cp

    cuda = ctypes.CDLL("libcuda.so.1")
    attr = cp.cuda.runtime.deviceGetAttribute
    max_persist = attr(108, 0)  # cudaDevAttrMaxPersistingL2CacheSize
    max_window = attr(109, 0)   # cudaDevAttrMaxAccessPolicyWindowSize
    assert cuda.cuCtxSetLimit(ctypes.c_int(0x06), ctypes.c_size_t(max_persist if nbytes else 0)) == 0
    window = min(nbytes, max_window)
    ratio = min(1.0, max_persist / window) if window else 0.0

    class Window(ctypes.Structure):
        _fields_ = [("base_ptr", ctypes.c_void_p), ("num_bytes", ctypes.c_size_t), ("hitRatio", ctypes.c_float),
                    ("hitProp", ctypes.c_int), ("missProp", ctypes.c_int), ("pad", ctypes.c_char * 36)]

    value = Window(ctypes.c_void_p(buffer.data.ptr), window, ratio, 2 if window else 0, 1 if window else 0)
    assert cuda.cuStreamSetAttribute(ctypes.c_void_p(stream.ptr), ctypes.c_int(1), ctypes.byref(value)) == 0
    if not nbytes:
        assert cuda.cuCtxResetPersistingL2Cache() == 0
    return max_persist, window, ratio


def run(g, sort_slots, by_degree, repeats, persist=False, permuted=False):
    """The variants over graph g: its slots sorted by neighbour index (sort_slots), its nodes
    taken by the threads of each 256-node block in decreasing slot count (by_degree) and their
    slots stored in that order (permuted: sliced ELL sorted by degree), the slot blocks persisting
    in L2 (persist)."""
    import cupy as cp

    stream = cp.cuda.Stream(non_blocking=True)
    stream.use()
    neighbor, slot_edge, count, edges = g["neighbor"], g["slot_edge"], g["incidences"], g["edges"]
    S, V = neighbor.shape
    if sort_slots:  # each node's used slots in increasing neighbour index
        key = np.where(np.arange(S)[:, None] < count[None, :], neighbor, np.iinfo(np.int32).max)
        perm = np.argsort(key, axis=0, kind="stable")
        neighbor = np.take_along_axis(neighbor, perm, 0)
        slot_edge = np.take_along_axis(slot_edge, perm, 0)
    order = np.arange(V, dtype=np.int32)
    if by_degree:
        for b0 in range(0, V, 256):
            seg = order[b0:b0 + 256]
            order[b0:b0 + 256] = seg[np.argsort(-count[seg], kind="stable")]
    E = edges.shape[0]
    rng = np.random.default_rng(0)
    edge_k = rng.standard_normal((E, 3, 3)).astype(np.float32)
    used = np.arange(S)[:, None] < count[None, :]
    code = np.where(used, slot_edge, 0)
    first = code >= 0
    kdir = np.where(first[..., None, None], edge_k[np.where(first, code, ~code)],
                    edge_k[np.where(first, code, ~code)].transpose(0, 1, 3, 2)) * used[..., None, None]
    node_k = np.ascontiguousarray(kdir.astype(np.float32))  # [S, V, 3, 3]
    p = rng.standard_normal((V, 3)).astype(np.float32)
    r = rng.standard_normal((V, 3)).astype(np.float32)
    safe = np.where(used, neighbor, 0)
    want = {}
    for direction in (0, 1):
        field = (r + np.float32(0.5) * p) if direction else p
        w = (field[safe] - field[None]).astype(np.float64) * used[..., None]
        want[direction] = -np.einsum("svab,svb->va", node_k.astype(np.float64), w)
    d = {k: cp.asarray(v) for k, v in dict(neighbor=neighbor, count=count, slot_edge=slot_edge, p=p, r=r,
                                           order=order).items()}
    padded = np.zeros((E, 12), np.float32)
    padded[:, :9] = edge_k.reshape(E, 9)
    rows = order if permuted else np.arange(V)
    d["neighbor"] = cp.asarray(np.ascontiguousarray(neighbor[:, rows]))
    d["slot_edge"] = cp.asarray(np.ascontiguousarray(slot_edge[:, rows]))
    d["count"] = cp.asarray(count[rows])
    layouts = {"blocks": (cp.asarray(np.ascontiguousarray(node_k[:, rows])), dict(PLANES=0, EDGES=0)),
               "edges48": (cp.asarray(padded), dict(PLANES=0, EDGES=48))}
    print(f"V {V}, slots {S} (mean {count.mean():.2f}), edges {E}; node_k used {count.sum() * 36 / 1e6:.1f} MB, "
          f"edge blocks {E * 36 / 1e6:.1f} MB (48-byte: {E * 48 / 1e6:.1f})", flush=True)
    records = []
    variants = [(layout, lanes, batch, 1) for layout in layouts for lanes in (1, 2) for batch in (2, 4)]
    for layout, lanes, batch, direction in variants:
        d_k, flags = layouts[layout]
        opts = tuple(f"-D{k}={v}" for k, v in dict(LANES=lanes, BATCH=batch, DIRECTION=direction,
                                                    ROWS_PERMUTED=int(permuted), **flags).items())
        kernel = cp.RawKernel(KERNEL, "matvec", options=opts)
        out = cp.zeros((V, 3), cp.float32)
        blocks = (V * lanes + 255) // 256
        window = persisting_window(stream, d_k, d_k.nbytes if persist else 0)
        call = lambda: kernel((blocks,), (256,), (d["neighbor"], d["count"], d_k, d["slot_edge"], d["p"], d["r"],  # noqa: E731
                                                 out, d["order"], np.int32(V)))
        call()
        err = float(np.abs(cp.asnumpy(out) - want[direction]).max() / np.abs(want[direction]).max())
        for _ in range(20):
            call()
        start, stop = cp.cuda.Event(), cp.cuda.Event()
        start.record(stream)
        for _ in range(repeats):
            call()
        stop.record(stream)
        stop.synchronize()
        us = cp.cuda.get_elapsed_time(start, stop) * 1e3 / repeats
        rec = dict(sort_slots=sort_slots, by_degree=by_degree, permuted=permuted, persist=window, layout=layout, lanes=lanes, batch=batch, direction=direction,
                   registers=kernel.attributes["num_regs"], rel_err=err, us=us)
        records.append(rec)
        print(f"sorted slots {int(sort_slots)} by degree {int(by_degree)} permuted {int(permuted)} L2 {window[1]} {layout:8s} lanes {lanes} batch {batch} dir {direction}: {us:7.2f} us  regs {rec['registers']}  "
              f"err {err:.1e}", flush=True)
    return records


if __name__ == "__main__":
    main()
