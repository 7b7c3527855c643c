// The multigrid family's kernels (ops.h): products of block-sparse matrices (BSR: blocks of R x C
// values, the blocks of a block row listed by row_ptr / block_cols) with a vector, ending in one
// of two epilogues, written once for the CPU and CUDA.
//
// A block row's product is summed by a group of G threads (G = 1 on the CPU): lane l takes the
// row's blocks l, l + G, l + 2G, ... in order, and the lanes' partial sums are then added in a
// fixed tree (the CUDA launcher's shuffles). So for one matrix and one G the result does not
// depend on timing: deterministic, no atomics. The CPU (G = 1) sums in block order; the two
// agree to rounding.
#pragma once

#include <cstdint>

#include "common/element_math.h"
#include "common/rigid_modes.h"

namespace tensormass {

// The blocks of one BSR matrix and how to sum a block row.
template <int R, int C, typename S>
struct BsrRows {
  const S* values;           // [nb, R, C]
  const int32_t* block_cols; // [nb]
  const int32_t* row_ptr;    // [Rb + 1]

  // out[i] = sum over the blocks k = row_ptr[row] + lane, + stride, ... of (block k x)_i
  TM_HD void partial(int64_t row, int lane, int stride, const S* x, S (&out)[R]) const {
    TM_UNROLL for (int i = 0; i < R; ++i) out[i] = S(0);
    const int32_t end = row_ptr[row + 1];
    for (int32_t k = row_ptr[row] + lane; k < end; k += stride) {
      const S* block = values + static_cast<int64_t>(k) * (R * C);
      const S* xc = x + static_cast<int64_t>(block_cols[k]) * C;
      S xv[C];
      TM_UNROLL for (int j = 0; j < C; ++j) xv[j] = xc[j];
      TM_UNROLL for (int i = 0; i < R; ++i) {
        TM_UNROLL for (int j = 0; j < C; ++j) out[i] += block[i * C + j] * xv[j];
      }
    }
  }
};

// multigrid_bsr_gemv: out = alpha A x + beta y (y absent: alpha A x). out may be y (each row reads
// its own entries of y before writing them) but not x.
template <int R, int C, typename S>
struct BsrGemvKernel {
  static constexpr int kRows = R;
  using Scalar = S;
  BsrRows<R, C, S> a;
  const S* x;  // [Cb C]
  const S* y;  // [Rb R] or nullptr
  S alpha, beta;
  S* out;      // [Rb R]

  TM_HD void partial(int64_t row, int lane, int stride, S (&sum)[R]) const { a.partial(row, lane, stride, x, sum); }

  TM_HD void finish(int64_t row, const S (&sum)[R]) const {
    TM_UNROLL for (int i = 0; i < R; ++i) {
      const int64_t j = row * R + i;
      out[j] = y != nullptr ? alpha * sum[i] + beta * y[j] : alpha * sum[i];
    }
  }
};

// multigrid_chebyshev: one step of Chebyshev iteration for A x = b scaled by D^-1:
//   r = b - A x (A a BSR matrix), or b - product (the product A x given), or b (x absent: x = 0)
//   step = a step + c D^-1 r   (a = 0: the first step, step's old values not read)
//   x_out = x + step           (x absent: step)
// x_out must not be x where A is given (other rows read x); elsewhere it may.
template <int R, int C, typename S>
struct ChebyshevKernel {
  static constexpr int kRows = R;
  using Scalar = S;
  BsrRows<R, C, S> a;  // values nullptr: no matrix
  const S* product;    // [n] or nullptr
  const S* b;          // [n]
  const S* inverse_diagonal;  // [n]
  const S* x;          // [n] or nullptr (zero)
  S* step;             // [n]
  S* x_out;            // [n]
  S coef_a, coef_c;

  TM_HD void partial(int64_t row, int lane, int stride, S (&sum)[R]) const {
    if (a.values != nullptr && x != nullptr) {
      a.partial(row, lane, stride, x, sum);
    } else {
      TM_UNROLL for (int i = 0; i < R; ++i) sum[i] = S(0);
    }
  }

  TM_HD void finish(int64_t row, const S (&sum)[R]) const {
    TM_UNROLL for (int i = 0; i < R; ++i) {
      const int64_t j = row * R + i;
      S r = b[j];
      if (a.values != nullptr && x != nullptr) {
        r -= sum[i];
      } else if (product != nullptr) {
        r -= product[j];
      }
      S s = coef_c * inverse_diagonal[j] * r;
      if (coef_a != S(0)) s += coef_a * step[j];
      step[j] = s;
      x_out[j] = x != nullptr ? x[j] + s : s;
    }
  }
};

// Block Jacobi's scaling (solver/preconditioner.py, JacobiScaling): for each symmetric d x d block
// A = L L^T (its lower triangle read), S = L^-T, S^T = L^-1 and S^-1 = L^T, the identity for all
// three where a pivot is not positive (a node with no mass and no element, whose row CG never
// moves). A column-by-column Cholesky, then L^-1 by forward substitution: the reference's
// operations in its order (preconditioner.block_cholesky_scaling). One block an item.
template <int D, typename S>
struct BlockCholeskyKernel {
  const S* blocks;  // [n, D, D]
  S* scale;         // [n, D, D] S = L^-T
  S* scale_t;       // [n, D, D] S^T = L^-1
  S* inverse;       // [n, D, D] S^-1 = L^T
  S tiny;           // the dtype's smallest normal number (a pivot's floor before its root)

  TM_HD void operator()(int64_t n) const {
    const S* a = blocks + n * (D * D);
    S lower[D][D];
    S inv[D][D];
    bool positive = true;
    TM_UNROLL for (int i = 0; i < D; ++i) {
      TM_UNROLL for (int j = 0; j < D; ++j) lower[i][j] = inv[i][j] = S(0);
    }
    TM_UNROLL for (int j = 0; j < D; ++j) {
      S squares = S(0);
      TM_UNROLL for (int k = 0; k < j; ++k) squares += lower[j][k] * lower[j][k];
      const S pivot = a[j * D + j] - squares;
      positive = positive && pivot > S(0);
      lower[j][j] = tm_sqrt(pivot > tiny ? pivot : tiny);
      TM_UNROLL for (int i = j + 1; i < D; ++i) {
        S sum = S(0);
        TM_UNROLL for (int k = 0; k < j; ++k) sum += lower[i][k] * lower[j][k];
        lower[i][j] = (a[i * D + j] - sum) / lower[j][j];
      }
    }
    TM_UNROLL for (int j = 0; j < D; ++j) {
      inv[j][j] = S(1) / lower[j][j];
      TM_UNROLL for (int i = j + 1; i < D; ++i) {
        S sum = S(0);
        TM_UNROLL for (int k = j; k < i; ++k) sum += lower[i][k] * inv[k][j];
        inv[i][j] = -sum / lower[i][i];
      }
    }
    S* s = scale + n * (D * D);
    S* st = scale_t + n * (D * D);
    S* si = inverse + n * (D * D);
    TM_UNROLL for (int r = 0; r < D; ++r) {
      TM_UNROLL for (int c = 0; c < D; ++c) {
        const S eye = r == c ? S(1) : S(0);
        s[r * D + c] = positive ? inv[c][r] : eye;
        st[r * D + c] = positive ? inv[r][c] : eye;
        si[r * D + c] = positive ? lower[c][r] : eye;
      }
    }
  }
};

// The rigid correction's transfers: its basis at each node is common/rigid_modes.h's.
// multigrid_rigid_restrict: out_b = sum over range b's nodes of Z'_i^T r_i = (u, a x u), u = N^T r;
// a range of nodes (a body, or a run of its nodes) a row, summed by lanes as BsrRows does
// (deterministic).
template <typename S>
struct RigidRestrictKernel {
  static constexpr int kRows = 6;
  using Scalar = S;
  const S* node_inverse;     // [V, 3, 3] N, or [V] (scalar)
  bool scalar;
  const S* arm;              // [V, 3]
  const int32_t* range_ptr;  // [R + 1]: range b's nodes range_ptr[b] .. range_ptr[b + 1] - 1
  const S* r;                // [V 3]
  S* out;                    // [R 6]

  TM_HD void partial(int64_t row, int lane, int stride, S (&sum)[6]) const {
    TM_UNROLL for (int k = 0; k < 6; ++k) sum[k] = S(0);
    const int32_t end = range_ptr[row + 1];
    for (int32_t i = range_ptr[row] + lane; i < end; i += stride) {
      const S* ri = r + static_cast<int64_t>(i) * 3;
      const S* a = arm + static_cast<int64_t>(i) * 3;
      const S rv[3] = {ri[0], ri[1], ri[2]};
      S u[3];
      rigid_node_apply(node_inverse, scalar, i, rv, true, u);
      sum[0] += u[0];
      sum[1] += u[1];
      sum[2] += u[2];
      sum[3] += a[1] * u[2] - a[2] * u[1];
      sum[4] += a[2] * u[0] - a[0] * u[2];
      sum[5] += a[0] * u[1] - a[1] * u[0];
    }
  }

  TM_HD void finish(int64_t row, const S (&sum)[6]) const {
    TM_UNROLL for (int k = 0; k < 6; ++k) out[row * 6 + k] = sum[k];
  }
};

// multigrid_rigid_prolong: out_i = r_i + weight Z'_i c_b = r_i + weight N_i (t + w x a_i) (no r: 0);
// a node an item. out may be r.
template <typename S>
struct RigidProlongKernel {
  RigidMotion<S> motion;
  const S* r;  // [V 3] or nullptr
  S* out;      // [V 3]

  TM_HD void operator()(int64_t i) const {
    S moved[3];
    motion.at(i, moved);
    TM_UNROLL for (int k = 0; k < 3; ++k) out[i * 3 + k] = r != nullptr ? r[i * 3 + k] + moved[k] : moved[k];
  }
};

// Heavy-edge matching of a graph's nodes into clusters of at most `most` nodes (multigrid_match_clusters,
// solver/rigid_modes.py: the coarse correction's groups). Each round, every cluster offers its
// highest-keyed edge to another cluster that fits beside it, and two clusters whose offers are the
// same edge merge into the smaller root (a cluster's label: its smallest node). Four kernels a
// round, each item writing only its own entries (no atomics): the result does not depend on
// timing or threads. The keys are distinct, so a cluster's offer is one edge and a round merges
// each cluster at most once. A cluster's members are a list (next, -1 at its tail) from its root.
struct MatchClusters {
  const int64_t* keys;            // [E] distinct, >= 0
  const int64_t* ends;            // [E, 2]
  const int64_t* incident_ptr;    // [B + 1]
  const int64_t* incident_edges;  // [2 E]: each node's edges
  int64_t most;
  int64_t* label;      // [B] each node's root
  int64_t* size;       // [B] a root's cluster's size
  int64_t* best;       // [B] a root's offer: the largest key of its members' node offers
  int64_t* node_best;  // [B] the largest key of a node's edges to a cluster that fits
  int64_t* next;       // [B] the next member of a node's cluster, -1 at the tail
  int64_t* tail;       // [B] a root's cluster's last member
  int64_t* merged;     // [B] the root a root merges into this round (itself if none)

  TM_HD int64_t offer(int64_t e) const {
    const int64_t cu = label[ends[2 * e]], cv = label[ends[2 * e + 1]];
    return cu != cv && size[cu] + size[cv] <= most ? keys[e] : int64_t(-1);
  }
};

struct MatchInitKernel {  // per node: a cluster of its own
  MatchClusters m;
  TM_HD void operator()(int64_t b) const {
    m.label[b] = b;
    m.size[b] = 1;
    m.next[b] = -1;
    m.tail[b] = b;
  }
};

struct MatchNodeOfferKernel {  // per node
  MatchClusters m;
  TM_HD void operator()(int64_t b) const {
    int64_t top = -1;
    for (int64_t k = m.incident_ptr[b]; k < m.incident_ptr[b + 1]; ++k) {
      const int64_t o = m.offer(m.incident_edges[k]);
      top = o > top ? o : top;
    }
    m.node_best[b] = top;
  }
};

struct MatchClusterOfferKernel {  // per node; roots only
  MatchClusters m;
  TM_HD void operator()(int64_t c) const {
    if (m.label[c] != c) return;
    int64_t top = -1;
    for (int64_t n = c; n >= 0; n = m.next[n]) top = m.node_best[n] > top ? m.node_best[n] : top;
    m.best[c] = top;
    m.merged[c] = c;
  }
};

struct MatchMergeKernel {  // per edge: the edge both its clusters offer joins them
  MatchClusters m;
  TM_HD void operator()(int64_t e) const {
    const int64_t cu = m.label[m.ends[2 * e]], cv = m.label[m.ends[2 * e + 1]];
    const int64_t key = m.keys[e];
    if (cu == cv || m.best[cu] != key || m.best[cv] != key) return;  // (a best is a valid offer's key)
    const int64_t a = cu < cv ? cu : cv, b = cu < cv ? cv : cu;
    m.next[m.tail[a]] = b;
    m.tail[a] = m.tail[b];
    m.size[a] += m.size[b];
    m.merged[b] = a;
  }
};

struct MatchRelabelKernel {  // per node
  MatchClusters m;
  TM_HD void operator()(int64_t b) const { m.label[b] = m.merged[m.label[b]]; }
};

}  // namespace tensormass
