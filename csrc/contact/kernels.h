// The per-query kernel of the contact broad phase (ops.h). The spatial hash itself is built by
// tensor ops (ops/contact.py: hash_queries): the surface triangles' boxes, grown by the reach,
// each listed once in every cell they cover, sorted by the cells' hash key; each query is a
// (surface vertex, one cell its box covers) and knows the run [start, stop) of the entries whose
// key is its cell's. This kernel walks a query's run without materialising it (as tensor ops,
// every entry of every run would be, then filtered) and keeps a (vertex, triangle) candidate where
//   - the entry's cell is the query's cell (keys of distinct cells may collide),
//   - the vertex's box meets the triangle's grown box,
//   - the low corner of the boxes' intersection lies in the query's cell (a pair that meets in
//     several cells both boxes cover is kept once),
//   - the triangle is another body's, unless same-body pairs are asked for (self-contact, whose
//     own filter the caller applies).
// Two passes: the count (counts[q]) and the fill at offsets[q] (an exclusive prefix sum of the
// counts), each candidate written by its query's thread in run order. So the output is the
// reference's order (query by query, entries in run order), deterministic, with no atomics.
// Item i serves query query_order[i]: the caller orders the queries by their run, so that the
// items of one warp walk the same entries together (one load serves them all) instead of as many
// runs as lanes; where each query's output goes does not depend on it.
// With triangle_first (the triangles in body order, body b's triangle_first[b] ..
// triangle_first[b + 1] - 1; not with same_body) a query skips its own body's entries: a run lists
// its entries in triangle order (hash_queries' stable sort), so they are one stretch of it, found
// by two binary searches (43 % of a settled pile's entries walked, but the cheap ones to reject:
// 8 % of the walk's time there). What is kept, and its order, are those of the whole walk.
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

template <typename S>
struct CandidatesKernel {
  const S* cell;                   // [1] the hash cell's side
  const S* point_low;              // [Sv, 3] each surface vertex's box
  const S* point_high;             // [Sv, 3]
  const int64_t* vertex_object;    // [Sv] each surface vertex's body
  const int64_t* query_vertex;     // [Q] into the surface vertices
  const int64_t* query_cells;      // [Q, 3] integer cells
  const int64_t* query_start;      // [Q] the first entry of the query's key
  const int64_t* query_stop;       // [Q] one past the last
  const int64_t* query_order;      // [Q] the query each item serves (a permutation)
  const int64_t* entry_triangle;   // [E] the triangle of each entry (entries sorted by key)
  const int64_t* entry_cells;      // [E, 3]
  const S* low;                    // [F, 3] the triangles' boxes, grown by the reach
  const S* high;                   // [F, 3]
  const int64_t* triangle_object;  // [F]
  bool same_body;                  // keep pairs of one body (self-contact)
  const int64_t* triangle_first;   // [B + 1] or nullptr: each body's first triangle (own entries skipped)
  const int64_t* offsets;          // [Q] fill pass: where query q's candidates start; nullptr: count pass
  int64_t* counts;                 // [Q] count pass
  int64_t* vertex_out;             // [C] fill pass
  int64_t* triangle_out;           // [C]

  // The query's own values, read once (a walk reads them for every entry otherwise).
  struct Query {
    int64_t cells[3];
    S low[3], high[3];
    int64_t object;
  };

  TM_HD bool kept(const Query& query, int64_t e) const {
    const int64_t t = entry_triangle[e];
    if (!same_body && query.object == triangle_object[t]) return false;
    bool ok = true;
    TM_UNROLL for (int k = 0; k < 3; ++k) {
      const S tl = low[t * 3 + k];
      const S corner = query.low[k] > tl ? query.low[k] : tl;
      ok = ok && entry_cells[e * 3 + k] == query.cells[k] && query.low[k] <= high[t * 3 + k] &&
           query.high[k] >= tl && static_cast<int64_t>(tm_floor(corner / cell[0])) == query.cells[k];
    }
    return ok;
  }

  // The first entry of [begin, end) whose triangle is at least t (the run's entries in triangle order).
  TM_HD int64_t first_at_or_past(int64_t begin, int64_t end, int64_t t) const {
    while (begin < end) {
      const int64_t mid = begin + (end - begin) / 2;
      if (entry_triangle[mid] < t) {
        begin = mid + 1;
      } else {
        end = mid;
      }
    }
    return begin;
  }

  TM_HD void operator()(int64_t item) const {
    const int64_t q = query_order[item];
    const int64_t v = query_vertex[q];
    Query query;
    TM_UNROLL for (int k = 0; k < 3; ++k) {
      query.cells[k] = query_cells[q * 3 + k];
      query.low[k] = point_low[v * 3 + k];
      query.high[k] = point_high[v * 3 + k];
    }
    query.object = vertex_object[v];
    const int64_t start = query_start[q], stop = query_stop[q];
    int64_t own_begin = stop, own_end = stop;  // the stretch of the query's own body's entries
    if (triangle_first != nullptr) {
      own_begin = first_at_or_past(start, stop, triangle_first[query.object]);
      own_end = first_at_or_past(own_begin, stop, triangle_first[query.object + 1]);
    }
    if (offsets == nullptr) {
      int64_t n = 0;
      for (int64_t e = start; e < stop; ++e) {
        if (e == own_begin) e = own_end;
        if (e >= stop) break;
        n += kept(query, e) ? 1 : 0;
      }
      counts[q] = n;
      return;
    }
    int64_t at = offsets[q];
    for (int64_t e = start; e < stop; ++e) {
      if (e == own_begin) e = own_end;
      if (e >= stop) break;
      if (kept(query, e)) {
        vertex_out[at] = v;
        triangle_out[at] = entry_triangle[e];
        ++at;
      }
    }
  }
};

// ------------------------------------------------------------------------- narrow phase

// The point of triangle (a, b, c) closest to p: its barycentric weights w, p minus it (diff), its
// distance d and the triangle's unit normal (b - a) x (c - a). The projection onto the plane where
// it falls inside the triangle, else the nearest of the three edges' closest points (a degenerate
// triangle: its edges). The same formulas, in the same order, as mesh.distance.closest_point.
// diff is (p - a) - w_b (b - a) - w_c (c - a) (w_a = 1 - w_b - w_c): differences of nearby points
// are exact, so its error is the rounding's of the triangle's size, not of the coordinates' (p -
// sum w_i x_i lost all of a resting pair's micrometre in float32 a metre from the origin, and the
// pair's direction diff / d with it).
template <typename S>
struct TriangleClosest {
  S w[3], diff[3], d, normal[3];
};

template <typename S>
TM_HD S dot3_(const S* u, const S* v) {
  return u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
}

template <typename S>
TM_HD void closest_on_edge(const S* p, const S* start, const S* end, S tiny, S& t, S& dist_sq) {
  S e[3], ps[3];
  TM_UNROLL for (int k = 0; k < 3; ++k) {
    e[k] = end[k] - start[k];
    ps[k] = p[k] - start[k];
  }
  const S ee = dot3_(e, e);
  t = dot3_(ps, e) / (ee > tiny ? ee : tiny);
  t = t < S(0) ? S(0) : (t > S(1) ? S(1) : t);
  dist_sq = S(0);
  TM_UNROLL for (int k = 0; k < 3; ++k) {
    const S r = ps[k] - t * e[k];
    dist_sq += r * r;
  }
}

template <typename S>
TM_HD TriangleClosest<S> triangle_closest(const S* p, const S* a, const S* b, const S* c, S tiny) {
  TriangleClosest<S> out;
  S ab[3], ac[3], ap[3];
  TM_UNROLL for (int k = 0; k < 3; ++k) {
    ab[k] = b[k] - a[k];
    ac[k] = c[k] - a[k];
    ap[k] = p[k] - a[k];
  }
  const S d00 = dot3_(ab, ab), d01 = dot3_(ab, ac), d11 = dot3_(ac, ac), d20 = dot3_(ap, ab), d21 = dot3_(ap, ac);
  const S denom = d00 * d11 - d01 * d01;
  const S safe = denom > S(0) ? denom : S(1);
  const S wb = (d11 * d20 - d01 * d21) / safe;
  const S wc = (d00 * d21 - d01 * d20) / safe;
  const S wa = S(1) - wb - wc;
  if (denom > S(1e-12) * d00 * d11 && wa >= S(0) && wb >= S(0) && wc >= S(0)) {
    out.w[0] = wa;
    out.w[1] = wb;
    out.w[2] = wc;
  } else {
    S t_ab, d_ab, t_ac, d_ac, t_bc, d_bc;
    closest_on_edge(p, a, b, tiny, t_ab, d_ab);
    closest_on_edge(p, a, c, tiny, t_ac, d_ac);
    closest_on_edge(p, b, c, tiny, t_bc, d_bc);
    if (d_bc < (d_ab < d_ac ? d_ab : d_ac)) {
      out.w[0] = S(0);
      out.w[1] = S(1) - t_bc;
      out.w[2] = t_bc;
    } else if (d_ab <= d_ac) {
      out.w[0] = S(1) - t_ab;
      out.w[1] = t_ab;
      out.w[2] = S(0);
    } else {
      out.w[0] = S(1) - t_ac;
      out.w[1] = S(0);
      out.w[2] = t_ac;
    }
  }
  S cross[3] = {ab[1] * ac[2] - ab[2] * ac[1], ab[2] * ac[0] - ab[0] * ac[2], ab[0] * ac[1] - ab[1] * ac[0]};
  const S norm = tm_sqrt(dot3_(cross, cross));
  const S inv = S(1) / (norm > tiny ? norm : tiny);
  S dist_sq = S(0);
  TM_UNROLL for (int k = 0; k < 3; ++k) {
    out.diff[k] = ap[k] - (out.w[1] * ab[k] + out.w[2] * ac[k]);
    out.normal[k] = cross[k] * inv;
    dist_sq += out.diff[k] * out.diff[k];
  }
  out.d = tm_sqrt(dist_sq);
  return out;
}

// What one surface vertex keeps of one other body: the nearest of its candidate triangles of that
// body within the reach, the lowest triangle id among those tied with it (within `rounding`), and
// the sum of the tied triangles' normals (the pseudonormal that decides the side).
template <typename S>
struct NearestSlot {
  int64_t body, triangle, position;
  S least, pseudo[3];
  TriangleClosest<S> closest;
};

// The most bodies one surface vertex may be near at once; a vertex near more is reported (count
// -1) and the caller takes the reference for the whole detection.
constexpr int kNearestSlots = 8;
constexpr int64_t kNoPair = -1;
constexpr int64_t kSeveralPairs = -2;

// One surface vertex an item: over its run of candidates [first[s], first[s + 1]) (the broad
// phase's, grouped by vertex), for each other body the nearest triangle within the reach
// (body_contact.SurfaceContact.nearby: the reach grows by what the pair may close over the step
// when `spread` is given), its side by the pseudonormal of the triangles tied with it, and only
// pairs nearer than the plain reach by the ties' rounding, or outside. Count pass (offsets == nullptr): how many
// pairs the vertex keeps, -1 past kNearestSlots bodies, and in `chosen` what the fill pass needs
// not find again. Fill pass: the pairs at offsets[s], in the order of their chosen candidates in
// the run (the reference's order).
//
// `chosen[s]` (written by the count pass, read by the fill pass): kNoPair where the vertex keeps
// no pair (or is past the slots), 2 i + outside for a vertex that keeps one pair, i its chosen
// candidate's index into candidate_triangle and outside 1 for the side +1, and kSeveralPairs
// where it keeps more (the fill pass walks the run again). Most vertices keep none or one, so the
// fill pass does one closest-point query where the count pass did two per candidate; the query
// is the same call on the same inputs as the count pass's (`near`), so the pair is bit for bit
// the one a walk would write.
template <typename S>
struct NearestPairsKernel {
  const S* x;                      // [V, 3]
  const int64_t* vertices;         // [Sv] node ids
  const int64_t* vertex_object;    // [Sv]
  const int64_t* triangles;        // [F, 3] node ids
  const int64_t* triangle_object;  // [F]
  const int64_t* first;            // [Sv + 1] each vertex's run of candidates
  const int64_t* candidate_triangle;  // [C]
  const S* spread;                 // [V] each node's motion apart from its body's, or nullptr
  const S* body_step;              // [B, 3] each body's mean motion (with spread)
  S reach;                         // thickness + search
  S eps;                           // the dtype's epsilon
  S tiny;                          // the dtype's smallest normal number
  const int64_t* offsets;          // [Sv] fill pass; nullptr: count pass
  int64_t* counts;                 // [Sv] count pass
  int64_t* chosen;                 // [Sv] written by the count pass, read by the fill pass (above)
  int64_t* pair_vertex;            // [P] fill pass: into the surface vertices
  int64_t* pair_triangle;          // [P]
  S* weights;                      // [P, 3]
  S* diff;                         // [P, 3]
  S* distance;                     // [P]
  S* normal;                       // [P, 3]
  S* side;                         // [P] +-1

  TM_HD void load(int64_t node, S* out) const {
    TM_UNROLL for (int k = 0; k < 3; ++k) out[k] = x[node * 3 + k];
  }

  // The candidate's closest point and whether it is within its reach.
  TM_HD bool near(const S* p, int64_t node, int64_t body, int64_t t, TriangleClosest<S>& cp) const {
    S a[3], b[3], c[3];
    const int64_t* tri = triangles + t * 3;
    load(tri[0], a);
    load(tri[1], b);
    load(tri[2], c);
    cp = triangle_closest<S>(p, a, b, c, tiny);
    S limit = reach;
    if (spread != nullptr) {
      const S s0 = spread[tri[0]], s1 = spread[tri[1]], s2 = spread[tri[2]];
      const S most = s0 > s1 ? (s0 > s2 ? s0 : s2) : (s1 > s2 ? s1 : s2);
      const int64_t other = triangle_object[t];
      S between = S(0);
      TM_UNROLL for (int k = 0; k < 3; ++k) {
        const S gap = body_step[body * 3 + k] - body_step[other * 3 + k];
        between += gap * gap;
      }
      limit = reach + spread[node] + most + tm_sqrt(between);
    }
    return cp.d < limit;
  }

  TM_HD void operator()(int64_t s) const {
    const int64_t node = vertices[s], body = vertex_object[s];
    S p[3];
    load(node, p);
    const S largest = tm_abs(p[0]) > tm_abs(p[1]) ? (tm_abs(p[0]) > tm_abs(p[2]) ? tm_abs(p[0]) : tm_abs(p[2]))
                                                  : (tm_abs(p[1]) > tm_abs(p[2]) ? tm_abs(p[1]) : tm_abs(p[2]));
    const S rounding = S(32) * eps * (largest + reach);
    TriangleClosest<S> cp;
    if (offsets != nullptr) {
      const int64_t pick = chosen[s];
      if (pick == kNoPair) return;
      if (pick >= 0) {  // one pair, its candidate and side known
        const int64_t i = pick >> 1, t = candidate_triangle[i];
        near(p, node, body, t, cp);
        write(offsets[s], s, t, cp, (pick & 1) ? S(1) : S(-1));
        return;
      }
    }
    NearestSlot<S> slot[kNearestSlots];
    int used = 0;
    // pass 1: each body's least distance
    for (int64_t i = first[s]; i < first[s + 1]; ++i) {
      const int64_t t = candidate_triangle[i];
      if (!near(p, node, body, t, cp)) continue;
      const int64_t other = triangle_object[t];
      int k = 0;
      while (k < used && slot[k].body != other) ++k;
      if (k == used) {
        if (used == kNearestSlots) {
          if (offsets == nullptr) {
            counts[s] = -1;
            chosen[s] = kNoPair;
          }
          return;
        }
        slot[k].body = other;
        slot[k].least = cp.d;
        slot[k].triangle = INT64_MAX;
        slot[k].pseudo[0] = slot[k].pseudo[1] = slot[k].pseudo[2] = S(0);
        ++used;
      } else if (cp.d < slot[k].least) {
        slot[k].least = cp.d;
      }
    }
    // pass 2: the tied triangles' normals summed, the lowest tied triangle chosen
    for (int64_t i = first[s]; i < first[s + 1]; ++i) {
      const int64_t t = candidate_triangle[i];
      if (!near(p, node, body, t, cp)) continue;
      const int64_t other = triangle_object[t];
      int k = 0;
      while (slot[k].body != other) ++k;
      if (!(cp.d <= slot[k].least + rounding)) continue;
      TM_UNROLL for (int c = 0; c < 3; ++c) slot[k].pseudo[c] += cp.normal[c];
      if (t < slot[k].triangle) {
        slot[k].triangle = t;
        slot[k].position = i;
        slot[k].closest = cp;
      }
    }
    int kept = 0;
    bool keep[kNearestSlots];
    S sides[kNearestSlots];
    for (int k = 0; k < used; ++k) {
      const TriangleClosest<S>& c = slot[k].closest;
      sides[k] = dot3_(slot[k].pseudo, c.diff) >= S(0) ? S(1) : S(-1);
      // within the rounding of the reach a triangle tied with the chosen one may lie just past
      // the limit and be left out of the pseudonormal, and past the reach (swept) the candidates
      // need not hold every nearer triangle: there a pair is kept only outside (the reference's
      // `trusted`)
      keep[k] = c.d < reach - rounding || sides[k] > S(0);
      kept += keep[k] ? 1 : 0;
    }
    if (offsets == nullptr) {
      counts[s] = kept;
      int64_t pick = kept == 0 ? kNoPair : kSeveralPairs;
      for (int k = 0; k < used && kept == 1; ++k) {
        if (keep[k]) pick = 2 * slot[k].position + (sides[k] > S(0) ? 1 : 0);
      }
      chosen[s] = pick;
      return;
    }
    int64_t at = offsets[s];
    for (int written = 0; written < kept; ++written) {  // in the order of the chosen candidates
      int best = -1;
      for (int k = 0; k < used; ++k) {
        if (keep[k] && (best < 0 || slot[k].position < slot[best].position)) best = k;
      }
      keep[best] = false;
      write(at, s, slot[best].triangle, slot[best].closest, sides[best]);
      ++at;
    }
  }

  // The fill pass's pair at `at`: vertex s, triangle t, its closest point c, its side.
  TM_HD void write(int64_t at, int64_t s, int64_t t, const TriangleClosest<S>& c, S outside) const {
    pair_vertex[at] = s;
    pair_triangle[at] = t;
    TM_UNROLL for (int k = 0; k < 3; ++k) {
      weights[at * 3 + k] = c.w[k];
      diff[at * 3 + k] = c.diff[k];
      normal[at * 3 + k] = c.normal[k];
    }
    distance[at] = c.d;
    side[at] = outside;
  }
};

// ----------------------------------------------------------------------- the pairs' product

// The pairs' part of a step's matrix times dx (body_contact.PairStiffness): per pair c,
//   r = J dx = sum_i coef[c][i] dx[nodes[c][i]],  vector[c] = b r + (a - b) (u . r) u,
// then each node sums coef[c][i] vector[c] over its entries (c, i), in the order `order` lists
// them (sorted by node once per load: order[offsets[v]:offsets[v + 1]] are node v's, as 4 c + i).
// Two kernels, no atomics: the sums are deterministic. Padding pairs (zero coefficients) give
// zero vectors, and their entries lie past every node's run.
template <typename S>
struct PairVectorKernel {
  const S* dx;         // [V, 3]
  const int64_t* nodes;  // [C, 4]
  const S* coef;       // [C, 4]
  const S* direction;  // [C, 3]
  const S* normal;     // [C] a
  const S* friction;   // [C] b
  S* vector;           // [C, 3]

  TM_HD void operator()(int64_t c) const {
    S r[3] = {S(0), S(0), S(0)};
    TM_UNROLL for (int i = 0; i < 4; ++i) {
      const S w = coef[c * 4 + i];
      const int64_t n = nodes[c * 4 + i];
      TM_UNROLL for (int k = 0; k < 3; ++k) r[k] += w * dx[n * 3 + k];
    }
    const S* u = direction + c * 3;
    const S along = r[0] * u[0] + r[1] * u[1] + r[2] * u[2];
    const S b = friction[c], a_minus_b = normal[c] - friction[c];
    TM_UNROLL for (int k = 0; k < 3; ++k) vector[c * 3 + k] = b * r[k] + a_minus_b * along * u[k];
  }
};

template <typename S>
struct PairGatherKernel {
  const S* coef;           // [C, 4]
  const S* vector;         // [C, 3]
  const int64_t* order;    // [4 C]
  const int64_t* offsets;  // [V + 1]
  S* out;                  // [V, 3]
  bool accumulate;         // out[v] += the sum (a node with no entry left as it is), else out[v] = it

  TM_HD void operator()(int64_t v) const {
    const int64_t begin = offsets[v], end = offsets[v + 1];
    if (accumulate && begin == end) return;
    S sum[3] = {S(0), S(0), S(0)};
    for (int64_t e = begin; e < end; ++e) {
      const int64_t entry = order[e], c = entry / 4;
      const S w = coef[entry];
      TM_UNROLL for (int k = 0; k < 3; ++k) sum[k] += w * vector[c * 3 + k];
    }
    TM_UNROLL for (int k = 0; k < 3; ++k) out[v * 3 + k] = accumulate ? out[v * 3 + k] + sum[k] : sum[k];
  }
};

}  // namespace tensormass
