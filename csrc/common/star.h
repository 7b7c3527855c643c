// A node's column of a [S, V] table (node_slots: the elements that hold it, -1 past the last; or a
// table beside it, as a cut's group) read into one thread's memory, and a small table of ids for
// membership tests in it. For the kernels that run a thread per node over its star (the cut on the
// device, the node graph's rebuilt rows): such a thread's time is the latency of its loads, so a
// column is read whole, eight independent loads at a time, and an element's row (or flag) is read
// for eight elements at a time, rather than entry by entry.
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

// Where each id of a list sits in it: open addressing over kIdTable entries of place + 1 (0: empty),
// at most kIdTable - 1 ids. Ids of one star or one row are near each other, so id mod kIdTable
// rarely collides.
constexpr int kIdTable = 128;

struct IdTable {
  uint8_t place[kIdTable];

  TM_HD void clear() {
    for (int h = 0; h < kIdTable; ++h) place[h] = 0;
  }

  // The place of id in list (list[place] == id), or -1.
  template <typename I>
  TM_HD int find(const I* list, I id) const {
    int h = static_cast<int>(static_cast<int64_t>(id) & (kIdTable - 1));
    while (place[h] != 0) {
      if (list[place[h] - 1] == id) return place[h] - 1;
      h = (h + 1) & (kIdTable - 1);
    }
    return -1;
  }

  // Records that the list holds id (not yet recorded) at place `at` < kIdTable - 1.
  template <typename I>
  TM_HD void add(I id, int at) {
    int h = static_cast<int>(static_cast<int64_t>(id) & (kIdTable - 1));
    while (place[h] != 0) h = (h + 1) & (kIdTable - 1);
    place[h] = static_cast<uint8_t>(at + 1);
  }
};

}  // namespace tensormass
