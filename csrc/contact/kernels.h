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
  const int64_t* entry_triangle;   // [E] the triangle of each entry (entries sorted by key)
  const int64_t* entry_cells;      // [E, 3]
  const S* low;                    // [F, 3] the triangles' boxes, grown by the reach
  const S* high;                   // [F, 3]
  const int64_t* triangle_object;  // [F]
  bool same_body;                  // keep pairs of one body (self-contact)
  const int64_t* offsets;          // [Q] fill pass: where query q's candidates start; nullptr: count pass
  int64_t* counts;                 // [Q] count pass
  int64_t* vertex_out;             // [C] fill pass
  int64_t* triangle_out;           // [C]

  TM_HD bool kept(int64_t q, int64_t v, int64_t e) const {
    const int64_t t = entry_triangle[e];
    if (!same_body && vertex_object[v] == triangle_object[t]) return false;
    bool ok = true;
    TM_UNROLL for (int k = 0; k < 3; ++k) {
      const int64_t qc = query_cells[q * 3 + k];
      const S pl = point_low[v * 3 + k], tl = low[t * 3 + k];
      const S corner = pl > tl ? pl : tl;
      ok = ok && entry_cells[e * 3 + k] == qc && pl <= high[t * 3 + k] && point_high[v * 3 + k] >= tl &&
           static_cast<int64_t>(tm_floor(corner / cell[0])) == qc;
    }
    return ok;
  }

  TM_HD void operator()(int64_t q) const {
    const int64_t v = query_vertex[q];
    if (offsets == nullptr) {
      int64_t n = 0;
      for (int64_t e = query_start[q]; e < query_stop[q]; ++e) n += kept(q, v, e) ? 1 : 0;
      counts[q] = n;
      return;
    }
    int64_t at = offsets[q];
    for (int64_t e = query_start[q]; e < query_stop[q]; ++e) {
      if (kept(q, v, e)) {
        vertex_out[at] = v;
        triangle_out[at] = entry_triangle[e];
        ++at;
      }
    }
  }
};

}  // namespace tensormass
