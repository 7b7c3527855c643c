// A node's column of a [S, V] table (node_slots: the elements that hold it, -1 past the last; or a
// table beside it, as a cut's group) read into one thread's memory. For the kernels that run a
// thread per node over its star (the cut on the device, the node graph's rebuilt rows): such a
// thread's time is the latency of its loads, so a column is read whole, eight independent loads
// at a time, and elements' rows and flags eight elements at a time, rather than entry by entry.
// (The nodes a cut touches are numbered near each other, so their threads share warps: what they
// do with the star should branch alike in each, or the warp runs the branches one after another:
// docs/performance-history.md.)
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

// The most elements a node's star may hold where a thread reads it whole (node_slots' rows for the
// cut on the device and the node graph's rebuilt rows).
constexpr int kMaxStarElements = 64;

// The column `node` of table [num_slots, num_nodes] into column [num_slots] (the caller checked
// num_slots against its capacity).
template <typename T>
TM_HD void load_column(const T* table, int64_t num_slots, int64_t num_nodes, int64_t node, T* column) {
  int64_t s = 0;
  for (; s + 8 <= num_slots; s += 8) {
    T eight[8];
    TM_UNROLL for (int k = 0; k < 8; ++k) eight[k] = table[(s + k) * num_nodes + node];
    TM_UNROLL for (int k = 0; k < 8; ++k) column[s + k] = eight[k];
  }
  for (; s < num_slots; ++s) column[s] = table[s * num_nodes + node];
}

// The column `node` of node_slots into star [num_slots]; returns the count of elements before the
// first -1.
template <typename I>
TM_HD int load_star(const I* node_slots, int64_t num_slots, int64_t num_nodes, int64_t node, I* star) {
  load_column(node_slots, num_slots, num_nodes, node, star);
  int count = 0;
  while (count < num_slots && star[count] >= 0) ++count;
  return count;
}

// The rows [count, NN] of elements ids[0 .. count) (each >= 0) into rows, eight elements at a time.
template <int NN, typename I>
TM_HD void load_rows(const I* elements, const I* ids, int count, I (*rows)[NN]) {
  for (int j0 = 0; j0 < count; j0 += 8) {
    I eight[8][NN];
    TM_UNROLL for (int k = 0; k < 8; ++k) {
      const int64_t e = j0 + k < count ? static_cast<int64_t>(ids[j0 + k]) : 0;
      TM_UNROLL for (int a = 0; a < NN; ++a) eight[k][a] = j0 + k < count ? elements[e * NN + a] : I(-1);
    }
    for (int k = 0; k < 8 && j0 + k < count; ++k) {
      TM_UNROLL for (int a = 0; a < NN; ++a) rows[j0 + k][a] = eight[k][a];
    }
  }
}

// flags[ids[j]] for j < count (each id >= 0) into out, eight at a time (any per-element value:
// alive flags, mass shares).
template <typename T, typename I>
TM_HD void load_flags(const T* flags, const I* ids, int count, T* out) {
  for (int j0 = 0; j0 < count; j0 += 8) {
    T eight[8];
    TM_UNROLL for (int k = 0; k < 8; ++k) eight[k] = j0 + k < count ? flags[ids[j0 + k]] : T();
    for (int k = 0; k < 8 && j0 + k < count; ++k) out[j0 + k] = eight[k];
  }
}

// Which node an item of a per-node star kernel runs: item i runs node (i * stride) mod n, stride a
// prime that does not divide n (a permutation of the nodes). The nodes a cut touches are numbered
// near each other; run in node order they fill a few blocks, so a few SMs, whose L1 then cannot
// hold those threads' stars (local memory) and every access goes to L2: a row rebuilt alone took
// 4 us, a hundred neighbouring rows 117 us. Spread, each SM gets one or two of them.
struct NodeSpread {
  int64_t num_nodes = 1;
  int64_t stride = 1;

  static NodeSpread of(int64_t num_nodes) {
    NodeSpread spread;
    spread.num_nodes = num_nodes > 0 ? num_nodes : 1;
    for (int64_t prime : {257, 263, 269, 271}) {  // (no n has all four as factors below 2^32)
      if (spread.num_nodes % prime != 0) {
        spread.stride = prime;
        break;
      }
    }
    return spread;
  }

  TM_HD int64_t node(int64_t item) const { return (item * stride) % num_nodes; }
};

// Slots s0 .. s0 + 7 of a node's column of node_slots read together: the element ids (-1 past the
// column and past the list), then their alive flags and rows, all eight elements' loads issued
// before any is used.
template <int NN, typename I>
struct EightElements {
  I ids[8];
  bool living[8];
  I rows[8][NN];

  TM_HD void load(const I* node_slots, int64_t num_slots, int64_t num_nodes, int64_t node, int64_t s0,
                  const bool* alive, const I* elements) {
    TM_UNROLL for (int k = 0; k < 8; ++k) ids[k] = s0 + k < num_slots ? node_slots[(s0 + k) * num_nodes + node] : I(-1);
    TM_UNROLL for (int k = 0; k < 8; ++k) {
      living[k] = ids[k] >= 0 && alive[ids[k]];
      TM_UNROLL for (int a = 0; a < NN; ++a) rows[k][a] = ids[k] >= 0 ? elements[static_cast<int64_t>(ids[k]) * NN + a] : I(-1);
    }
  }

  // The local index of node in element k (-1 where it has none).
  TM_HD int local_of(int k, int64_t node) const {
    int local = -1;
    TM_UNROLL for (int a = 0; a < NN; ++a) local = static_cast<int64_t>(rows[k][a]) == node ? a : local;
    return local;
  }

  // Whether the list ended in these eight (a later batch holds nothing).
  TM_HD bool last() const { return ids[7] < 0; }
};

// The place of the lowest set bit of a non-zero mask (a star's elements as the bits of a 64-bit
// word: kMaxStarElements <= 64).
TM_HD int lowest_bit(uint64_t mask) {
#if defined(__CUDA_ARCH__)
  return __ffsll(static_cast<long long>(mask)) - 1;
#else
  return __builtin_ctzll(mask);
#endif
}

}  // namespace tensormass
