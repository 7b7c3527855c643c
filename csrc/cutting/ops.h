// Host side of the mesh-cutting op (its schema and what it computes: schema.cpp; registered for the
// CPU by cpu.cpp): argument checks and the host algorithm of tensormass_torch.mesh.cutting.cut.
// The ops that edit the tables a cut changes (cutting_edit_element_tables, cutting_edit_edge_tables)
// have theirs in tables.h; register_cutting_ops, at the end, registers the three.
//
// The algorithm, for a blade that meets a few elements of a large mesh. R_k below is the reach:
// the largest distance along axis k from an alive element's centroid to one of its nodes.
//   one pass over all elements (at::parallel_for over fixed chunks): copy the elements into the
//     output, check the alive elements' node ids, compute their centroids (as torch's mean: the
//     nodes summed in order from 0, then divided by n) and the reach, keep the elements whose
//     centroid lies in the blade's box grown by 2 R (with R guessed beforehand from a sample of
//     the elements; where the guess falls short, a second pass looks again), and collect the
//     elements holding a node of a slit face.
//   then, on the elements near the blade only: their faces through a hash table (a face met by two
//     elements is an interior face; its centroid-to-centroid segment is tested against the blade),
//     the cut nodes' stars, their incidences joined through the faces not parted (union-find, the
//     first incidence the root), the new nodes numbered, the output re-pointed, the pairs still
//     joined listed.
// What the near elements are a superset of, and why, is said where they are chosen. Everything
// after the pass is serial; the chunks are fixed and merged in chunk order, so nothing depends on
// the number of threads.
#pragma once

#include <ATen/ATen.h>
#include <ATen/Parallel.h>
#include <torch/library.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include "common/checks.h"
#include "common/dispatch.h"
#include "cutting/tables.h"

namespace tensormass {
namespace cutting {

// ---------------------------------------------------------------------------------------------
// The floating-point steps of the reference, one for one. Each torch kernel the reference calls
// rounds its result to the dtype. Whether torch's CPU kernels of torch.linalg.cross and of the
// 2-norm over the last dimension fuse a product into the following add depends on the build torch
// dispatches to (its AVX2 and AVX512 kernels on x86-64 do, its default one does not:
// ATEN_CPU_CAPABILITY=default): torch_rounding asks them, and the steps below follow. Every other
// product is rounded on its own (`rounded` keeps the compiler from fusing it into an add where
// the target has FMA instructions).
// ---------------------------------------------------------------------------------------------

template <typename S>
inline S rounded(S v) {
#if defined(__GNUC__) && (defined(__x86_64__) || (defined(__i386__) && defined(__SSE2__)))
  __asm__("" : "+x"(v));
#elif defined(__GNUC__) && defined(__aarch64__)
  __asm__("" : "+w"(v));
#else
  volatile S held = v;
  v = held;
#endif
  return v;
}

template <typename S>
inline S product(S a, S b) {
  return rounded(a * b);
}

// How torch's cross product and norm kernels round (per dtype): fused (a b + c in one rounding,
// std::fma) or each product rounded.
struct Rounding {
  bool fused_cross = true;
  bool fused_norm = true;
};

// a b - c d, as torch.linalg.cross computes each component.
template <typename S>
inline S difference(S a, S b, S c, S d, bool fused) {
  return fused ? std::fma(a, b, -product(c, d)) : product(a, b) - product(c, d);
}

// torch.linalg.cross: r_i = a_j b_k - a_k b_j.
template <typename S>
inline void cross(const S* a, const S* b, S* r, const Rounding& rounding) {
  r[0] = difference(a[1], b[2], a[2], b[1], rounding.fused_cross);
  r[1] = difference(a[2], b[0], a[0], b[2], rounding.fused_cross);
  r[2] = difference(a[0], b[1], a[1], b[0], rounding.fused_cross);
}

// (a * b).sum(-1) over 3: the products rounded, then summed in order.
template <typename S>
inline S dot(const S* a, const S* b) {
  return (product(a[0], b[0]) + product(a[1], b[1])) + product(a[2], b[2]);
}

// a.norm(dim=-1) over 3: the squares accumulated in order from 0, then the root.
template <typename S>
inline S norm(const S* a, const Rounding& rounding) {
  if (rounding.fused_norm) return std::sqrt(std::fma(a[2], a[2], std::fma(a[1], a[1], product(a[0], a[0]))));
  return std::sqrt((product(a[0], a[0]) + product(a[1], a[1])) + product(a[2], a[2]));
}

// Asks torch's kernels once per dtype, on values for which the two ways give different results
// (in float32 and float64).
template <typename S>
Rounding torch_rounding() {
  static const Rounding rounding = [] {
    const S a[3] = {S(0.303), S(0.577), S(-0.812)}, b[3] = {S(-0.943), S(0.672), S(-0.134)};
    const S n[3] = {S(-0.145), S(0.589), S(0.872)};
    const auto options = at::TensorOptions().dtype(c10::CppTypeToScalarType<S>::value);
    auto rows = [&](const S* v) { return at::tensor({v[0], v[1], v[2], v[0], v[1], v[2]}, options).view({2, 3}); };
    const at::Tensor crossed = at::linalg_cross(rows(a), rows(b), -1).contiguous();
    const at::Tensor length = at::linalg_vector_norm(rows(n), 2, at::IntArrayRef{-1}).contiguous();
    Rounding plain;
    plain.fused_cross = plain.fused_norm = false;
    S plain_cross[3];
    cross(a, b, plain_cross, plain);
    const S* got = crossed.data_ptr<S>();
    Rounding asked;
    asked.fused_cross = !(got[0] == plain_cross[0] && got[1] == plain_cross[1] && got[2] == plain_cross[2]);
    asked.fused_norm = !(length.data_ptr<S>()[0] == norm(n, plain));
    return asked;
  }();
  return rounding;
}

// One blade triangle as _segments_cross uses it: corner a, edges e1 = b - a and e2 = c - a and
// their norms.
template <typename S>
struct BladeTriangle {
  S a[3], e1[3], e2[3], n1, n2;
};

template <typename S>
struct Blade {
  Rounding rounding;
  std::vector<BladeTriangle<S>> triangles;
  S low[3], high[3];  // the box of all the blade's vertices (blade.vertices.min(0), .max(0))
};

template <typename S>
Blade<S> make_blade(const at::Tensor& vertices, const at::Tensor& triangles) {
  const S* v = vertices.data_ptr<S>();
  const int64_t* t = triangles.data_ptr<int64_t>();
  Blade<S> blade;
  blade.rounding = torch_rounding<S>();
  for (int k = 0; k < 3; ++k) blade.low[k] = blade.high[k] = v[k];
  for (int64_t i = 1; i < vertices.size(0); ++i) {
    for (int k = 0; k < 3; ++k) {
      const S c = v[i * 3 + k];
      // as torch's min / max: a NaN wins (and stays, since no comparison with it holds)
      if (c < blade.low[k] || std::isnan(c)) blade.low[k] = c;
      if (c > blade.high[k] || std::isnan(c)) blade.high[k] = c;
    }
  }
  blade.triangles.resize(triangles.size(0));
  for (int64_t i = 0; i < triangles.size(0); ++i) {
    BladeTriangle<S>& tri = blade.triangles[i];
    const S* a = v + t[i * 3] * 3;
    const S* b = v + t[i * 3 + 1] * 3;
    const S* c = v + t[i * 3 + 2] * 3;
    for (int k = 0; k < 3; ++k) {
      tri.a[k] = a[k];
      tri.e1[k] = b[k] - a[k];
      tri.e2[k] = c[k] - a[k];
    }
    tri.n1 = norm(tri.e1, blade.rounding);
    tri.n2 = norm(tri.e2, blade.rounding);
  }
  return blade;
}

// Whether the segment p -> q crosses a blade triangle: mesh.cutting.cut_faces's box test (the
// segment's box meets the blade's; torch.minimum / maximum propagate NaN) and then
// _segments_cross's Moller-Trumbore with its tolerance |det| > eps |d| |e1| |e2|.
template <typename S>
bool segment_crosses(const S* p, const S* q, const Blade<S>& blade) {
  for (int k = 0; k < 3; ++k) {
    if (std::isnan(p[k]) || std::isnan(q[k])) return false;
    if (!(std::min(p[k], q[k]) <= blade.high[k] && std::max(p[k], q[k]) >= blade.low[k])) return false;
  }
  const S d[3] = {q[0] - p[0], q[1] - p[1], q[2] - p[2]};
  const S length = norm(d, blade.rounding);
  const S eps = std::numeric_limits<S>::epsilon();
  for (const BladeTriangle<S>& tri : blade.triangles) {
    S h[3];
    cross(d, tri.e2, h, blade.rounding);
    const S det = dot(tri.e1, h);
    // not ok: the reference's inverse is 0, hence t = 0: no hit
    if (!(std::abs(det) > eps * ((length * tri.n1) * tri.n2))) continue;
    const S inv = S(1) / det;
    const S s[3] = {p[0] - tri.a[0], p[1] - tri.a[1], p[2] - tri.a[2]};
    const S u = product(inv, dot(s, h));  // rounded before u + v, as the reference's tensors are
    S qv[3];
    cross(s, tri.e1, qv, blade.rounding);
    const S v = product(inv, dot(d, qv));
    const S t = product(inv, dot(tri.e2, qv));
    if (u >= S(0) && v >= S(0) && u + v <= S(1) && t > S(0) && t < S(1)) return true;
  }
  return false;
}

// ---------------------------------------------------------------------------------------------
// Topology helpers
// ---------------------------------------------------------------------------------------------

// The key of a face: its sorted node ids (n - 1 of them; a membrane's edge pads with -1). Packed in
// one word while node ids fit in 21 bits (the sorted ids then compare as the word does), else
// three.
struct PackedKey {
  static constexpr int64_t kLimit = (int64_t(1) << 21) - 1;  // node ids below it; the pad is kLimit
  uint64_t word;
  PackedKey() = default;
  PackedKey(int64_t a, int64_t b, int64_t c)
      : word((static_cast<uint64_t>(a) << 42) | (static_cast<uint64_t>(b) << 21) |
             static_cast<uint64_t>(c < 0 ? kLimit : c)) {}
  uint64_t hash() const { return word; }
  bool operator==(const PackedKey& o) const { return word == o.word; }
};

struct WideKey {
  int64_t a, b, c;
  WideKey() = default;
  WideKey(int64_t a_, int64_t b_, int64_t c_) : a(a_), b(b_), c(c_) {}
  uint64_t hash() const {
    return static_cast<uint64_t>(a) * 0x9E3779B97F4A7C15ull ^ static_cast<uint64_t>(b) * 0xC2B2AE3D27D4EB4Full ^
           static_cast<uint64_t>(c);
  }
  bool operator==(const WideKey& o) const { return a == o.a && b == o.b && c == o.c; }
};

// The sorted node ids of face f of an element (its nodes but node f).
template <int NN, typename I>
inline std::array<int64_t, 3> face_nodes(const I* row, int f) {
  int64_t v[NN - 1];
  for (int i = 0, j = 0; i < NN; ++i) {
    if (i != f) v[j++] = row[i];
  }
  if (NN == 3) return {{std::min(v[0], v[1]), std::max(v[0], v[1]), -1}};
  // a sorting network of three
  const int64_t a = std::min(v[0], v[1]), b = std::max(v[0], v[1]), c = v[NN - 2];
  const int64_t middle = std::min(b, c);
  return {{std::min(a, middle), std::max(a, middle), std::max(b, c)}};
}

// An open-addressing table of faces that remembers the last owner that met each: meeting a face
// returns the previous owner (-1 for the first), so that the owners of a face pair up in the order
// they come, as interior_faces pairs consecutive owners (their order: element, then local face).
// Sized for at most `capacity_for` faces (load <= 2/3).
template <class Key>
class FaceTable {
 public:
  explicit FaceTable(size_t capacity_for) {
    size_t capacity = 16;
    while (2 * capacity < 3 * capacity_for) capacity *= 2;
    mask_ = capacity - 1;
    slots_.reset(new Slot[capacity]);
    for (size_t i = 0; i < capacity; ++i) slots_[i].owner = -1;
  }

  int64_t meet(const Key& key, int64_t owner) {
    uint64_t h = key.hash();  // finished as splitmix64 does
    h = (h ^ (h >> 30)) * 0xBF58476D1CE4E5B9ull;
    h = (h ^ (h >> 27)) * 0x94D049BB133111EBull;
    h ^= h >> 31;
    for (size_t i = h & mask_;; i = (i + 1) & mask_) {
      Slot& slot = slots_[i];
      if (slot.owner < 0) {
        slot.key = key;
        slot.owner = owner;
        return -1;
      }
      if (slot.key == key) {
        const int64_t previous = slot.owner;
        slot.owner = owner;
        return previous;
      }
    }
  }

 private:
  struct Slot {
    Key key;
    int64_t owner;
  };
  size_t mask_;
  std::unique_ptr<Slot[]> slots_;
};

// How many of a's n slots hold a node of b (still_joined's and split_nodes's count); a pair shares a
// face when it is n - 1.
template <int NN, typename I>
inline int shared_slots(const I* a, const I* b) {
  int count = 0;
  for (int i = 0; i < NN; ++i) {
    bool found = false;
    for (int j = 0; j < NN; ++j) found = found || a[i] == b[j];
    count += found;
  }
  return count;
}

template <int NN, typename I>
inline int slot_of(const I* row, int64_t node) {
  int slot = 0;
  while (slot < NN - 1 && row[slot] != node) ++slot;
  return slot;
}

inline int64_t find_root(std::vector<int64_t>& parent, int64_t i) {
  while (parent[i] != i) {
    parent[i] = parent[parent[i]];
    i = parent[i];
  }
  return i;
}

// Joins the sets of i and j; the root of a set is its smallest member.
inline void join(std::vector<int64_t>& parent, int64_t i, int64_t j) {
  const int64_t a = find_root(parent, i), b = find_root(parent, j);
  if (a < b) {
    parent[b] = a;
  } else if (b < a) {
    parent[a] = b;
  }
}

struct Pair {
  int64_t first, second;
};

// A crossed face: its sorted node ids (the output's order) and its pair.
struct Crossed {
  std::array<int64_t, 3> key;
  int64_t first, second;
};

// An alive element whose centroid lies in a box around the blade.
template <typename S>
struct Near {
  int64_t element;
  S centroid[3];
};

// What a pass over a chunk of elements gathers.
template <typename S>
struct ChunkScan {
  std::array<double, 3> reach{{0.0, 0.0, 0.0}};  // the largest |node - centroid| per axis
  bool nan = false;                              // a NaN distance (the reference's radius is then NaN)
  int64_t bad = -1;                              // the first alive element with a node id out of range
  std::vector<Near<S>> near;                     // the elements in the box, in element order
  std::vector<int64_t> slit_star;                // the elements holding a slit node, in element order
};

// Elements per chunk of the parallel passes (a fixed size: their merged results do not depend on
// the number of threads).
constexpr int64_t kChunk = 2048;

// One pass over all elements in fixed chunks (at::parallel_for): the alive elements whose centroid
// (torch's mean: the nodes summed in order from 0, then divided by n) lies in [low, high]. The
// first pass (kFirst) also copies the elements into `out`, checks the node ids and measures the
// reach, and collects the stars of the nodes marked in `node_mark` (the slit's).
template <bool kFirst, typename S, typename I, int NN>
std::vector<ChunkScan<S>> scan_elements(const I* el, const bool* live, const S* xs, int64_t num_elements,
                                        int64_t num_nodes, const double* low, const double* high, I* out,
                                        const int32_t* node_mark, bool mark_stars) {
  const int64_t num_chunks = (num_elements + kChunk - 1) / kChunk;
  std::vector<ChunkScan<S>> scans(num_chunks);
  at::parallel_for(0, num_chunks, 1, [&](int64_t c0, int64_t c1) {
    for (int64_t c = c0; c < c1; ++c) {
      ChunkScan<S>& scan = scans[c];
      const int64_t begin = c * kChunk, end = std::min(num_elements, begin + kChunk);
      if (kFirst) std::memcpy(out + begin * NN, el + begin * NN, sizeof(I) * NN * (end - begin));
      std::array<double, 3> reach{{0.0, 0.0, 0.0}};
      bool nan = false;
      for (int64_t e = begin; e < end; ++e) {
        if (!live[e]) continue;
        int64_t v[NN];
        bool in_range = true;
        for (int i = 0; i < NN; ++i) {
          v[i] = static_cast<int64_t>(el[e * NN + i]);
          in_range = in_range && static_cast<uint64_t>(v[i]) < static_cast<uint64_t>(num_nodes);
        }
        if (kFirst && !in_range) {
          if (scan.bad < 0) scan.bad = e;
          continue;
        }
        Near<S> item;
        item.element = e;
        for (int k = 0; k < 3; ++k) {
          S sum = S(0), lowest = xs[v[0] * 3 + k], highest = lowest;
          for (int i = 0; i < NN; ++i) {
            const S value = xs[v[i] * 3 + k];
            sum += value;
            lowest = std::min(lowest, value), highest = std::max(highest, value);
          }
          const S centroid = sum / S(NN);
          item.centroid[k] = centroid;
          if (kFirst) {
            // the largest |node - centroid| along k (a NaN one is caught below)
            reach[k] = std::max(reach[k], std::max(static_cast<double>(highest) - static_cast<double>(centroid),
                                                   static_cast<double>(centroid) - static_cast<double>(lowest)));
          }
        }
        if (kFirst) {
          // A distance |node - centroid| is NaN only where a centroid is not finite (a NaN node,
          // or an infinite one): then look at each.
          const S finite = (item.centroid[0] - item.centroid[0]) + (item.centroid[1] - item.centroid[1]) +
                           (item.centroid[2] - item.centroid[2]);
          if (std::isnan(finite)) {
            for (int i = 0; i < NN; ++i) {
              for (int k = 0; k < 3; ++k) nan = nan || std::isnan(xs[v[i] * 3 + k] - item.centroid[k]);
            }
          }
          if (mark_stars) {
            for (int i = 0; i < NN; ++i) {
              if (node_mark[v[i]] >= 0) {
                scan.slit_star.push_back(e);
                break;
              }
            }
          }
        }
        bool inside = true;
        for (int k = 0; k < 3; ++k) {
          const double value = item.centroid[k];
          inside = inside && value >= low[k] && value <= high[k];
        }
        if (inside) scan.near.push_back(item);
      }
      scan.reach = reach;
      scan.nan = nan;
    }
  });
  return scans;
}

// The interior faces of the `near` elements (those in the blade's box grown by 2 R) that the blade
// crosses, in the output's order. A face goes in only where an element on its other side could
// end a segment whose box meets the blade's: along an axis where this centroid lies above the
// blade's box, the other centroid must not (below it: likewise).
template <class Key, typename S, typename I, int NN>
std::vector<Crossed> crossed_faces(const std::vector<Near<S>>& near, const I* el, const S* xs, const Blade<S>& blade,
                                   const std::array<double, 3>& reach, const double* low, const double* high) {
  double spread[3];
  for (int k = 0; k < 3; ++k) {
    // R_k with a margin for the rounding of the tests below (the nodes lie within R_k of the box)
    spread[k] = reach[k] * (1.0 + 1e-9) + 1e-9 * (std::max(std::abs(low[k]), std::abs(high[k])) + 2.0 * reach[k]);
  }
  std::vector<std::pair<Key, int64_t>> faces;  // (face, near position * n + face), in that order
  faces.reserve(near.size() * NN);
  for (size_t j = 0; j < near.size(); ++j) {
    const S* c = near[j].centroid;
    const I* row = el + near[j].element * NN;
    int side[3];
    bool beyond = false;
    for (int k = 0; k < 3; ++k) {
      side[k] = c[k] > blade.high[k] ? 1 : (c[k] < blade.low[k] ? -1 : 0);
      beyond = beyond || side[k] != 0;
    }
    S p[NN][3];
    if (beyond) {
      for (int i = 0; i < NN; ++i) {
        for (int k = 0; k < 3; ++k) p[i][k] = xs[static_cast<int64_t>(row[i]) * 3 + k];
      }
    }
    for (int f = 0; f < NN; ++f) {
      bool open = true;
      for (int k = 0; k < 3 && open && beyond; ++k) {
        if (side[k] == 0) continue;
        // the other centroid lies within R_k of every node of the face: at least (its highest
        // node - R_k) along k, at most (its lowest node + R_k)
        double bound = side[k] > 0 ? -std::numeric_limits<double>::infinity() : std::numeric_limits<double>::infinity();
        for (int i = 0; i < NN; ++i) {
          if (i == f) continue;
          const double v = p[i][k];
          bound = side[k] > 0 ? std::max(bound, v) : std::min(bound, v);
        }
        open = side[k] > 0 ? bound - spread[k] <= blade.high[k] : bound + spread[k] >= blade.low[k];
      }
      if (!open) continue;
      const std::array<int64_t, 3> nodes = face_nodes<NN>(row, f);
      faces.emplace_back(Key(nodes[0], nodes[1], nodes[2]), static_cast<int64_t>(j) * NN + f);
    }
  }
  std::vector<Crossed> crossed;
  FaceTable<Key> table(faces.size());
  for (const auto& face : faces) {
    const int64_t previous = table.meet(face.first, face.second);
    if (previous < 0) continue;
    const Near<S>& a = near[previous / NN];  // met earlier: the smaller element
    const Near<S>& b = near[face.second / NN];
    if (segment_crosses(a.centroid, b.centroid, blade)) {
      crossed.push_back({face_nodes<NN>(el + b.element * NN, static_cast<int>(face.second % NN)), a.element,
                         b.element});
    }
  }
  std::stable_sort(crossed.begin(), crossed.end(), [](const Crossed& a, const Crossed& b) { return a.key < b.key; });
  return crossed;
}

// Splits the cut nodes (node_mark[node] >= 0: their rank in node order, cut_nodes[rank] = node)
// over their star (the alive elements holding one, in element order): incidences (star position
// * n + slot) are joined through the faces holding a cut node that two star elements share,
// consecutive owners of a face paired as interior_faces pairs them, unless they are a parted
// pair; the root of each set is its first incidence. Each cut node's first set keeps it, each
// other one (in the order of its first incidence) gets the next new node, cut nodes in node
// order. Writes the new ids into `out`; returns the new nodes' parents.
template <class Key, typename I, int NN>
std::vector<int64_t> split_stars(const std::vector<int64_t>& star, const I* el, I* out,
                                 const std::vector<int32_t>& node_mark, const std::vector<int64_t>& cut_nodes,
                                 const std::vector<std::pair<int64_t, int64_t>>& parted, int64_t num_nodes) {
  const size_t num_cut = cut_nodes.size();
  std::vector<int64_t> parent(star.size() * NN);
  for (size_t u = 0; u < parent.size(); ++u) parent[u] = static_cast<int64_t>(u);
  std::vector<int64_t> offsets(num_cut + 1, 0);
  std::vector<std::pair<int32_t, int64_t>> incidences;  // (cut node rank, incidence), in incidence order
  std::vector<char> in_pair(star.size(), 0);  // in a parted pair: only those need the lookup
  for (const auto& pair : parted) {
    for (int64_t e : {pair.first, pair.second}) {
      const auto at = std::lower_bound(star.begin(), star.end(), e);
      if (at != star.end() && *at == e) in_pair[at - star.begin()] = 1;
    }
  }
  size_t num_faces = 0;  // the faces holding a cut node: all but the one without the node where
  for (int64_t e : star) {  // an element holds one cut node, all where it holds more
    int cut = 0;
    for (int i = 0; i < NN; ++i) cut += node_mark[el[e * NN + i]] >= 0;
    num_faces += cut == 1 ? NN - 1 : NN;
  }
  FaceTable<Key> table(num_faces);
  for (size_t j = 0; j < star.size(); ++j) {
    const I* row = el + star[j] * NN;
    int32_t rank[NN];
    int cut = 0;
    for (int i = 0; i < NN; ++i) {
      rank[i] = node_mark[row[i]];
      if (rank[i] >= 0) {
        ++cut;
        ++offsets[rank[i] + 1];
        incidences.emplace_back(rank[i], static_cast<int64_t>(j * NN + i));
      }
    }
    for (int f = 0; f < NN; ++f) {
      if (cut - (rank[f] >= 0) == 0) continue;  // the face (all nodes but f) holds no cut node
      const std::array<int64_t, 3> nodes = face_nodes<NN>(row, f);
      const int64_t previous = table.meet(Key(nodes[0], nodes[1], nodes[2]), static_cast<int64_t>(j));
      if (previous < 0) continue;
      if (in_pair[previous] && in_pair[j] &&
          std::binary_search(parted.begin(), parted.end(), std::make_pair(star[previous], star[j]))) {
        continue;
      }
      const I* other = el + star[previous] * NN;
      for (int i = 0; i < NN; ++i) {
        if (i != f && rank[i] >= 0) join(parent, previous * NN + slot_of<NN>(other, row[i]), j * NN + i);
      }
    }
  }
  // each cut node's incidences in order (a counting sort by rank keeps the incidence order)
  for (size_t m = 0; m < num_cut; ++m) offsets[m + 1] += offsets[m];
  std::vector<int64_t> listed(incidences.size());
  {
    std::vector<int64_t> fill(offsets.begin(), offsets.end() - 1);
    for (const auto& item : incidences) listed[fill[item.first]++] = item.second;
  }
  std::vector<int64_t> new_parents;
  std::vector<int64_t> group_node(parent.size());
  int64_t next_node = num_nodes;
  for (size_t m = 0; m < num_cut; ++m) {
    const int64_t node = cut_nodes[m];
    for (int64_t q = offsets[m]; q < offsets[m + 1]; ++q) {
      const int64_t u = listed[q], root = find_root(parent, u);
      if (root == u) {
        group_node[u] = q == offsets[m] ? node : next_node++;
        if (q != offsets[m]) new_parents.push_back(node);
      }
      group_node[u] = group_node[root];
      if (group_node[u] != node) out[star[u / NN] * NN + u % NN] = static_cast<I>(group_node[u]);
    }
  }
  TORCH_CHECK(next_node - 1 <= static_cast<int64_t>(std::numeric_limits<I>::max()),
              "tensormass: elements: the cut numbers nodes up to ", std::to_string(next_node - 1),
              ", past the int32 range of elements (pass int64 elements)");
  return new_parents;
}

template <typename S, typename I, int NN>
std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> cut_mesh(
    const at::Tensor& elements, const at::Tensor& alive, const at::Tensor& x, const at::Tensor& blade_vertices,
    const at::Tensor& blade_triangles, const at::Tensor& slit) {
  const int64_t num_elements = elements.size(0), num_nodes = x.size(0);
  const bool packed = num_nodes < PackedKey::kLimit;
  const I* el = elements.data_ptr<I>();
  const bool* live = alive.data_ptr<bool>();
  const S* xs = x.data_ptr<S>();
  const int64_t* slit_rows = slit.data_ptr<int64_t>();
  at::Tensor out = at::empty_like(elements, at::MemoryFormat::Contiguous);
  I* oe = out.data_ptr<I>();
  const Blade<S> blade = make_blade<S>(blade_vertices, blade_triangles);

  auto in_range = [&](int64_t e) {
    for (int i = 0; i < NN; ++i) {
      if (el[e * NN + i] < 0 || el[e * NN + i] >= num_nodes) return false;
    }
    return true;
  };
  auto out_of_range = [&](int64_t e) {
    TORCH_CHECK(false, "tensormass: elements: alive element ", std::to_string(e), " holds a node id outside [0, ",
                std::to_string(num_nodes), ") (x is [V, 3])");
  };

  // Cut nodes: the nodes of the faces the pairs share, numbered in the order they are met
  // (node_mark[node] = that number, -1 for the others; renumbered in node order before the split).
  std::vector<int32_t> node_mark(num_nodes, -1);
  std::vector<int64_t> cut_nodes;
  std::vector<std::pair<int64_t, int64_t>> parted;  // the pairs that share a face, (smaller, larger)
  auto add_pair = [&](int64_t a, int64_t b) {
    const I* ra = el + a * NN;
    const I* rb = el + b * NN;
    if (shared_slots<NN>(ra, rb) != NN - 1) return;  // no face shared: the pair is ignored
    for (int i = 0; i < NN; ++i) {
      bool shared = false;
      for (int j = 0; j < NN; ++j) shared = shared || ra[i] == rb[j];
      if (shared && node_mark[ra[i]] < 0) {
        node_mark[ra[i]] = static_cast<int32_t>(cut_nodes.size());
        cut_nodes.push_back(ra[i]);
      }
    }
    parted.emplace_back(std::min(a, b), std::max(a, b));
  };

  // the slit rows whose elements are alive (the pairs after this cut's); their nodes are marked
  // now so that the first pass collects their stars
  std::vector<Pair> slit_pairs;
  for (int64_t r = 0; r < slit.size(0); ++r) {
    const int64_t a = slit_rows[2 * r], b = slit_rows[2 * r + 1];
    if (!live[a] || !live[b]) continue;
    if (!in_range(a)) out_of_range(a);
    if (!in_range(b)) out_of_range(b);
    slit_pairs.push_back({a, b});
    add_pair(a, b);
  }
  const size_t num_slit_nodes = cut_nodes.size();

  // A guess of the reach R (below) from a sample of the elements, with a margin: the first pass
  // keeps the elements in the blade's box grown by twice the guess; where the reach it measures
  // is larger than the guess, a second pass looks again with the reach (the result is the same).
  std::array<double, 3> guess{{0.0, 0.0, 0.0}};
  {
    const int64_t stride = std::max<int64_t>(1, num_elements / 512);
    for (int64_t e = 0; e < num_elements; e += stride) {
      if (!live[e] || !in_range(e)) continue;
      for (int k = 0; k < 3; ++k) {
        S sum = S(0);
        for (int i = 0; i < NN; ++i) sum += xs[static_cast<int64_t>(el[e * NN + i]) * 3 + k];
        const S centroid = sum / S(NN);
        for (int i = 0; i < NN; ++i) {
          const double gap = std::abs(static_cast<double>(xs[static_cast<int64_t>(el[e * NN + i]) * 3 + k]) -
                                      static_cast<double>(centroid));
          guess[k] = std::max(guess[k], 1.25 * gap);
        }
      }
    }
  }
  // The blade's box grown by `times` the reach along each axis, with margins that only add
  // elements (they cover the rounding of these bounds).
  auto grown = [&](const std::array<double, 3>& reach, double times, double* low, double* high) {
    for (int k = 0; k < 3; ++k) {
      const double margin = 1e-9 * (std::abs(double(blade.low[k])) + std::abs(double(blade.high[k])) + reach[k]);
      low[k] = double(blade.low[k]) - times * reach[k] * (1.0 + 1e-9) - margin;
      high[k] = double(blade.high[k]) + times * reach[k] * (1.0 + 1e-9) + margin;
    }
  };

  // Pass 1: copy, check, centroids, the reach R_k (the largest distance along axis k of a node
  // from its element's centroid), the slit nodes' stars, the elements near the blade.
  double low[3], high[3];
  grown(guess, 2.0, low, high);
  std::vector<ChunkScan<S>> scans = scan_elements<true, S, I, NN>(el, live, xs, num_elements, num_nodes, low, high,
                                                                 oe, node_mark.data(), num_slit_nodes > 0);
  std::array<double, 3> reach{{0.0, 0.0, 0.0}};
  bool nan = false, guessed = true;
  for (const ChunkScan<S>& scan : scans) {
    if (scan.bad >= 0) out_of_range(scan.bad);
    for (int k = 0; k < 3; ++k) reach[k] = std::max(reach[k], scan.reach[k]);
    nan = nan || scan.nan;
  }
  for (int k = 0; k < 3; ++k) guessed = guessed && reach[k] <= guess[k];

  // The elements near the blade: those in its box grown by 2 R. Two elements that share a face
  // share a node, so their centroids are at most 2 R_k apart along axis k: a segment whose box
  // meets the blade's box has both ends in that box. Each node P of its face lies within R_k of
  // both ends, hence (one end below the blade's top, one above its bottom) in the blade's box
  // grown by R; every element holding P then has its centroid in the box grown by 2 R. The
  // reference finds nothing when a distance is NaN (its radius is then NaN): so does this.
  std::vector<Near<S>> near;  // in element order
  std::vector<int64_t> slit_star;
  {
    size_t gathered = 0;
    for (const ChunkScan<S>& scan : scans) {
      slit_star.insert(slit_star.end(), scan.slit_star.begin(), scan.slit_star.end());
      gathered += scan.near.size();
    }
    grown(reach, 2.0, low, high);
    if (!nan) {
      if (!guessed) {
        scans = scan_elements<false, S, I, NN>(el, live, xs, num_elements, num_nodes, low, high, oe, nullptr, false);
      }
      near.reserve(gathered);
      for (const ChunkScan<S>& scan : scans) {
        for (const Near<S>& item : scan.near) {
          bool inside = true;
          for (int k = 0; k < 3; ++k) inside = inside && item.centroid[k] >= low[k] && item.centroid[k] <= high[k];
          if (inside) near.push_back(item);
        }
      }
    }
  }
  scans.clear();

  const std::vector<Crossed> crossed = packed ? crossed_faces<PackedKey, S, I, NN>(near, el, xs, blade, reach, low, high)
                                              : crossed_faces<WideKey, S, I, NN>(near, el, xs, blade, reach, low, high);
  const int64_t num_crossed = static_cast<int64_t>(crossed.size());
  at::Tensor first = at::empty({num_crossed}, elements.options().dtype(at::kLong));
  at::Tensor second = at::empty({num_crossed}, elements.options().dtype(at::kLong));
  for (int64_t i = 0; i < num_crossed; ++i) {
    first.data_ptr<int64_t>()[i] = crossed[i].first;
    second.data_ptr<int64_t>()[i] = crossed[i].second;
  }

  // pairs: this cut's, then the alive slit rows
  std::vector<Pair> pairs;
  pairs.reserve(crossed.size() + slit_pairs.size());
  for (const Crossed& c : crossed) pairs.push_back({c.first, c.second});
  pairs.insert(pairs.end(), slit_pairs.begin(), slit_pairs.end());

  std::vector<int64_t> new_parents;
  if (num_crossed > 0) {
    for (const Crossed& c : crossed) add_pair(c.first, c.second);
    std::sort(parted.begin(), parted.end());
    parted.erase(std::unique(parted.begin(), parted.end()), parted.end());

    // The stars of the cut nodes: those of this cut's nodes are near elements whose centroid
    // lies within R of the nodes' box, those of the slit's nodes were collected by the first pass.
    double node_low[3], node_high[3];
    for (int k = 0; k < 3; ++k) {
      node_low[k] = std::numeric_limits<double>::infinity(), node_high[k] = -node_low[k];
      for (size_t m = num_slit_nodes; m < cut_nodes.size(); ++m) {
        const double v = xs[cut_nodes[m] * 3 + k];
        node_low[k] = std::min(node_low[k], v), node_high[k] = std::max(node_high[k], v);
      }
      if (num_slit_nodes == cut_nodes.size()) continue;  // no node of this cut's own: an empty box
      const double spread =
          reach[k] * (1.0 + 1e-9) + 1e-9 * (std::abs(node_low[k]) + std::abs(node_high[k]) + reach[k]);
      node_low[k] -= spread, node_high[k] += spread;
    }
    std::vector<int64_t> star;
    star.reserve(near.size() + slit_star.size());
    {
      auto holds_cut_node = [&](int64_t e) {
        for (int i = 0; i < NN; ++i) {
          if (node_mark[el[e * NN + i]] >= 0) return true;
        }
        return false;
      };
      auto around = [&](const Near<S>& item) {
        for (int k = 0; k < 3; ++k) {
          if (!(item.centroid[k] >= node_low[k] && item.centroid[k] <= node_high[k])) return false;
        }
        return holds_cut_node(item.element);
      };
      // merge the near elements around the nodes with the slit's stars, in element order
      size_t a = 0, b = 0;
      while (a < near.size() || b < slit_star.size()) {
        if (b == slit_star.size() || (a < near.size() && near[a].element < slit_star[b])) {
          if (around(near[a])) star.push_back(near[a].element);
          ++a;
        } else {
          if (a < near.size() && near[a].element == slit_star[b]) ++a;
          star.push_back(slit_star[b++]);  // holds a slit node, a cut node
        }
      }
    }
    std::sort(cut_nodes.begin(), cut_nodes.end());
    for (size_t m = 0; m < cut_nodes.size(); ++m) node_mark[cut_nodes[m]] = static_cast<int32_t>(m);
    new_parents = packed ? split_stars<PackedKey, I, NN>(star, el, oe, node_mark, cut_nodes, parted, num_nodes)
                         : split_stars<WideKey, I, NN>(star, el, oe, node_mark, cut_nodes, parted, num_nodes);
  }

  at::Tensor parents = at::empty({num_nodes + static_cast<int64_t>(new_parents.size())},
                                 elements.options().dtype(at::kLong));
  int64_t* pp = parents.data_ptr<int64_t>();
  for (int64_t i = 0; i < num_nodes; ++i) pp[i] = i;
  std::copy(new_parents.begin(), new_parents.end(), pp + num_nodes);

  // slit: the pairs whose elements still share a face
  std::vector<Pair> joined;
  for (const Pair& p : pairs) {
    if (shared_slots<NN>(oe + p.first * NN, oe + p.second * NN) == NN - 1) joined.push_back(p);
  }
  at::Tensor slit_out = at::empty({static_cast<int64_t>(joined.size()), 2}, elements.options().dtype(at::kLong));
  int64_t* so = slit_out.data_ptr<int64_t>();
  for (size_t i = 0; i < joined.size(); ++i) {
    so[2 * i] = joined[i].first;
    so[2 * i + 1] = joined[i].second;
  }
  return {out, parents, first, second, slit_out};
}

}  // namespace cutting

// ---------------------------------------------------------------------------------------------
// Argument checks and dispatch
// ---------------------------------------------------------------------------------------------

inline void check_host_tensor(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device().is_cpu(), "tensormass: ", name, " is on ", t.device().str(),
              "; cutting_cut_mesh runs on the CPU (copy the mesh there)");
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

// cutting_cut_mesh: see schema.cpp.
inline std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> cutting_cut_mesh(
    const at::Tensor& elements, const at::Tensor& alive, const at::Tensor& x, const at::Tensor& blade_vertices,
    const at::Tensor& blade_triangles, const at::Tensor& slit) {
  const at::ScalarType index_type = index_type_of(elements, "elements");
  check_host_tensor(elements, "elements");
  TORCH_CHECK(elements.dim() == 2 && (elements.size(1) == 4 || elements.size(1) == 3),
              "tensormass: elements must be [N, 4] (tetrahedra) or [N, 3] (membrane triangles), got shape ",
              shape_str(elements.sizes()));
  const int64_t num_elements = elements.size(0);
  check_host_tensor(alive, "alive");
  TORCH_CHECK(alive.scalar_type() == at::kBool, "tensormass: alive must be bool, got ",
              dtype_str(alive.scalar_type()));
  TORCH_CHECK(alive.dim() == 1 && alive.size(0) == num_elements, "tensormass: alive has shape ",
              shape_str(alive.sizes()), "; expected [", std::to_string(num_elements), "] (elements is [N, n])");
  check_host_tensor(x, "x");
  TORCH_CHECK(x.scalar_type() == at::kFloat || x.scalar_type() == at::kDouble,
              "tensormass: x must be float32 or float64, got ", dtype_str(x.scalar_type()));
  TORCH_CHECK(x.dim() == 2 && x.size(1) == 3, "tensormass: x must be [V, 3] (3-D positions), got shape ",
              shape_str(x.sizes()));
  check_host_tensor(blade_vertices, "blade_vertices");
  TORCH_CHECK(blade_vertices.scalar_type() == x.scalar_type(), "tensormass: blade_vertices is ",
              dtype_str(blade_vertices.scalar_type()), " but x is ", dtype_str(x.scalar_type()),
              " (the blade is cut at x's precision)");
  TORCH_CHECK(blade_vertices.dim() == 2 && blade_vertices.size(1) == 3 && blade_vertices.size(0) >= 1,
              "tensormass: blade_vertices must be [B >= 1, 3], got shape ", shape_str(blade_vertices.sizes()));
  check_host_tensor(blade_triangles, "blade_triangles");
  TORCH_CHECK(blade_triangles.scalar_type() == at::kLong, "tensormass: blade_triangles must be int64, got ",
              dtype_str(blade_triangles.scalar_type()));
  TORCH_CHECK(blade_triangles.dim() == 2 && blade_triangles.size(1) == 3 && blade_triangles.size(0) >= 1,
              "tensormass: blade_triangles must be [T >= 1, 3], got shape ", shape_str(blade_triangles.sizes()));
  const int64_t num_vertices = blade_vertices.size(0);
  const int64_t* tri = blade_triangles.data_ptr<int64_t>();
  for (int64_t i = 0; i < blade_triangles.numel(); ++i) {
    TORCH_CHECK(tri[i] >= 0 && tri[i] < num_vertices, "tensormass: blade_triangles holds ", std::to_string(tri[i]),
                ", outside the ", std::to_string(num_vertices), " blade_vertices");
  }
  check_host_tensor(slit, "slit");
  TORCH_CHECK(slit.scalar_type() == at::kLong, "tensormass: slit must be int64, got ", dtype_str(slit.scalar_type()));
  TORCH_CHECK(slit.dim() == 2 && slit.size(1) == 2, "tensormass: slit must be [S, 2] (element pairs), got shape ",
              shape_str(slit.sizes()));
  const int64_t* rows = slit.data_ptr<int64_t>();
  for (int64_t i = 0; i < slit.numel(); ++i) {
    TORCH_CHECK(rows[i] >= 0 && rows[i] < num_elements, "tensormass: slit holds element ", std::to_string(rows[i]),
                ", outside the ", std::to_string(num_elements), " elements");
  }
  std::tuple<at::Tensor, at::Tensor, at::Tensor, at::Tensor, at::Tensor> result;
  dispatch_scalar(x.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      if (elements.size(1) == 4) {
        result = cutting::cut_mesh<S, I, 4>(elements, alive, x, blade_vertices, blade_triangles, slit);
      } else {
        result = cutting::cut_mesh<S, I, 3>(elements, alive, x, blade_vertices, blade_triangles, slit);
      }
    });
  });
  return result;
}

// Registers the CPU implementation of the cutting op (cpu.cpp); its schema: schema.cpp.
inline void register_cutting_ops(torch::Library& m) {
  m.impl("cutting_cut_mesh", &cutting_cut_mesh);
  m.impl("cutting_edit_element_tables", &cutting_edit_element_tables);
  m.impl("cutting_edit_edge_tables", &cutting_edit_edge_tables);
}

}  // namespace tensormass
