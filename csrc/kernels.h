// Per-item kernel bodies shared by the CPU (at::parallel_for) and CUDA (one thread per item)
// implementations: load one element (or edge, or node), call the element math of
// element_math.h, write the result. Each body is a small functor with a host/device
// `operator()(int64_t item)`; cpu/ and cuda/ only decide how the items are iterated.
//
// The paper's Algorithm 1, no atomics:
//   kernel 1 (one thread per element e): partial force on each local node v written to
//            PartialForce[ForceIndex[e][v]][index[e][v]]   (padded buffer [N_n, V, d])
//            or, for the element-level ops, to out[e][v]    (compact [N, n, d]);
//   kernel 2 (one thread per node i): TotalForce[i] = (node term) + sum_{s < incidences[i]}
//            PartialForce[s][i]: every slot it reads was written once, in a fixed order, so
//            the result is bitwise reproducible and the unused slots are never read (the
//            buffer is allocated uninitialised).
// The hooke tensor form's CG matvec also has a one-kernel variant (NodeHookeSystemKernel): one
// thread per node reads its slots' neighbours and edge tensors and sums the same terms in the
// same slot order, bitwise equal to kernels 1 + 2, without the PartialForce round trip.
//
// Layouts (all row-major contiguous, as the Python groups store them):
//   u, du [V, D]; elements / force_index [N, NN] (int32 or int64); shape_vectors [N, NN, D];
//   measure, lam, mu [N]; projector [N, D, D]; PartialForce [N_n, V, D]; out [V, D];
//   corotational: rest element nodes [N, NN, 3], rotations [N, D, D].
// The per-element blocks (shape vectors, indices, projector) are contiguous per element, so a
// thread reads its own contiguous bytes; on the GPU they are read with 16-byte vector loads when
// aligned (see load_block). PartialForce [N_n, V, D] makes kernel 2 coalesced: the threads of a
// warp read consecutive nodes of one slot.
#pragma once

#include <cstdint>
#include <cstring>

#include "element_math.h"

namespace tensormass {

// Read-only load: through the read-only data cache on the GPU.
template <typename T>
TM_HD T ld(const T* p) {
#if defined(__CUDA_ARCH__)
  return __ldg(p);
#else
  return *p;
#endif
}

struct Loader {
  template <typename T>
  TM_HD T operator()(const T* p) const { return ld(p); }
};

// Load 16 bytes (16 / sizeof(T) values) from a 16-byte aligned p: one vector load on the GPU.
template <typename T>
TM_HD void load16(const T* p, T* out) {
#if defined(__CUDA_ARCH__)
  const int4 v = __ldg(reinterpret_cast<const int4*>(p));
  const T* t = reinterpret_cast<const T*>(&v);
  TM_UNROLL for (int k = 0; k < int(16 / sizeof(T)); ++k) out[k] = t[k];
#else
  std::memcpy(out, p, 16);
#endif
}

// Load K contiguous values starting at p into out: with 16-byte loads when K * sizeof(T) is a
// multiple of 16 and p is 16-byte aligned (a runtime check, uniform across a warp for the
// per-element blocks of contiguous tensors), else one value at a time. The same path runs on
// the CPU (memcpy), so the CPU tests exercise its indexing.
template <int K, typename T>
TM_HD void load_block(const T* p, T (&out)[K]) {
  constexpr int kPer = int(16 / sizeof(T));
  if ((K * sizeof(T)) % 16 == 0 && (reinterpret_cast<uintptr_t>(p) & 15) == 0) {
    TM_UNROLL for (int i = 0; i < K / kPer; ++i) load16<T>(p + i * kPer, out + i * kPer);
    return;
  }
  TM_UNROLL for (int k = 0; k < K; ++k) out[k] = ld(p + k);
}

template <int NN, int D, typename T>
TM_HD void load_matrix(const T* p, T (&out)[NN][D]) {
  T flat[NN * D];
  load_block<NN * D, T>(p, flat);
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int a = 0; a < D; ++a) out[j][a] = flat[j * D + a];
  }
}

// Gather the D-vectors of the NN nodes idx[] from a [V, D] field.
template <int NN, int D, typename S, typename I>
TM_HD void gather_nodes(const S* field, const I (&idx)[NN], S (&out)[NN][D]) {
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    const S* p = field + static_cast<int64_t>(idx[j]) * D;
    TM_UNROLL for (int a = 0; a < D; ++a) out[j][a] = ld(p + a);
  }
}

// Where kernel 1 writes: compact [N, NN, D] (element-level ops) or padded [N_n, V, D].
template <int NN, int D, typename S, typename I, bool PADDED>
struct Writer;

template <int NN, int D, typename S, typename I>
struct Writer<NN, D, S, I, false> {
  S* out;
  TM_HD void operator()(int64_t e, const I (&)[NN], const S (&f)[NN][D]) const {
    S* p = out + e * (NN * D);
    TM_UNROLL for (int j = 0; j < NN; ++j) {
      TM_UNROLL for (int a = 0; a < D; ++a) p[j * D + a] = f[j][a];
    }
  }
};

template <int NN, int D, typename S, typename I>
struct Writer<NN, D, S, I, true> {
  S* out;                  // PartialForce [N_n, V, D]
  const I* force_index;    // [N, NN]
  int64_t num_nodes;       // V
  TM_HD void operator()(int64_t e, const I (&idx)[NN], const S (&f)[NN][D]) const {
    I slot[NN];
    load_block<NN, I>(force_index + e * NN, slot);
    TM_UNROLL for (int j = 0; j < NN; ++j) {
      S* p = out + (static_cast<int64_t>(slot[j]) * num_nodes + static_cast<int64_t>(idx[j])) * D;
      TM_UNROLL for (int a = 0; a < D; ++a) p[a] = f[j][a];
    }
  }
};

// ------------------------------------------------------------------ kernel 1, stress form

template <typename S, typename I>
struct StressInputs {
  const S* u;              // [V, D]
  const S* du;             // [V, D] (dforces only)
  const I* elements;       // [N, NN]
  const S* shape_vectors;  // [N, NN, D]
  const S* measure;        // [N]
  const S* lam;            // [N]
  const S* mu;             // [N]
  const S* projector;      // [N, D, D] (membranes only)
  const S* rest;           // [N, NN, D] rest element nodes (corotational QR recomputed per call; D = 3)
  const S* rotations;      // [N, D, D] element rotations (corotational; nullptr: QR frame from rest)

  // What every stress-form element kernel starts from: element e's node ids, shape vectors,
  // measure, Lame parameters, tangent plane (the projector of a membrane) and displacements.
  template <int NN, int D, bool M>
  TM_HD void load_element(int64_t e, I (&idx)[NN], S (&m)[NN][D], S& vol, S& lam_e, S& mu_e,
                          Plane<D, S, M>& plane, S (&u_e)[NN][D]) const {
    load_block<NN, I>(elements + e * NN, idx);
    load_matrix<NN, D, S>(shape_vectors + e * (NN * D), m);
    vol = ld(measure + e);
    lam_e = ld(lam + e);
    mu_e = ld(mu + e);
    if constexpr (M) load_matrix<D, D, S>(projector + e * (D * D), plane.p);
    gather_nodes<NN, D, S, I>(u, idx, u_e);
  }
};

template <int MODEL, bool DFORCE, int NN, int D, typename S, typename I, bool PADDED>
struct StressElementKernel {
  static constexpr bool kMembrane = NN - 1 < D;
  StressInputs<S, I> in;
  Writer<NN, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    S m[NN][D], vol, lam, mu, u[NN][D], f[NN][D];
    Plane<D, S, kMembrane> plane;
    in.load_element(e, idx, m, vol, lam, mu, plane, u);
    if constexpr (MODEL == kCorotational) {
      // The rotations of the linearisation when given (9 loads, the CG path), else SOFA's QR
      // frame recomputed from u and the rest nodes (a uniform branch: one pointer per launch).
      S r[D][D];
      if (in.rotations != nullptr) {
        load_matrix<D, D, S>(in.rotations + e * (D * D), r);
      } else if constexpr (D == 3) {
        S x0[NN][D];
        load_matrix<NN, D, S>(in.rest + e * (NN * D), x0);
        qr_rotation<NN, S>(u, x0, r);
      }
      if (DFORCE) {
        S du[NN][D];
        gather_nodes<NN, D, S, I>(in.du, idx, du);
        corotational_dforces<NN, D, S, kMembrane>(du, r, m, vol, lam, mu, plane, f);
      } else {
        corotational_forces<NN, D, S, kMembrane>(u, r, m, vol, lam, mu, plane, f);
      }
    } else if (DFORCE) {
      S du[NN][D];
      gather_nodes<NN, D, S, I>(in.du, idx, du);
      stress_dforces<MODEL, NN, D, S, kMembrane>(u, du, m, vol, lam, mu, plane, f);
    } else {
      stress_forces<MODEL, NN, D, S, kMembrane>(u, m, vol, lam, mu, plane, f);
    }
    write(e, idx, f);
  }

};

// ------------------------------------------------------------------ the tangent on the node graph
//
// The force differential of a stress-form group at u, held fixed for a whole CG solve, as 3x3
// blocks on the edges of the mesh: with H_ij = d f_i / d u_j summed over the elements sharing
// the edge (i, j), every row of an element's blocks sums to zero (sum_k m_k = 0), so
//   (dF/du) p at node i = sum_j H_ij (p_j - p_i)
// and the CG matvec is hooke_node_system's over the node graph with node_k = -H_ij in the slot
// of (i -> j) and -H_ij^T in that of (j -> i) (the differentials are symmetric: H_ji = H_ij^T).
// Built once per linearisation (the paper's element kernel and gather, no atomics): kernel 1 per
// element writes its pair blocks into a padded per-edge buffer, kernel 2 per edge sums its slots
// in order, kernel 3 per slot of the node graph copies its edge's sum into node_k (kernel 2
// writing node_k itself made two scattered 36-byte stores an edge: partial sectors). Every CG
// iteration then reads 9 values an edge and direction instead of recomputing each element's
// differential.

// The index of the local pair (a, b), a < b, in the order of topology.unique_edges:
// (0,1), (0,2), ..., (1,2), ...
template <int NN>
TM_HD constexpr int pair_index(int a, int b) {
  return a * (2 * NN - a - 1) / 2 + (b - a - 1);
}

// A block of edge_partial: D x D values padded to a multiple of 16 bytes (12 for 3-D, 4 for
// 2-D), so kernel 1 stores and kernel 2 loads it in 16-byte pieces (scattered 4-byte stores were
// most of kernel 1's time: each touched its own 32-byte sector).
template <int D, typename S>
struct PaddedBlock {
  static constexpr int kStride = D == 3 ? 12 : 4;  // 48 / 96 bytes (3-D), 16 / 32 (2-D)
  static constexpr int kPer = int(16 / sizeof(S));

  static TM_HD void store(S* dst, const S (&v)[kStride]) {
#if defined(__CUDA_ARCH__)
    TM_UNROLL for (int q = 0; q < kStride / kPer; ++q) {
      int4 chunk;
      memcpy(&chunk, v + q * kPer, 16);
      reinterpret_cast<int4*>(dst)[q] = chunk;
    }
#else
    std::memcpy(dst, v, sizeof(v));
#endif
  }

  static TM_HD void load(const S* src, S (&v)[kStride]) {
    TM_UNROLL for (int q = 0; q < kStride / kPer; ++q) load16<S>(src + q * kPer, v + q * kPer);
  }
};

// Kernel 1: NN - 1 items per element, one per column node b = 1 .. NN-1 (item e (NN - 1) + b - 1):
// column c of H_ab (a < b) is the differential on node a along du = e_c at node b: the model's
// own dforces, D evaluations an item (the same function the element path of the CG calls, so
// both are one formula). Each block goes to edge_partial[edge_slot[e][p]][element_edges[e][p]]
// oriented from the pair's lower global node to its higher (transposed where idx[a] > idx[b]),
// whole. (One item an element, all (NN - 1) D evaluations, left 16 warps a multiprocessor at
// 128 registers to hide its loads: 220 us on the paper beam.)
template <int MODEL, int NN, int D, typename S, typename I>
struct TangentElementKernel {
  static constexpr bool kMembrane = NN - 1 < D;
  static constexpr int kPairs = NN * (NN - 1) / 2;
  using Block = PaddedBlock<D, S>;
  StressInputs<S, I> in;   // rotations given for the corotational model
  const I* element_edges;  // [N, P] the edge of each local pair
  const I* edge_slots;     // [N, P] its slot among the edge's elements
  int64_t num_edges;       // Ed
  S* edge_partial;         // [N_es, Ed, Block::kStride]

  TM_HD void operator()(int64_t t) const {
    const int64_t e = t / (NN - 1);
    const int b = 1 + static_cast<int>(t - e * (NN - 1));
    // b known at compile time in each branch: the unit displacements fold into the arithmetic
    if (b == 1) column_blocks<1>(e);
    if constexpr (NN > 2) {
      if (b == 2) column_blocks<2>(e);
    }
    if constexpr (NN > 3) {
      if (b == 3) column_blocks<3>(e);
    }
  }

  template <int B>
  TM_HD void column_blocks(int64_t e) const {
    I idx[NN], edge[kPairs], slot[kPairs];
    S m[NN][D], vol, lam, mu, u[NN][D], r[D][D];
    Plane<D, S, kMembrane> plane;
    in.load_element(e, idx, m, vol, lam, mu, plane, u);
    load_block<kPairs, I>(element_edges + e * kPairs, edge);
    load_block<kPairs, I>(edge_slots + e * kPairs, slot);
    if constexpr (MODEL == kCorotational) load_matrix<D, D, S>(in.rotations + e * (D * D), r);
    S column[D][NN][D];  // column[c][a] = d f_a / d u_B[c]
    TM_UNROLL for (int c = 0; c < D; ++c) {
      S du[NN][D];
      TM_UNROLL for (int k = 0; k < NN; ++k) {
        TM_UNROLL for (int x = 0; x < D; ++x) du[k][x] = (k == B && x == c) ? S(1) : S(0);
      }
      if constexpr (MODEL == kCorotational) {
        corotational_dforces<NN, D, S, kMembrane>(du, r, m, vol, lam, mu, plane, column[c]);
      } else {
        stress_dforces<MODEL, NN, D, S, kMembrane>(u, du, m, vol, lam, mu, plane, column[c]);
      }
    }
    TM_UNROLL for (int a = 0; a < B; ++a) {
      const int pair = pair_index<NN>(a, B);
      const bool low_first = idx[a] < idx[B];
      S v[Block::kStride];
      TM_UNROLL for (int x = 0; x < D; ++x) {
        TM_UNROLL for (int c = 0; c < D; ++c) v[x * D + c] = low_first ? column[c][a][x] : column[x][a][c];
      }
      TM_UNROLL for (int q = D * D; q < Block::kStride; ++q) v[q] = S(0);
      Block::store(edge_partial + (static_cast<int64_t>(slot[pair]) * num_edges + static_cast<int64_t>(edge[pair])) *
                                      Block::kStride, v);
    }
  }
};

// Kernel 2: one item per edge: H = the sum of its used slots in slot order, stored into the
// edge's slot-0 row of edge_partial (in place: no other item reads or writes that row), written
// in edge order (whole blocks, consecutive edges side by side).
template <int D, typename S, typename I>
struct TangentEdgeKernel {
  using Block = PaddedBlock<D, S>;
  S* edge_partial;          // [N_es, Ed, Block::kStride]; row 0 ends as the edges' sums
  const I* edge_counts;     // [Ed] elements of each edge
  int64_t num_edges;

  TM_HD void operator()(int64_t g) const {
    S h[Block::kStride];
    TM_UNROLL for (int q = 0; q < Block::kStride; ++q) h[q] = S(0);
    const int64_t count = static_cast<int64_t>(ld(edge_counts + g));
    for (int64_t s = 0; s < count; ++s) {
      S v[Block::kStride];
      Block::load(edge_partial + (s * num_edges + g) * Block::kStride, v);
      TM_UNROLL for (int q = 0; q < Block::kStride; ++q) h[q] += v[q];
    }
    Block::store(edge_partial + g * Block::kStride, h);
  }
};

// Kernel 3: one item per value (r, q) of a row's block (the rows of the node graph,
// HookeNodeGraph), over the row's used slots s: node_k [s][r] holds -H_g where the row's node is
// the first node of the slot's edge g (slot_edge = g), -H_g^T where it is the second (slot_edge =
// ~g). The D*D items of a row are consecutive, so each slot's stores are side by side. (On the
// paper beam: 38 us; one item per slot, D*D strided stores each, 74 us; one item per value of
// node_k, 65 us.) Slots beyond a row's incidences are not written.
template <int D, typename S, typename I>
struct TangentSlotKernel {
  using Block = PaddedBlock<D, S>;
  const S* edge_sums;       // [Ed, Block::kStride] (kernel 2's row 0)
  const I* slot_edge;       // [N_n, V] by row
  const I* incidences;      // [V] by row
  int64_t num_nodes;
  S* node_k;                // [N_n, V, D, D] by row

  TM_HD void operator()(int64_t t) const {
    const int64_t row = t / (D * D);
    const int q = static_cast<int>(t - row * (D * D)), x = q / D, y = q - x * D;
    const int64_t count = static_cast<int64_t>(ld(incidences + row));
    for (int64_t s = 0; s < count; ++s) {
      const int64_t code = static_cast<int64_t>(ld(slot_edge + s * num_nodes + row));
      const bool first = code >= 0;
      const S* h = edge_sums + (first ? code : -code - 1) * Block::kStride;
      node_k[(s * num_nodes + row) * (D * D) + q] = -ld(h + (first ? q : y * D + x));
    }
  }
};

// ------------------------------------------------------------------ corotational rotations

// One item per element: its rotation R [D, D] at u (element_math.h: element_rotation), written
// to out [N, D, D]. Reads the rest nodes only where the method needs them (QR, polar membranes).
template <int METHOD, int NN, int D, typename S, typename I>
struct RotationKernel {
  static constexpr bool kMembrane = NN - 1 < D;
  static constexpr bool kNeedsRest = RotationNeedsRest<METHOD, kMembrane>::value;
  const S* u;              // [V, D]
  const I* elements;       // [N, NN]
  const S* shape_vectors;  // [N, NN, D] (polar)
  const S* projector;      // [N, D, D] (polar membranes)
  const S* rest;           // [N, NN, D] (QR, polar membranes)
  S* out;                  // [N, D, D]

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(elements + e * NN, idx);
    S x[NN][D], x0[NN][D], m[NN][D];
    gather_nodes<NN, D, S, I>(u, idx, x);
    if constexpr (kNeedsRest) load_matrix<NN, D, S>(rest + e * (NN * D), x0);
    if constexpr (METHOD == kPolar) load_matrix<NN, D, S>(shape_vectors + e * (NN * D), m);
    Plane<D, S, kMembrane> plane;
    if constexpr (kMembrane && METHOD == kPolar) load_matrix<D, D, S>(projector + e * (D * D), plane.p);
    S r[D][D];
    element_rotation<METHOD, NN, D, S, kMembrane>(x, x0, m, plane, r);
    S* p = out + e * (D * D);
    TM_UNROLL for (int a = 0; a < D; ++a) {
      TM_UNROLL for (int b = 0; b < D; ++b) p[a * D + b] = r[a][b];
    }
  }
};

// ------------------------------------------------------------------ kernel 1, tensor form

// hooke: one item per edge [Ed, 2] with tensor edge_k [Ed, D, D].
template <int D, typename S, typename I, bool PADDED>
struct TensorHookeEdgeKernel {
  const S* u;       // [V, D]
  const I* edges;   // [Ed, 2]
  const S* edge_k;  // [Ed, D, D]
  Writer<2, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[2];
    load_block<2, I>(edges + e * 2, idx);
    S k[D][D];
    load_matrix<D, D, S>(edge_k + e * (D * D), k);
    S x[2][D], f[2][D];
    gather_nodes<2, D, S, I>(u, idx, x);
    tensor_hooke_edge<D, S>(k, x[0], x[1], f);
    write(e, idx, f);
  }
};

// stvk: one item per element with B [N, NN, NN, D, D], C [N, NN, NN, NN, D], D [N, NN, NN, NN, NN].
template <bool DFORCE, int NN, int D, typename S, typename I, bool PADDED>
struct TensorStvkKernel {
  const S* u;         // [V, D]
  const S* du;        // [V, D] (dforces only)
  const I* elements;  // [N, NN]
  const S* tb;
  const S* tc;
  const S* td;
  Writer<NN, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(elements + e * NN, idx);
    S x[NN][D], f[NN][D];
    gather_nodes<NN, D, S, I>(u, idx, x);
    const S* b = tb + e * (NN * NN * D * D);
    const S* c = tc + e * (NN * NN * NN * D);
    const S* d = td + e * (NN * NN * NN * NN);
    if (DFORCE) {
      S dx[NN][D];
      gather_nodes<NN, D, S, I>(du, idx, dx);
      tensor_stvk_dforces<NN, D, S>(x, dx, b, c, d, Loader{}, f);
    } else {
      tensor_stvk_forces<NN, D, S>(x, b, c, d, Loader{}, f);
    }
    write(e, idx, f);
  }
};

// ------------------------------------------------------------------ kernel 2

// Kernel 2's core: acc = sum of node i's used slots of PartialForce [N_n, V, D], in slot order
// (the fixed order that makes the result bitwise reproducible).
template <int D, typename S, typename I>
TM_HD void sum_slots(const S* partial, const I* incidences, int64_t num_nodes, int64_t i, S (&acc)[D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) acc[a] = S(0);
  const int64_t count = static_cast<int64_t>(ld(incidences + i));
  const S* q = partial + i * D;
  const int64_t stride = num_nodes * D;
  for (int64_t s = 0; s < count; ++s) {
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += ld(q + a);
    q += stride;
  }
}

// TotalForce[i] = sum_{s < incidences[i]} PartialForce[s][i] (+ node_term[i]).
template <int D, typename S, typename I>
struct GatherKernel {
  const S* partial;     // [N_n, V, D]
  const I* incidences;  // [V]
  const S* node_term;   // [V, D] added as is, or nullptr
  S* out;               // [V, D]
  int64_t num_nodes;

  TM_HD void operator()(int64_t i) const {
    S acc[D];
    sum_slots<D, S, I>(partial, incidences, num_nodes, i, acc);
    if (node_term != nullptr) {
      TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += ld(node_term + i * D + a);
    }
    TM_UNROLL for (int a = 0; a < D; ++a) out[i * D + a] = acc[a];
  }
};

// The implicit-Euler system epilogue of node i, shared by the CG matvec kernels (the padded
// SystemGatherKernel and the node-centric NodeHookeSystemKernel), given acc = the stiffness
// product's sum (K p)_i over the node's slots and pv = p_i:
//   (K p)_i -= K_ii p_i  (node stiffness K_ii [V, D, D]: contact penalties k n n^T)
//   Ap[i] = free_i * (c_M m_i p_i - c_K (K p)_i),   pAp[i] = sum_a p[i][a] Ap[i][a]
// The arithmetic follows the torch expression (c_M m_i) p_i - c_K (K p)_i, then the projection,
// so that the result equals the composed path to rounding.
template <int D, typename S, bool HAS_FREE, bool HAS_NODE_K>
struct SystemEpilogue {
  static constexpr bool kHasNodeK = HAS_NODE_K;
  const S* mass;            // [V]
  const S* free;            // [V] 0/1 (HAS_FREE)
  const S* node_stiffness;  // [V, D, D] (HAS_NODE_K)
  S c_mass;
  S c_stiff;
  S* ap;                    // [V, D]
  S* p_dot_ap;              // [V], or nullptr (the CG step-length kernels use the returned dot)

  // Node i's inputs to the row: its own stiffness (HAS_NODE_K), c_M m_i and free_i (1 without).
  TM_HD void load_node(int64_t i, S (&k_own)[D][D], S& m, S& f) const {
    if (HAS_NODE_K) load_matrix<D, D, S>(node_stiffness + i * (D * D), k_own);
    m = c_mass * ld(mass + i);
    f = HAS_FREE ? ld(free + i) : S(1);
  }

  // (A p)_i from the stiffness sum acc = (K p)_i without the node's own stiffness k_own, m = c_M m_i,
  // f = free_i: the arithmetic of every CG matvec of the hooke node graph (acc is updated).
  static TM_HD void row(const S (&k_own)[D][D], S m, S f, S c_stiff_, const S (&pv)[D], S (&acc)[D], S (&out)[D]) {
    if (HAS_NODE_K) {
      TM_UNROLL for (int a = 0; a < D; ++a) {
        S s = S(0);
        TM_UNROLL for (int b = 0; b < D; ++b) s += k_own[a][b] * pv[b];
        acc[a] -= s;
      }
    }
    TM_UNROLL for (int a = 0; a < D; ++a) {
      const S mp = m * pv[a];
      const S kp = c_stiff_ * acc[a];
      S v = mp - kp;
      if (HAS_FREE) v = v * f;
      out[a] = v;
    }
  }

  // Writes Ap_i (and p_dot_ap[i] when that buffer is given) and returns p_i . Ap_i.
  TM_HD S operator()(int64_t i, const S (&pv)[D], S (&acc)[D]) const {
    S k_own[D][D], m, f, out[D];
    load_node(i, k_own, m, f);
    row(k_own, m, f, c_stiff, pv, acc, out);
    S dot = S(0);
    TM_UNROLL for (int a = 0; a < D; ++a) {
      ap[i * D + a] = out[a];
      dot += pv[a] * out[a];
    }
    if (p_dot_ap != nullptr) p_dot_ap[i] = dot;
    return dot;
  }
};

// Kernel 2 with the system epilogue (the CG matvec of A = c_M M - c_K K, two kernels):
// (K p)_i = sum_{s < incidences[i]} PartialForce[s][i], where PartialForce holds the partial
// force differentials (dF/du) p of kernel 1.
template <int D, typename S, typename I, bool HAS_FREE, bool HAS_NODE_K>
struct SystemGatherKernel {
  using Scalar = S;
  using Index = I;
  const S* partial;         // [N_n, V, D]
  const I* incidences;      // [V]
  const S* p;               // [V, D]
  int64_t num_nodes;
  SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K> epilogue;

  // Ap_i and p_i . Ap_i (returned): the CG step-length kernels call this (cg_reduce.cuh).
  TM_HD S apply(int64_t i) const {
    S acc[D];
    sum_slots<D, S, I>(partial, incidences, num_nodes, i, acc);
    S pv[D];
    TM_UNROLL for (int a = 0; a < D; ++a) pv[a] = ld(p + i * D + a);
    return epilogue(i, pv, acc);
  }
  TM_HD void operator()(int64_t i) const { apply(i); }
};

// ------------------------------------------------------------------ node-centric hooke matvec

// The CG matvec of the hooke tensor form in one kernel, one item per node: the product with the
// stiffness is a sparse block product over the node graph,
//   (K p)_i = sum_{s < incidences[i]} -Kdir[s][i] (p[neighbor[s][i]] - p_i),
// with Kdir = K_e where i is the first node of edge e and K_e^T where it is the second, in the
// slots of the padded plan (slot-major "ELL" arrays neighbor [N_n, V], node_k [N_n, V, D, D]: the
// threads of a warp read consecutive nodes of one slot). Each term is tensor_hooke_edge's force
// on its first node with (Kdir, p_i, p_j): for the second node of an edge, w' = p_i - p_j = -w
// and -(K^T w') = K^T w exactly, so every term, and the sum in slot order, is bitwise the one
// kernel 1 writes and kernel 2 adds; no PartialForce buffer is written or read back.
//
// HookeNodeGraph holds the graph and sums that product for any field w read through load_p
// (f_i = sum_s -Kdir[s][i] (w_j - w_i), the elastic force of the displacements w): the matvec
// reads p, the step's right-hand side (NodeHookeStepRhsKernel) reads (x - rest) + c v.
//
// The graph's arrays are stored by ROW: row r holds the slots of node row_node[r] (a permutation
// of the nodes; nullptr: row r is node r). Rows are the nodes sorted by slot count within windows
// of each object (native.node_graph_rows), so that the threads of a warp, which take consecutive
// rows, walk as many slots each and read the slot arrays side by side: on the paper beam, whose
// nodes alternate 10 and 26 slots, a node-ordered matvec idles half its lanes (docs/node-graph.md;
// benchmarks/probes/node_k_layout_probe.py). Every result is per node and its slots are summed in
// slot order, so the row order changes no value.
template <int D, typename S, typename I>
struct HookeNodeGraph {
  const I* neighbor;    // [N_n, V] by row: the other NODE of the edge in each slot
  const S* node_k;      // [N_n, V, D, D] by row: Kdir of each slot
  const I* incidences;  // [V] by row: the row's slot count
  const I* row_node;    // [V] the node of each row, or nullptr (the identity)
  int64_t num_nodes;

  TM_HD int64_t node_of(int64_t row) const { return row_node != nullptr ? static_cast<int64_t>(ld(row_node + row)) : row; }

  // Slots are loaded kBatch at a time before any is used: a thread has only a few nodes' worth
  // of parallelism (one node), so its loads must be in flight together, not one dependent chain
  // (neighbor -> w_j) per slot; the terms are still added in slot order.
  static constexpr int kBatch = 4;

  // The neighbour in slot s of node i, read from the graph's arrays.
  struct GlobalNeighbors {
    const I* neighbor;
    int64_t num_nodes;
    TM_HD int64_t operator()(int64_t s, int64_t i) const { return static_cast<int64_t>(ld(neighbor + s * num_nodes + i)); }
  };

  // The forces of row `row` (node i, wi = w_i already loaded); load_p(field + j * D + a) reads w_j[a].
  template <class LoadP>
  TM_HD void add_forces(int64_t row, int64_t i, const S* field, const S (&wi)[D], const LoadP& load_p,
                        S (&acc)[D]) const {
    add_forces(row, i, static_cast<int64_t>(ld(incidences + row)), GlobalNeighbors{neighbor, num_nodes}, field, wi,
               load_p, acc);
  }

  // The same with the row's slot count and neighbours given (neighbors(s, row): the persistent CG
  // keeps them in shared memory across its iterations).
  template <class Neighbors, class LoadP>
  TM_HD void add_forces(int64_t row, int64_t i, int64_t count, const Neighbors& neighbors, const S* field,
                        const S (&wi)[D], const LoadP& load_p, S (&acc)[D]) const {
    for (int64_t s0 = 0; s0 < count; s0 += kBatch) {
      int64_t j[kBatch];
      TM_UNROLL for (int q = 0; q < kBatch; ++q) j[q] = s0 + q < count ? neighbors(s0 + q, row) : i;
      S k[kBatch][D][D], wj[kBatch][D];
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (s0 + q < count) load_matrix<D, D, S>(node_k + ((s0 + q) * num_nodes + row) * (D * D), k[q]);
        TM_UNROLL for (int a = 0; a < D; ++a) wj[q][a] = load_p(field + j[q] * D + a);
      }
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (s0 + q >= count) break;
        S f[2][D];
        tensor_hooke_edge<D, S>(k[q], wi, wj[q], f);  // f[1] is unused (dead code for the compiler)
        TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += f[0][a];
      }
    }
  }
};

template <int D, typename S, typename I, bool HAS_FREE, bool HAS_NODE_K>
struct NodeHookeSystemKernel {
  using Scalar = S;
  using Index = I;
  static constexpr int kDim = D;
  const S* p;  // [V, D]
  HookeNodeGraph<D, S, I> graph;
  SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K> epilogue;

  // For the node i of row `row`: Ap_i, and p_i . Ap_i (returned): the CG step-length kernels call
  // this over rows (cg_reduce.cuh); load_p reads p (the persistent CG's DirectionLoader forms
  // r + beta p with plain loads: p changes during that kernel, and the read-only cache of ld()
  // may hold stale copies).
  template <class LoadP = Loader>
  TM_HD S apply(int64_t row, LoadP load_p = LoadP()) const {
    using Global = typename HookeNodeGraph<D, S, I>::GlobalNeighbors;
    return apply(row, static_cast<int64_t>(ld(graph.incidences + row)), Global{graph.neighbor, graph.num_nodes},
                 load_p);
  }

  // apply with the row's slot count and neighbours given (HookeNodeGraph::add_forces).
  template <class Neighbors, class LoadP>
  TM_HD S apply(int64_t row, int64_t count, const Neighbors& neighbors, LoadP load_p) const {
    const int64_t i = graph.node_of(row);
    S pv[D];
    TM_UNROLL for (int a = 0; a < D; ++a) pv[a] = load_p(p + i * D + a);
    S acc[D];
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] = S(0);
    graph.add_forces(row, i, count, neighbors, p, pv, load_p, acc);
    return epilogue(i, pv, acc);
  }
  TM_HD void operator()(int64_t row) const { apply(row); }
};

// ------------------------------------------------------------------ implicit Euler, per node

// The displacement an implicit Euler step's right-hand side is taken at, w = (x - rest) + c v
// (one expression for every kernel that forms it: their right-hand sides agree bitwise).
template <typename S>
TM_HD S step_displacement(S x, S rest, S v, S c) {
  return (x - rest) + c * v;
}

// step_displacement read through the pointer into x that the node graph computes (q = x + offset).
template <typename S>
struct StepDisplacementLoader {
  const S* x;
  const S* rest;
  const S* v;
  S c;
  TM_HD S operator()(const S* q) const {
    const int64_t o = q - x;
    return step_displacement(ld(x + o), ld(rest + o), ld(v + o), c);
  }
};

// Penalty planes n.x >= offset (contact.Planes): P planes of normals [P, 3], offsets [P] and
// stiffness [P]; 3-D only.
template <typename S>
struct PenaltyPlanes {
  const S* normals;
  const S* offsets;
  const S* stiffness;
  int64_t count;

  // The force on a node at x (sum of k (offset - n.x) n over the planes it is below) and its
  // stiffness -(df/dx) (sum of k n n^T over those planes).
  TM_HD void linearize(const S (&x)[3], S (&force)[3], S (&k)[3][3]) const {
    TM_UNROLL for (int a = 0; a < 3; ++a) {
      force[a] = S(0);
      TM_UNROLL for (int b = 0; b < 3; ++b) k[a][b] = S(0);
    }
    for (int64_t q = 0; q < count; ++q) {
      const S n[3] = {ld(normals + 3 * q), ld(normals + 3 * q + 1), ld(normals + 3 * q + 2)};
      const S depth = ld(offsets + q) - (x[0] * n[0] + x[1] * n[1] + x[2] * n[2]);
      if (!(depth > S(0))) continue;
      const S kq = ld(stiffness + q);
      TM_UNROLL for (int a = 0; a < 3; ++a) {
        force[a] += depth * kq * n[a];
        TM_UNROLL for (int b = 0; b < 3; ++b) k[a][b] += kq * n[a] * n[b];
      }
    }
  }
};

// A node's own terms of implicit Euler's right-hand side, given its elastic force sum `total`
// over the node graph (the force of w = (x - rest) + c_w v) and damping = r_M m_i:
//   rhs = h (total + external + contact(x) - Kc (c_w v) - damping v)
// and the contact stiffness Kc at x (HAS_PLANES, 3-D; `total` is updated). Shared by the
// right-hand side's kernel and the solve that computes it itself (cuda/cg_pipelined.cuh).
template <int D, typename S, bool HAS_PLANES>
TM_HD void step_rhs_node(const PenaltyPlanes<S>& planes, S h, S c_w, S damping, const S (&x)[D], const S (&v)[D],
                         const S (&external)[D], S (&total)[D], S (&k_contact)[D][D], S (&rhs)[D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) total[a] += external[a];
  if constexpr (HAS_PLANES && D == 3) {
    S force[3];
    planes.linearize(x, force, k_contact);
    TM_UNROLL for (int a = 0; a < 3; ++a) {
      S kw = S(0);
      TM_UNROLL for (int b = 0; b < 3; ++b) kw += k_contact[a][b] * (c_w * v[b]);
      total[a] += force[a] - kw;
    }
  }
  TM_UNROLL for (int a = 0; a < D; ++a) rhs[a] = h * (total[a] - damping * v[a]);
}

// The right-hand side of an implicit Euler step of the hooke tensor form, one node per item
// (what SystemMatvec.load + forces_along + the damping and h terms compose from a dozen torch
// ops), at positions x and velocities v with w = (x - rest) + c_w v, c_w = h + r_K:
//   rhs_i = h (f_i(w) + external_i + contact_i(x) - Kc_i (c_w v_i) - r_M m_i v_i)
// where f(w) is the elastic force over the node graph (linear: f(u) + K c_w v in one pass) and
// Kc_i the contact stiffness at x_i, which is also written (node_stiffness, for the CG
// matvec), as are the displacements u = x - rest.
template <int D, typename S, typename I, bool HAS_PLANES>
struct NodeHookeStepRhsKernel {
  using Scalar = S;
  const S* x;         // [V, D]
  const S* v;         // [V, D]
  const S* rest;      // [V, D]
  const S* mass;      // [V]
  const S* external;  // [V, D]
  HookeNodeGraph<D, S, I> graph;
  PenaltyPlanes<S> planes;  // HAS_PLANES (D == 3)
  S h, c_w, rayleigh_mass;
  S* u;               // [V, D] out
  S* rhs;             // [V, D] out
  S* node_stiffness;  // [V, D, D] out (HAS_PLANES)

  TM_HD void operator()(int64_t row) const {
    const int64_t i = graph.node_of(row);
    const StepDisplacementLoader<S> load_w{x, rest, v, c_w};
    S wi[D], total[D];
    TM_UNROLL for (int a = 0; a < D; ++a) {
      wi[a] = load_w(x + i * D + a);
      total[a] = S(0);
      u[i * D + a] = ld(x + i * D + a) - ld(rest + i * D + a);
    }
    graph.add_forces(row, i, x, wi, load_w, total);
    S xi[D], vi[D], external_i[D], k_contact[D][D], out[D];
    TM_UNROLL for (int a = 0; a < D; ++a) {
      xi[a] = ld(x + i * D + a);
      vi[a] = ld(v + i * D + a);
      external_i[a] = ld(external + i * D + a);
    }
    step_rhs_node<D, S, HAS_PLANES>(planes, h, c_w, rayleigh_mass * ld(mass + i), xi, vi, external_i, total, k_contact,
                                    out);
    if constexpr (HAS_PLANES) {
      TM_UNROLL for (int a = 0; a < D; ++a) {
        TM_UNROLL for (int b = 0; b < D; ++b) node_stiffness[(i * D + a) * D + b] = k_contact[a][b];
      }
    }
    TM_UNROLL for (int a = 0; a < D; ++a) rhs[i * D + a] = out[a];
  }
};

// Scatter compact partial forces [N, NN, D] into the padded buffer (the write of kernel 1 for
// partial forces computed elsewhere, e.g. by the reference or by the element-level ops).
template <int NN, int D, typename S, typename I>
struct ScatterKernel {
  const S* partial;  // [N, NN, D]
  const I* index;    // [N, NN]
  Writer<NN, D, S, I, true> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(index + e * NN, idx);
    S f[NN][D];
    load_matrix<NN, D, S>(partial + e * (NN * D), f);
    write(e, idx, f);
  }
};

}  // namespace tensormass
