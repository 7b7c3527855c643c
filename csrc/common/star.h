// A node's star (the elements that hold it: a column of node_slots [S, V], -1 past the last) read
// into one thread's memory, and a small table of ids for membership tests in it. For the kernels
// that run a thread per node over its star (the cut on the device, the node graph's rebuilt rows):
// such a thread's time is the latency of its loads, so the column is read whole, eight independent
// loads at a time, rather than entry by entry up to the first -1.
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

// The column `node` of node_slots into star [num_slots] (the caller checked num_slots against its
// capacity); returns the count of elements before the first -1.
template <typename I>
TM_HD int load_star(const I* node_slots, int64_t num_slots, int64_t num_nodes, int64_t node, I* star) {
  int64_t s = 0;
  for (; s + 8 <= num_slots; s += 8) {
    I eight[8];
    for (int k = 0; k < 8; ++k) eight[k] = node_slots[(s + k) * num_nodes + node];
    for (int k = 0; k < 8; ++k) star[s + k] = eight[k];
  }
  for (; s < num_slots; ++s) star[s] = node_slots[s * num_nodes + node];
  int count = 0;
  while (count < num_slots && star[count] >= 0) ++count;
  return count;
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
