// A node's column of a [S, V] table (node_slots: the elements that hold it, -1 past the last; or a
// table beside it, as a cut's group) read into one thread's memory, and a node's elements read
// eight at a time. For the kernels of the cut on the device and the node graph's rebuilt rows that
// read a star: such a thread's time is the latency of its loads, so a column is read eight
// independent loads at a time, and the elements' rows and flags eight elements at a time, rather
// than entry by entry.
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

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
// word: kMaxStar <= 64).
TM_HD int lowest_bit(uint64_t mask) {
#if defined(__CUDA_ARCH__)
  return __ffsll(static_cast<long long>(mask)) - 1;
#else
  return __builtin_ctzll(mask);
#endif
}

}  // namespace tensormass
