// The per-item kernels of element removal (ops.h). A removal does not subtract: each target a
// removed element touched (a node, an edge of the hooke tensor form) is summed again from the
// elements still on it, read from its incidence list (a padded table [S, T]: slot s of target t
// holds an element id, -1 past the last) in the list's order, which is the order in which the
// model was assembled. So the result is what a model built from the remaining elements holds (to
// the rounding of the element math; a target left with no element holds exactly 0, not a
// subtraction's residue), and it is deterministic with no atomics and no sort: an item per
// touched (element, node) or (element, edge) pair, and a target touched by several removed
// elements is written by each of them with the same value.
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

// One (removed row, local node) an item: node i = elements[rows[r]][a] gets
//   mass[i] = sum of element_share[e] over its listed elements e not removed (slot order),
//   node_elements[i] = how many there are.
template <typename S, typename I>
struct RefreshNodesKernel {
  const I* elements;       // [N, NN] (the group's)
  const I* rows;           // [R]
  int nodes_per_element;   // NN
  const I* node_slots;     // [num_slots, V] model element ids, -1 past the last
  int64_t num_slots;
  int64_t num_nodes;       // V
  const S* element_share;  // [N_model] element mass / its node count
  const bool* removed;     // [N_model]
  S* mass;                 // [V]
  int32_t* node_elements;  // [V]

  TM_HD void operator()(int64_t item) const {
    const int64_t r = item / nodes_per_element, a = item % nodes_per_element;
    const int64_t node = static_cast<int64_t>(elements[static_cast<int64_t>(rows[r]) * nodes_per_element + a]);
    S sum = S(0);
    int32_t alive = 0;
    for (int64_t s = 0; s < num_slots; ++s) {
      const I e = node_slots[s * num_nodes + node];
      if (e < 0) break;
      if (removed[e]) continue;
      sum += element_share[e];
      ++alive;
    }
    mass[node] = sum;
    node_elements[node] = alive;
  }
};

// One (removed row, local pair) an item: edge g = element_edges[rows[r]][p] gets
//   edge_k[g] = sum of K_ab over its listed elements q not removed (slot order),
// K_ab the tensor of q's local pair (a < b) on g, formed from the rest shape (Cotin's
// hooke_pair_tensor), stored from the lower to the higher global node.
template <int NN, int D, typename S, typename I>
struct RefreshHookeEdgesKernel {
  const S* rest;            // [V, D]
  const I* elements;        // [N, NN]
  const I* rows;            // [R]
  const I* element_edges;   // [N, P] the edge of each local pair
  const I* edge_slots;      // [num_slots, Ed] model element ids, -1 past the last
  int64_t num_slots;
  int64_t num_edges;        // Ed
  const I* element_row;     // [N_model] the group row of each model element id
  const bool* removed;      // [N_model]
  const S* measure;         // [N]
  const S* young;           // [N]
  const S* poisson;         // [N]
  S* edge_k;                // [Ed, D, D]

  static constexpr int P = NN * (NN - 1) / 2;

  TM_HD void operator()(int64_t item) const {
    const int64_t r = item / P, p = item % P;
    const I edge = element_edges[static_cast<int64_t>(rows[r]) * P + p];
    S sum[D][D];
    TM_UNROLL for (int x = 0; x < D; ++x) {
      TM_UNROLL for (int y = 0; y < D; ++y) sum[x][y] = S(0);
    }
    for (int64_t s = 0; s < num_slots; ++s) {
      const I q = edge_slots[s * num_edges + edge];
      if (q < 0) break;
      if (removed[q]) continue;
      const int64_t row = static_cast<int64_t>(element_row[q]);
      I idx[NN];
      S x0[NN][D];
      TM_UNROLL for (int a = 0; a < NN; ++a) {
        idx[a] = elements[row * NN + a];
        TM_UNROLL for (int c = 0; c < D; ++c) x0[a][c] = rest[static_cast<int64_t>(idx[a]) * D + c];
      }
      S m[NN][D], proj[D][D];
      rest_shape_vectors<NN, D, S>(x0, m, proj);
      S lam, mu;
      lame_of<NN, S>(young[row], poisson[row], lam, mu);
      int pair = 0;
      TM_UNROLL for (int a = 0; a < NN; ++a) {
        TM_UNROLL for (int b = a + 1; b < NN; ++b) {
          if (element_edges[row * P + pair] == edge) {
            S k[D][D];
            hooke_pair_tensor<NN, D, S>(m, proj, measure[row], lam, mu, a, b, k);
            const bool low_first = idx[a] < idx[b];
            TM_UNROLL for (int x = 0; x < D; ++x) {
              TM_UNROLL for (int y = 0; y < D; ++y) sum[x][y] += low_first ? k[x][y] : k[y][x];
            }
          }
          ++pair;
        }
      }
    }
    S* out = edge_k + static_cast<int64_t>(edge) * (D * D);
    TM_UNROLL for (int x = 0; x < D; ++x) {
      TM_UNROLL for (int y = 0; y < D; ++y) out[x * D + y] = sum[x][y];
    }
  }
};

}  // namespace tensormass
