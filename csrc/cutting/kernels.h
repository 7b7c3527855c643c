// The per-item kernels of the cut on the device (device_ops.h): the same cut as the host
// algorithm (ops.h) and its reference (tensormass_torch.mesh.cutting.cut), made of three fixed-size
// passes that read and write preallocated tables, so that a cut needs no host synchronisation and
// can run inside a captured CUDA graph.
//
// The tables (made once per mesh by tensormass_torch.ops.cutting.face_table, never resized):
//   face_elements [F, 2]   the two elements of each interior face of the mesh as built (first < second)
//   element_faces [N, n]   the face opposite local node k of element e, -1 where it is a boundary face
//   parted [F] bool        faces cut so far. A face keeps its two elements whatever the cuts do
//                          (elements are never divided), so a pair's face is "still shared" while
//                          the two elements hold the same n - 1 nodes, and "joined" while it is
//                          shared, not parted and both elements alive.
//   node_slots [S, V]      each node's elements (ids into elements), -1 past the last.
//
// Invariant the passes keep (by induction over cuts, as the reference's): around every node its
// alive elements are joined through faces not parted, or the node is on a parted face that is still
// shared; a face that is not parted is shared. So only the nodes of parted, still shared faces can
// split, and their stars are read whole.
//
// 1. CrossFacesKernel, a face an item: crossed = shared, both alive, and the segment between the
//    two centroids crosses a blade triangle (the reference's Moller-Trumbore, with its box test);
//    parted |= crossed.
// 2. MarkCutNodesKernel, a face an item, marks the nodes of the parted faces that are still
//    shared; StarJoinsKernel, a (slot, node) an item, finds for each element of a marked node's
//    star the joined faces holding the node and the slots of the elements across them; then
//    SplitStarsKernel, a node an item: a marked node's alive elements are grouped through those
//    joins (the star, at most kMaxStar elements, as the bits of a 64-bit word), the groups ranked by their
//    smallest element id (the rank-0 group keeps the node), and each star slot gets
//    group = rank * n + the node's local index (-1: an element removed, and every slot of a node
//    not marked); new_count = groups - 1.
// 3. The caller numbers the new nodes: offset = exclusive prefix sum of new_count (a node's copies
//    are numbered consecutively, nodes in order: the reference's (node, group) order).
// 4. RepointStarsKernel, a node an item: elements of rank r >= 1 get node first_new + offset + r - 1,
//    and parents of those new nodes = the node; nothing is written where the copies do not fit
//    (total > room).
// Each item writes only its own entries (a face its flags, or a 1 into its nodes' marks, the same
// value whichever face writes it; a (slot, node) its entry of group; a node its column of group, its count,
// its new nodes' parents, and in each of its elements the column that holds it), so the results do
// not depend on the order of items: deterministic, no atomics.
#pragma once

#include <cstdint>

#include "common/element_math.h"
#include "common/star.h"

namespace tensormass {
namespace cutting {

// The most elements a node's star may hold (node_slots' rows): the per-node passes hold a star in
// one thread's memory, and the groups' pass as the bits of a 64-bit word.
constexpr int kMaxStar = 64;

// The segment test's vector steps, on local arrays (element_math.h's cross3 and dot3).
template <typename S>
TM_HD void load3(const S* p, S (&r)[3]) {
  r[0] = p[0];
  r[1] = p[1];
  r[2] = p[2];
}

template <typename S>
TM_HD void sub3(const S (&a)[3], const S (&b)[3], S (&r)[3]) {
  r[0] = a[0] - b[0];
  r[1] = a[1] - b[1];
  r[2] = a[2] - b[2];
}

template <typename S>
TM_HD S norm3(const S (&a)[3]) {
  return tm_sqrt(dot3<S>(a, a));
}

// Whether elements a and b (rows of NN node ids) share NN - 1 nodes.
template <int NN, typename I>
TM_HD bool share_face(const I* a, const I* b) {
  int shared = 0;
  TM_UNROLL for (int i = 0; i < NN; ++i) {
    TM_UNROLL for (int j = 0; j < NN; ++j) shared += a[i] == b[j] ? 1 : 0;
  }
  return shared == NN - 1;
}

template <int NN, typename S, typename I>
struct CrossFacesKernel {
  const S* x;                 // [V, 3]
  const I* elements;          // [N, NN]
  const I* face_elements;     // [F, 2]
  const bool* alive;          // [N]
  const S* blade_vertices;    // [B, 3]
  int64_t num_blade_vertices; // B
  const int64_t* blade_triangles;  // [T, 3]
  int64_t num_triangles;
  S eps;                      // the dtype's machine epsilon
  bool* parted;               // [F]
  bool* crossed;              // [F]

  TM_HD void centroid(I e, S* c) const {
    c[0] = c[1] = c[2] = S(0);
    for (int a = 0; a < NN; ++a) {
      const S* p = x + static_cast<int64_t>(elements[static_cast<int64_t>(e) * NN + a]) * 3;
      c[0] += p[0];
      c[1] += p[1];
      c[2] += p[2];
    }
    c[0] /= S(NN);
    c[1] /= S(NN);
    c[2] /= S(NN);
  }

  TM_HD void operator()(int64_t f) const {
    const I e1 = face_elements[2 * f], e2 = face_elements[2 * f + 1];
    bool hit = false;
    if (alive[e1] && alive[e2] &&
        share_face<NN, I>(elements + static_cast<int64_t>(e1) * NN, elements + static_cast<int64_t>(e2) * NN)) {
      S p[3], q[3];
      centroid(e1, p);
      centroid(e2, q);
      // the blade's box: only segments whose box meets it are tested (as the reference)
      S low[3], high[3];
      for (int k = 0; k < 3; ++k) low[k] = high[k] = blade_vertices[k];
      for (int64_t j = 1; j < num_blade_vertices; ++j) {
        const S* v = blade_vertices + j * 3;
        for (int k = 0; k < 3; ++k) {
          low[k] = v[k] < low[k] ? v[k] : low[k];
          high[k] = v[k] > high[k] ? v[k] : high[k];
        }
      }
      bool close = true;
      for (int k = 0; k < 3; ++k) {
        const S lo = p[k] < q[k] ? p[k] : q[k], hi = p[k] < q[k] ? q[k] : p[k];
        close = close && lo <= high[k] && hi >= low[k];
      }
      S d[3];
      sub3<S>(q, p, d);
      const S d_norm = norm3<S>(d);
      for (int64_t t = 0; close && t < num_triangles && !hit; ++t) {
        S a[3], b[3], c[3], e1v[3], e2v[3], h[3], s[3], qv[3];
        load3<S>(blade_vertices + blade_triangles[3 * t] * 3, a);
        load3<S>(blade_vertices + blade_triangles[3 * t + 1] * 3, b);
        load3<S>(blade_vertices + blade_triangles[3 * t + 2] * 3, c);
        sub3<S>(b, a, e1v);
        sub3<S>(c, a, e2v);
        cross3<S>(d, e2v, h);
        const S det = dot3<S>(e1v, h);
        const S det_abs = det < S(0) ? -det : det;
        if (!(det_abs > eps * (d_norm * norm3<S>(e1v) * norm3<S>(e2v)))) continue;
        const S inv = S(1) / det;
        sub3<S>(p, a, s);
        const S u = inv * dot3<S>(s, h);
        cross3<S>(s, e1v, qv);
        const S v = inv * dot3<S>(d, qv);
        const S t_hit = inv * dot3<S>(e2v, qv);
        hit = u >= S(0) && v >= S(0) && u + v <= S(1) && t_hit > S(0) && t_hit < S(1);
      }
    }
    crossed[f] = hit;
    if (hit) parted[f] = true;
  }
};

// A face an item: a parted face that this blade crossed (or that recheck names) whose two elements
// are alive and still share it marks its n - 1 shared nodes (on_cut, zeroed by the caller). Several
// faces may mark one node: each writes the same 1, so the result does not depend on their order.
// Only these nodes can split: a node's elements are joined through its faces that are not parted,
// and only a face crossed now became parted since the last cut (recheck: the parted faces a cut
// before this table did not examine, each cleared once read).
template <int NN, typename I>
struct MarkCutNodesKernel {
  const I* elements;       // [N, NN]
  const I* face_elements;  // [F, 2]
  const bool* alive;       // [N]
  const bool* parted;      // [F]
  const bool* crossed;     // [F]
  bool* recheck;           // [F]
  uint8_t* on_cut;         // [V]

  TM_HD void operator()(int64_t f) const {
    const bool again = recheck[f];
    if (again) recheck[f] = false;
    if (!parted[f] || !(crossed[f] || again)) return;
    const I e1 = face_elements[2 * f], e2 = face_elements[2 * f + 1];
    if (!alive[e1] || !alive[e2]) return;
    const I* a = elements + static_cast<int64_t>(e1) * NN;
    const I* b = elements + static_cast<int64_t>(e2) * NN;
    if (!share_face<NN, I>(a, b)) return;
    for (int i = 0; i < NN; ++i) {
      for (int j = 0; j < NN; ++j) {
        if (a[i] == b[j]) on_cut[static_cast<int64_t>(a[i])] = 1;
      }
    }
  }
};

// SplitStarsKernel's first pass, a (slot s, node i) an item (item = s V + i), for the nodes
// MarkCutNodesKernel marked: the joins of the s-th element e of i's star through the faces holding
// i, packed into group[s, i] (the second pass reads and overwrites them):
//   bits 0-2           e's local index of i, or NN where e is removed or does not hold i;
//   bits 3 + 7k .. +6  for the face opposite e's local node k: 1 + the slot of the element across it
//                      in i's star where the face is joined and that element's id is above e's (each
//                      face once, from its element of smaller id), 0 otherwise.
// (3 + 7 NN <= 31 bits: non-negative in an int32.) Every other item writes -1. So a thread follows
// one element's few dependent loads, and a star's elements are examined side by side rather than
// one after another in one thread, whose time would be the sum of their latencies.
template <int NN, typename I>
struct StarJoinsKernel {
  const I* elements;       // [N, NN]
  const I* node_slots;     // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;       // V
  const bool* alive;       // [N]
  const I* element_faces;  // [N, NN]
  const I* face_elements;  // [F, 2]
  const bool* parted;      // [F]
  const uint8_t* on_cut;   // [V] MarkCutNodesKernel's
  int32_t* group;          // [num_slots, V]

  static constexpr int kField = 7;
  static_assert(3 + kField * NN <= 31, "the packed joins must fit a non-negative int32");
  static_assert(kMaxStar < (1 << kField), "a slot + 1 must fit a field");

  TM_HD int32_t joins(int64_t i, I e) const {
    I row[NN], faces[NN];
    TM_UNROLL for (int a = 0; a < NN; ++a) {
      row[a] = elements[static_cast<int64_t>(e) * NN + a];
      faces[a] = element_faces[static_cast<int64_t>(e) * NN + a];
    }
    const bool living = alive[e];
    int local = NN;
    TM_UNROLL for (int a = 0; a < NN; ++a) local = static_cast<int64_t>(row[a]) == i ? a : local;
    if (!living || local == NN) return NN;
    // the faces holding i (opposite another local node), not parted, to an element of larger id
    I others[NN];
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      const I f = faces[k];
      others[k] = -1;
      if (f < 0 || k == local) continue;
      const I a = face_elements[2 * static_cast<int64_t>(f)], b = face_elements[2 * static_cast<int64_t>(f) + 1];
      const I other = a == e ? b : a;
      if (!parted[f] && other > e) others[k] = other;
    }
    // still shared: the element across holds the same NN - 1 nodes (rows loaded together)
    I across[NN][NN];
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      TM_UNROLL for (int a = 0; a < NN; ++a) {
        across[k][a] = others[k] >= 0 ? elements[static_cast<int64_t>(others[k]) * NN + a] : I(-1);
      }
    }
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      if (others[k] >= 0 && !share_face<NN, I>(row, across[k])) others[k] = -1;
    }
    // their slots in i's star (an element not there does not hold i: the face is not shared)
    int slot[NN];
    int wanted = 0;
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      slot[k] = -1;
      wanted += others[k] >= 0 ? 1 : 0;
    }
    for (int64_t s0 = 0; wanted > 0 && s0 < num_slots; s0 += 8) {
      I eight[8];
      TM_UNROLL for (int k = 0; k < 8; ++k) eight[k] = s0 + k < num_slots ? node_slots[(s0 + k) * num_nodes + i] : I(-1);
      TM_UNROLL for (int k = 0; k < 8; ++k) {
        TM_UNROLL for (int c = 0; c < NN; ++c) {
          if (others[c] >= 0 && slot[c] < 0 && eight[k] == others[c]) {
            slot[c] = static_cast<int>(s0 + k);
            --wanted;
          }
        }
      }
      if (eight[7] < 0) break;
    }
    int32_t packed = local;
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      if (slot[k] >= 0) packed |= static_cast<int32_t>(slot[k] + 1) << (3 + kField * k);
    }
    return packed;
  }

  TM_HD void operator()(int64_t item) const {
    const int64_t i = item % num_nodes;
    int32_t out = -1;
    if (on_cut[i]) {
      const I e = node_slots[item];
      if (e >= 0) out = joins(i, e);
    }
    group[item] = out;
  }
};

// SplitStarsKernel, a node an item, after StarJoinsKernel: a marked node's alive elements grouped
// through the joins its column of group holds (the star's elements as the bits of a 64-bit word:
// each element's joined ones as a mask, each group flooded from its first element), the groups
// ranked by their smallest element id, each slot's group written over its joins;
// new_count = groups - 1 (0 for every other node, whose column StarJoinsKernel left -1).
template <int NN, typename I>
struct SplitStarsKernel {
  static_assert(kMaxStar <= 64, "a star's elements are the bits of a 64-bit word");
  const I* node_slots;     // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;       // V
  const uint8_t* on_cut;   // [V] MarkCutNodesKernel's
  int32_t* group;          // [num_slots, V]: StarJoinsKernel's joins in, the groups out
  int32_t* new_count;      // [V]

  TM_HD void operator()(int64_t i) const {
    if (!on_cut[i]) {
      new_count[i] = 0;
      return;
    }
    using Joins = StarJoinsKernel<NN, I>;
    I star[kMaxStar];
    int32_t packed[kMaxStar];
    const int count = load_star(node_slots, num_slots, num_nodes, i, star);
    load_column(group, num_slots, num_nodes, i, packed);
    uint64_t living = 0;  // the elements that take part (alive, holding i)
    for (int j = 0; j < count; ++j) living |= (packed[j] & 7) < NN ? uint64_t(1) << j : uint64_t(0);
    uint64_t joined[kMaxStar];
    for (int j = 0; j < count; ++j) joined[j] = 0;
    for (int j = 0; j < count; ++j) {
      if (!((living >> j) & 1)) continue;
      TM_UNROLL for (int k = 0; k < NN; ++k) {
        const int m = ((packed[j] >> (3 + Joins::kField * k)) & ((1 << Joins::kField) - 1)) - 1;
        if (m < 0 || m >= count || !((living >> m) & 1)) continue;  // no join, or to a removed element
        joined[j] |= uint64_t(1) << m;
        joined[m] |= uint64_t(1) << j;
      }
    }
    // the groups, each with its smallest element id, in the order of their first elements
    uint64_t members[kMaxStar];
    I least[kMaxStar];
    int groups = 0;
    for (uint64_t left = living; left != 0; ++groups) {
      const int seed = lowest_bit(left);
      uint64_t found = uint64_t(1) << seed, frontier = found;
      I smallest = star[seed];
      while (frontier != 0) {
        const int b = lowest_bit(frontier);
        frontier &= frontier - 1;
        smallest = star[b] < smallest ? star[b] : smallest;
        const uint64_t more = joined[b] & ~found;
        found |= more;
        frontier |= more;
      }
      left &= ~found;
      members[groups] = found;
      least[groups] = smallest;
    }
    // each group's rank: its place among the smallest ids
    for (int j = 0; j < count; ++j) {
      if (!((living >> j) & 1)) group[static_cast<int64_t>(j) * num_nodes + i] = -1;
    }
    for (int g = 0; g < groups; ++g) {
      int rank = 0;
      for (int h = 0; h < groups; ++h) rank += least[h] < least[g] ? 1 : 0;
      for (uint64_t bits = members[g]; bits != 0; bits &= bits - 1) {
        const int j = lowest_bit(bits);
        group[static_cast<int64_t>(j) * num_nodes + i] = rank * NN + (packed[j] & 7);
      }
    }
    new_count[i] = groups - 1 > 0 ? groups - 1 : 0;
  }
};

template <int NN, typename I>
struct RepointStarsKernel {
  const I* node_slots;       // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;         // V
  const int32_t* group;      // [num_slots, V]
  const int32_t* new_count;  // [V]
  const int64_t* offset;     // [V] exclusive prefix sum of new_count
  const int64_t* limits;     // [2]: the first new node's id, the room (new nodes that fit)
  I* elements;               // [N, NN]
  int64_t* parents;          // [P] node ids
  int64_t num_parents;       // P

  TM_HD void operator()(int64_t i) const {
    const int32_t copies = new_count[i];
    if (copies == 0) return;
    const int64_t total = offset[num_nodes - 1] + static_cast<int64_t>(new_count[num_nodes - 1]);
    if (total > limits[1] || limits[0] + total > num_parents) return;  // no room: the cut is not made
    const int64_t base = limits[0] + offset[i];
    I star[kMaxStar];
    int32_t groups[kMaxStar];
    const int count = load_star(node_slots, num_slots, num_nodes, i, star);
    load_column(group, num_slots, num_nodes, i, groups);
    for (int j = 0; j < count; ++j) {
      const int32_t g = groups[j];
      if (g < NN) continue;  // removed (-1), or rank 0: keeps the node
      elements[static_cast<int64_t>(star[j]) * NN + g % NN] = static_cast<I>(base + g / NN - 1);
    }
    for (int32_t r = 0; r < copies; ++r) parents[base + r] = i;
  }
};

// After RepointStarsKernel, a node an item (those with new_count > 0, where the cut was made): the
// node's list (its column of node_slots) keeps the elements of rank 0 and the removed ones, in order,
// and each copy's list (an empty column) gets the elements of its rank, in order: the lists a build
// of the cut mesh makes, since a build lists each node's elements in id order. The lumped masses and
// alive counts of the node and its copies are summed again from their lists (as
// topology::RefreshNodesKernel: the shares of the alive elements in list order), and every node of
// the star's elements is marked touched (the rows of the node graph that change: the node, its
// copies and their neighbours; several items may write the same 1).
template <int NN, typename S, typename I>
struct MoveListsKernel {
  const I* elements;         // [N, NN] after the cut
  const int32_t* group;      // [num_slots, V]
  const int32_t* new_count;  // [V]
  const int64_t* offset;     // [V]
  const int64_t* limits;     // [2]
  int64_t num_parents;       // P: the cut was made only where it fit (RepointStarsKernel's test)
  const S* element_share;    // [N] element mass / its node count
  const bool* alive;         // [N]
  I* node_slots;             // [num_slots, V]
  int64_t num_slots;
  int64_t num_nodes;
  S* mass;                   // [V]
  int32_t* node_elements;    // [V]
  uint8_t* touched;          // [V]

  TM_HD void operator()(int64_t i) const {
    const int32_t copies = new_count[i];
    if (copies == 0) return;
    const int64_t total = offset[num_nodes - 1] + static_cast<int64_t>(new_count[num_nodes - 1]);
    if (total > limits[1] || limits[0] + total > num_parents) return;
    const int64_t base = limits[0] + offset[i];
    // the star eight elements at a time (ids, flags, rows, groups and mass shares loaded together)
    I star[kMaxStar];
    int32_t rank[kMaxStar];
    bool living[kMaxStar];
    S share[kMaxStar];
    int count = 0;
    for (int64_t s0 = 0; s0 < num_slots; s0 += 8) {
      EightElements<NN, I> eight;
      eight.load(node_slots, num_slots, num_nodes, i, s0, alive, elements);
      int32_t groups[8];
      S shares[8];
      TM_UNROLL for (int k = 0; k < 8; ++k) {
        groups[k] = s0 + k < num_slots ? group[(s0 + k) * num_nodes + i] : -1;
        shares[k] = eight.ids[k] >= 0 ? element_share[eight.ids[k]] : S(0);
      }
      for (int k = 0; k < 8; ++k) {
        if (eight.ids[k] < 0) break;
        star[count] = eight.ids[k];
        rank[count] = groups[k] < 0 ? 0 : groups[k] / NN;
        living[count] = eight.living[k];
        share[count] = shares[k];
        ++count;
        TM_UNROLL for (int a = 0; a < NN; ++a) touched[static_cast<int64_t>(eight.rows[k][a])] = 1;
      }
      if (eight.last()) break;
    }
    for (int32_t r = 0; r <= copies; ++r) {
      const int64_t node = r == 0 ? i : base + r - 1;
      int64_t slot = 0;
      S sum = S(0);
      int32_t alive_here = 0;
      for (int j = 0; j < count; ++j) {
        if (rank[j] != r) continue;
        node_slots[slot * num_nodes + node] = star[j];
        ++slot;
        if (living[j]) {
          sum += share[j];
          ++alive_here;
        }
      }
      for (; slot < num_slots; ++slot) node_slots[slot * num_nodes + node] = I(-1);
      mass[node] = sum;
      node_elements[node] = alive_here;
    }
  }
};

// A byte of a new node's row an item: row first + r (r < count, rows = (first, count)) of a tensor
// laid out by node rows gets its parent's row, byte for byte (any dtype; values of the new nodes a
// cut made: positions, velocities, rest positions, flags).
struct CopyRowsKernel {
  const int64_t* rows;     // [2]: the first new node, how many
  const int64_t* parents;  // [P]
  int64_t row_bytes;
  uint8_t* values;         // [P', row_bytes] bytes

  TM_HD void operator()(int64_t item) const {
    const int64_t r = item / row_bytes, b = item % row_bytes;
    if (r >= rows[1]) return;
    const int64_t node = rows[0] + r;
    values[node * row_bytes + b] = values[parents[node] * row_bytes + b];
  }
};

// One item, after the new nodes were numbered (ends = the inclusive prefix sum of new_count, after a
// leading 0): the cut's rows (its first new node, how many it added: 0 where they do not fit, as
// RepointStarsKernel decides) and the status set to 1 where they do not fit.
struct CountNewNodesKernel {
  const int64_t* ends;    // [V + 1]
  int64_t num_nodes;      // V
  const int64_t* limits;  // [2]: the first new node's id, the room
  int64_t* rows;          // [2]
  int32_t* status;        // [1]

  TM_HD void operator()(int64_t) const {
    const int64_t total = ends[num_nodes];
    const bool fits = total <= limits[1];
    rows[0] = limits[0];
    rows[1] = fits ? total : 0;
    if (!fits) status[0] = 1;
  }
};

// A chunk of the solve an item: status set to 1 where its nodes now hold more slots (the sum of
// their incidences) than its captured launches were given (several items may write the same 1).
struct CheckChunksKernel {
  const int32_t* incidences;   // [V]
  const int64_t* chunk_start;  // [C + 1]: each chunk's first node, then the end
  int64_t chunk_slots;
  int32_t* status;             // [1]

  TM_HD void operator()(int64_t c) const {
    int64_t slots = 0;
    for (int64_t i = chunk_start[c]; i < chunk_start[c + 1]; ++i) slots += incidences[i];
    if (slots > chunk_slots) status[0] = 1;
  }
};

// One item, last: the cut's rows taken from the room (limits), and the outcome the host reads (the
// rows in use, the status).
struct CloseCutKernel {
  const int64_t* rows;    // [2]
  int64_t* limits;        // [2]
  const int32_t* status;  // [1]
  int64_t* outcome;       // [2]

  TM_HD void operator()(int64_t) const {
    limits[0] += rows[1];
    limits[1] -= rows[1];
    outcome[0] = limits[0];
    outcome[1] = status[0];
  }
};

}  // namespace cutting
}  // namespace tensormass
