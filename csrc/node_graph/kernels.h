// The node graph family's per-item kernels (the graph's CG matvec itself, NodeHookeSystemKernel, is
// common/node_graph.h, as the solves share it): the tangent of a stress-form group on the node graph
// (TangentElementKernel, TangentEdgeKernel, TangentSlotKernel) and implicit Euler's right-hand side
// of the hooke tensor form (NodeHookeStepRhsKernel).
#pragma once

#include <cstdint>
#include <cstring>

#include "common/element_math.h"
#include "common/kernel_io.h"
#include "common/node_graph.h"
#include "common/star.h"
#include "common/step_rhs.h"
#include "common/stress_args.h"

namespace tensormass {

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
// whole. (One item an element, all (NN - 1) D evaluations, needs too many registers to keep
// enough warps resident to hide its loads: docs/performance-history.md.)
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
// ~g). The D*D items of a row are consecutive, so each slot's stores are side by side (the
// layouts compared: docs/performance-history.md). Slots beyond a row's incidences are not written.
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
    if constexpr (HAS_PLANES && D == 3) {  // step_rhs_node forms k_contact only then (planes are 3-D)
      TM_UNROLL for (int a = 0; a < D; ++a) {
        TM_UNROLL for (int b = 0; b < D; ++b) node_stiffness[(i * D + a) * D + b] = k_contact[a][b];
      }
    }
    TM_UNROLL for (int a = 0; a < D; ++a) rhs[i * D + a] = out[a];
  }
};

// ------------------------------------------------------------------ edges written into the graph

// One listed edge an item (node_graph_write_edges): edge e = (i, j) writes its tensor K_e into the
// slot of its first node and K_e^T into that of its second, at each node's row (row_of[i], or i
// where rows are in node order). An edge listed twice writes the same values twice.
template <int D, typename S, typename I, typename J>
struct WriteEdgesKernel {
  const J* edge_ids;     // [M]
  const I* edges;        // [Ed, 2]
  const I* force_index;  // [Ed, 2]
  const S* edge_k;       // [Ed, D, D]
  const I* row_of;       // [V] or nullptr
  int64_t num_nodes;     // V (the graph's columns)
  S* node_k;             // [N_n, V, D, D]

  TM_HD void operator()(int64_t m) const {
    const int64_t e = static_cast<int64_t>(edge_ids[m]);
    const S* k = edge_k + e * (D * D);
    TM_UNROLL for (int side = 0; side < 2; ++side) {
      const int64_t node = static_cast<int64_t>(edges[e * 2 + side]);
      const int64_t row = row_of == nullptr ? node : static_cast<int64_t>(row_of[node]);
      const int64_t slot = static_cast<int64_t>(force_index[e * 2 + side]);
      S* out = node_k + (slot * num_nodes + row) * (D * D);
      TM_UNROLL for (int a = 0; a < D; ++a) {
        TM_UNROLL for (int b = 0; b < D; ++b) out[a * D + b] = side == 0 ? k[a * D + b] : k[b * D + a];
      }
    }
  }
};

// The most neighbours a row rebuilt by RebuildRowNeighborsKernel may hold.
constexpr int kMaxRebuiltSlots = 64;

// The row of a touched node of a hooke tensor-form group's node graph, rebuilt after its elements
// changed (a cut on the device, cutting/kernels.h), in three passes, each item a (slot, node) or a
// (node, slot), so that no thread walks a whole star (a thread per node would take as long as the
// node with the largest star, its loads one after another; docs/topology-changes.md):
//   RebuildRowFirstsKernel, a (slot h, touched node p) an item: which of the other nodes of p's h-th
//     element (if it is alive and holds p) no element before it in p's list holds, as a mask of its
//     local indices in firsts[h, p] (the earlier elements read eight at a time).
//   RebuildRowNeighborsKernel, a (slot h, touched node p) an item, after it: the neighbours of p in
//     the order first met over its list and their local nodes in order: h's first nodes go to
//     neighbor[t, row] from t = the firsts of the elements before h, and incidences[row] = all
//     of them. A row that would need more slots than max_slots (the most the captured solve's
//     launch holds, at most the graph's N_n) is not written and sets status = 1.
//   RebuildRowBlocksKernel, a (node, slot) an item, after them: the block of the slot's neighbour q,
//     summed over the node's alive elements holding q in list order, each element's pair tensor
//     (pair_k: K_lh of each local pair l < h, formed once from the rest shape; a cut re-points
//     elements but never changes their shape) oriented from the lower to the higher global node as
//     the edge stores it, and transposed where p is the higher node. So each block is what the edge
//     (p, q) of a build of these elements sums (the same terms in the same element order) and its
//     orientation the row's.
// Each item writes only its own entry, row or slot: deterministic, no atomics.
template <int NN, typename I>
struct RebuildRowFirstsKernel {
  const I* elements;         // [N, NN]
  const I* node_slots;       // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;         // V
  const bool* alive;         // [N]
  const uint8_t* touched;    // [V]
  int32_t* firsts;           // [num_slots, V]

  TM_HD void operator()(int64_t item) const {
    const int64_t h = item / num_nodes, p = item % num_nodes;
    if (!touched[p]) return;
    const I e = node_slots[item];
    if (e < 0) return;
    I row[NN];
    TM_UNROLL for (int a = 0; a < NN; ++a) row[a] = elements[static_cast<int64_t>(e) * NN + a];
    bool fresh[NN];
    bool holds = false;
    TM_UNROLL for (int b = 0; b < NN; ++b) {
      holds = holds || static_cast<int64_t>(row[b]) == p;
      fresh[b] = static_cast<int64_t>(row[b]) != p;
    }
    if (!alive[e] || !holds) {
      firsts[item] = 0;
      return;
    }
    for (int64_t s0 = 0; s0 < h; s0 += 8) {
      EightElements<NN, I> eight;
      eight.load(node_slots, h, num_nodes, p, s0, alive, elements);  // (slots before h only)
      TM_UNROLL for (int k = 0; k < 8; ++k) {
        const bool before = eight.ids[k] >= 0 && eight.living[k] && eight.local_of(k, p) >= 0;
        TM_UNROLL for (int a = 0; a < NN; ++a) {
          TM_UNROLL for (int b = 0; b < NN; ++b) fresh[b] = fresh[b] && !(before && eight.rows[k][a] == row[b]);
        }
      }
    }
    int32_t mask = 0;
    TM_UNROLL for (int b = 0; b < NN; ++b) mask |= fresh[b] ? 1 << b : 0;
    firsts[item] = mask;
  }
};

template <int NN, typename I>
struct RebuildRowNeighborsKernel {
  const I* elements;         // [N, NN]
  const I* node_slots;       // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;         // V
  const uint8_t* touched;    // [V]
  const int32_t* firsts;     // [num_slots, V] RebuildRowFirstsKernel's
  const I* row_of;           // [V] or nullptr (rows in node order)
  int64_t max_slots;
  I* neighbor;               // [N_n, V]
  I* incidences;             // [V] by row
  int32_t* status;           // [1]

  TM_HD static int count_bits(int32_t mask) {
    int bits = 0;
    TM_UNROLL for (int b = 0; b < NN; ++b) bits += (mask >> b) & 1;
    return bits;
  }

  TM_HD void operator()(int64_t item) const {
    const int64_t h = item / num_nodes, p = item % num_nodes;
    if (!touched[p]) return;
    const I e = node_slots[item];
    if (e < 0) {
      if (h == 0) incidences[row_of == nullptr ? p : static_cast<int64_t>(row_of[p])] = 0;  // (no element)
      return;
    }
    // the firsts of the elements before h, and of all of them (the list's ids and masks read eight
    // slots at a time)
    int before = 0, total = 0;
    for (int64_t s0 = 0; s0 < num_slots; s0 += 8) {
      I ids[8];
      int32_t masks[8];
      TM_UNROLL for (int k = 0; k < 8; ++k) {
        const bool in = s0 + k < num_slots;
        ids[k] = in ? node_slots[(s0 + k) * num_nodes + p] : I(-1);
        masks[k] = in ? firsts[(s0 + k) * num_nodes + p] : 0;
      }
      TM_UNROLL for (int k = 0; k < 8; ++k) {
        const int bits = ids[k] >= 0 ? count_bits(masks[k]) : 0;
        total += bits;
        before += s0 + k < h ? bits : 0;
      }
      if (ids[7] < 0) break;
    }
    if (total > max_slots || total > kMaxRebuiltSlots) {
      if (h == 0) status[0] = 1;
      return;
    }
    const int64_t row = row_of == nullptr ? p : static_cast<int64_t>(row_of[p]);
    const int32_t mine = firsts[item];
    int t = before;
    TM_UNROLL for (int b = 0; b < NN; ++b) {
      if ((mine >> b) & 1) neighbor[static_cast<int64_t>(t++) * num_nodes + row] = elements[static_cast<int64_t>(e) * NN + b];
    }
    if (h == 0) incidences[row] = static_cast<I>(total);
  }
};

template <int NN, int D, typename S, typename I>
struct RebuildRowBlocksKernel {
  static constexpr int P = NN * (NN - 1) / 2;
  const S* pair_k;           // [N, P, D, D]
  const I* elements;         // [N, NN]
  const I* node_slots;       // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;         // V
  const bool* alive;         // [N]
  const uint8_t* touched;    // [V]
  const I* row_of;           // [V] or nullptr
  int64_t graph_slots;       // N_n
  const I* neighbor;         // [N_n, V]
  const I* incidences;       // [V] by row
  S* node_k;                 // [N_n, V, D, D]

  TM_HD void operator()(int64_t item) const {
    const int64_t p = item / graph_slots, t = item % graph_slots;
    if (!touched[p]) return;
    const int64_t row = row_of == nullptr ? p : static_cast<int64_t>(row_of[p]);
    if (t >= static_cast<int64_t>(incidences[row])) return;
    const I q = neighbor[t * num_nodes + row];
    S block[D][D];
    TM_UNROLL for (int x = 0; x < D; ++x) {
      TM_UNROLL for (int y = 0; y < D; ++y) block[x][y] = S(0);
    }
    // the node's elements eight at a time, then the pair tensors of those holding q (a thread's
    // time here is the latency of its loads)
    for (int64_t s0 = 0; s0 < num_slots; s0 += 8) {
      EightElements<NN, I> eight;
      eight.load(node_slots, num_slots, num_nodes, p, s0, alive, elements);
      TM_UNROLL for (int k = 0; k < 8; ++k) {  // (unrolled: eight stays in registers)
        if (eight.ids[k] < 0 || !eight.living[k]) continue;
        const int mine = eight.local_of(k, p), other = eight.local_of(k, static_cast<int64_t>(q));
        if (mine < 0 || other < 0) continue;
        const int lo = mine < other ? mine : other, hi = mine < other ? other : mine;
        const int pair = lo * (2 * NN - lo - 1) / 2 + (hi - lo - 1);
        const S* k_pair = pair_k + (static_cast<int64_t>(eight.ids[k]) * P + pair) * (D * D);
        // k_pair runs from local lo to local hi and the row of p holds it from p (the orientation
        // of the edge, from its lower global node, cancels out of both)
        const bool transpose = mine > other;
        TM_UNROLL for (int x = 0; x < D; ++x) {
          TM_UNROLL for (int y = 0; y < D; ++y) block[x][y] += transpose ? k_pair[y * D + x] : k_pair[x * D + y];
        }
      }
      if (eight.last()) break;
    }
    S* out = node_k + (t * num_nodes + row) * (D * D);
    TM_UNROLL for (int x = 0; x < D; ++x) {
      TM_UNROLL for (int y = 0; y < D; ++y) out[x * D + y] = block[x][y];
    }
  }
};

}  // namespace tensormass
