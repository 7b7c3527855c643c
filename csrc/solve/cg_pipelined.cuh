// A whole CG solve over the hooke node graph in ONE kernel with ONE grid barrier an iteration
// (hooke_node_solve): Chronopoulos and Gear's CG, whose two inner products r.r and w.r (w = A r)
// come from the same reduction, on a persistent cooperative grid of one block per chunk.
//
// Where the time of a small system's CG iteration goes (benchmarks/probes/cg_latency_probe.py, SOFA
// beam, H100): not bytes (its 9 MB of node_k sit in L2) but chains of dependent L2 round trips
// and barriers. So, against cg_persistent.cuh:
//   - one grid barrier an iteration instead of two (the recurrence needs one reduction);
//   - the block's part of the node graph (node_k, neighbours) sits in shared memory for the
//     whole solve, read once;
//   - each node's own state (x, p, s, r, w, its mass, projection and contact stiffness) stays in
//     registers; only what neighbours read goes through memory: r, w and s in one exchange row of
//     4d values (three 16-byte loads a neighbour), double-buffered across iterations;
//   - two threads per node (kLanes), each walking half of its slots, their sums shuffled together;
//   - the object's totals are read by the whole block at once, both dots in one block reduction.
// (The probe that chose this design and its figures: docs/pipelined-cg.md.)
//
// Two layouts of the graph (the launcher takes the first that fits one wave):
//   shared    the block's slots in shared memory, two threads a node, chunks of <= 128 nodes
//             (kSolveChunkNodes): small systems, where latency is all;
//   streamed  one thread a node, chunks of <= 256 nodes (kStreamChunkNodes): graphs whose slots
//             exceed shared memory in one wave (the paper beam's 56k nodes: 220 blocks of 256 on
//             an H100's 264 resident). Each node's first slots stay in its column of shared memory
//             (as many as the SM's share holds: StreamedSlots), the rest are read from the graph's
//             arrays by row every iteration. Against the two-barrier persistent CG that served
//             these graphs, the update and both dots ride on the matvec's pass, one grid barrier
//             of two goes, and most of the graph's bytes stay on chip. Mirror rows of a chunk
//             share their slots' work (NodeSlots: the paper beam's 26- and 10-slot rows become
//             18 slots a thread), and the node's CG vectors sit in shared memory, leaving the
//             registers to the loads in flight.
//
// Where an implicit step asks (hooke_node_solve_step), the kernel also ends the step: each
// thread updates its node's velocity and position from its dv, and the object's last block
// writes the step's summary (euler_update's work without its launch). It may also begin it
// (hooke_node_steps, StepRhs): the right-hand side from the node graph it holds, each node's
// slots in slot order by one thread (hooke_node_step_rhs's values, bitwise), and then run
// several steps back to back, one grid barrier between them: the graph's shared memory, the
// launches and the gaps between kernels serve every step.
//
// The recurrence (iteration i, from r_i, w_i = A r_i, s_{i-1}, p_{i-1}, x_i; gamma_i = r_i.r_i,
// delta_i = w_i.r_i):
//   beta_i = gamma_i / gamma_{i-1} (cg_beta_step: convergence, the cap; 0 on the first step)
//   alpha_i = gamma_i / (delta_i - beta_i gamma_i / alpha_{i-1})  (cg_pipelined_alpha: breakdown)
//   p_i = r_i + beta_i p_{i-1};  s_i = w_i + beta_i s_{i-1};  x_{i+1} = x_i + alpha_i p_i
//   r_{i+1} = r_i - alpha_i s_i;  w_{i+1} = A r_{i+1}
// In exact arithmetic these are CG's iterates (s_i = A p_i); in floating point they round
// differently from the two-reduction CG of the other paths (not bitwise), and the statuses and
// counts mean the same. A neighbour's r_{i+1} is formed on the fly from its exchange row with
// the same expression (next_residual) its owner uses, so both agree bit for bit.
#pragma once

#include <cooperative_groups.h>

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <algorithm>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <type_traits>

#include "common/cg.h"
#include "common/cg_reduce.cuh"
#include "common/kernel_io.h"
#include "common/node_graph.h"
#include "common/step_rhs.h"

namespace tensormass {

constexpr int kLanes = 2;                                // threads per node
constexpr int kSolveChunkNodes = kReduceBlock / kLanes;  // nodes per chunk (Python: ops.solve.SOLVE_CHUNK_NODES)
constexpr int kSolveSlotBatch = 8;                       // slots whose loads a lane has in flight at once
constexpr int kStreamChunkNodes = kReduceBlock;          // nodes per chunk, streamed (Python: ops.solve.STREAM_CHUNK_NODES)

template <typename S>
__device__ inline S next_residual(S r, S w, S s, S alpha, S beta) {
  return fma(-alpha, fma(beta, s, w), r);
}

// One node's exchange row: r [D], w [D], s [D], padding [D] (16-byte loads).
template <int D, typename S>
struct ExchangeRow {
  static constexpr int kWidth = 4 * D;
  using Vec = std::conditional_t<sizeof(S) == 4, float4, double2>;
  static constexpr int kPerVec = 16 / sizeof(S);

  __device__ static void load(const S* row, S (&r)[D], S (&w)[D], S (&s)[D]) {
    S v[kWidth];
    TM_UNROLL for (int q = 0; q < kWidth / kPerVec; ++q) {
      const Vec chunk = reinterpret_cast<const Vec*>(row)[q];
      memcpy(v + q * kPerVec, &chunk, sizeof(Vec));
    }
    TM_UNROLL for (int a = 0; a < D; ++a) {
      r[a] = v[a];
      w[a] = v[D + a];
      s[a] = v[2 * D + a];
    }
  }

  __device__ static void store(S* row, const S (&r)[D], const S (&w)[D], const S (&s)[D]) {
    S v[kWidth];
    TM_UNROLL for (int a = 0; a < D; ++a) {
      v[a] = r[a];
      v[D + a] = w[a];
      v[2 * D + a] = s[a];
      v[3 * D + a] = S(0);
    }
    TM_UNROLL for (int q = 0; q < kWidth / kPerVec; ++q) {
      Vec chunk;
      memcpy(&chunk, v + q * kPerVec, sizeof(Vec));
      reinterpret_cast<Vec*>(row)[q] = chunk;
    }
  }
};

// The block's slots in shared memory: node_k [chunk_slots][D][D] then neighbours [chunk_slots].
template <int D, typename S>
struct SharedGraph {
  const S* node_k;
  const int32_t* neighbor;

  // acc += the elastic force terms over this lane's slots of a node (its slots from `first`,
  // `count` of them, every Stride-th from `lane`) along the field read by value(j, out[D]); wi:
  // the node's own value.
  template <int Stride, class Value>
  __device__ void add_forces(int first, int count, int lane, const S (&wi)[D], const Value& value,
                             S (&acc)[D]) const {
    for (int t0 = 0; t0 * Stride < count; t0 += kSolveSlotBatch) {
      int j[kSolveSlotBatch];
      S wj[kSolveSlotBatch][D];
      TM_UNROLL for (int q = 0; q < kSolveSlotBatch; ++q) {
        const int s = lane + (t0 + q) * Stride;
        j[q] = s < count ? neighbor[first + s] : -1;
      }
      TM_UNROLL for (int q = 0; q < kSolveSlotBatch; ++q) {
        if (j[q] >= 0) value(j[q], wj[q]);
      }
      TM_UNROLL for (int q = 0; q < kSolveSlotBatch; ++q) {
        const int s = lane + (t0 + q) * Stride;
        if (s >= count) break;
        S k[D][D], f[2][D];
        const S* slot_k = node_k + (first + s) * (D * D);  // shared memory: plain loads (ld() is global-only)
        TM_UNROLL for (int a = 0; a < D; ++a) {
          TM_UNROLL for (int b = 0; b < D; ++b) k[a][b] = slot_k[a * D + b];
        }
        tensor_hooke_edge<D, S>(k, wi, wj[q], f);
        TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += f[0][a];
      }
    }
  }
};

// One node's slots in the streamed layout (one thread a node): its first cached_neighbors
// neighbours and first cached_ks Kdir blocks in its own column of the block's shared memory, for
// the whole solve; the rest read from the graph's arrays by row every iteration (slot s of the
// row at neighbor[s * V], node_k[s * V]: consecutive rows are consecutive addresses, so a warp's
// loads of a slot coalesce). The neighbours come first: each is the head of a dependent chain
// (neighbour, then its exchange row). kBatch slots are in flight at once (the HookeNodeGraph
// matvec's pattern: a thread has one node's parallelism, its loads must not be one chain).
template <int D, typename S, typename I>
struct StreamedSlots {
  static constexpr int kBatch = 4;
  static constexpr int kColumn = kStreamChunkNodes;  // the stride of a column in shared memory
  const int32_t* cached_neighbor;  // slot s at [s * kColumn]
  const S* cached_k;               // slot s, entry e at [(s * D * D + e) * kColumn]
  int cached_neighbors, cached_ks;
  const I* neighbor;  // the row's first slot in the graph
  const S* node_k;    // the row's first slot's Kdir in the graph
  int64_t stride;     // V: from one slot of a row to the next

  __device__ int64_t neighbor_at(int s) const {
    return s < cached_neighbors ? static_cast<int64_t>(cached_neighbor[s * kColumn])
                                : static_cast<int64_t>(ld(neighbor + s * stride));
  }

  template <bool OnChip>
  __device__ void k_at(int s, S (&k)[D][D]) const {
    if (OnChip || s < cached_ks) {
      TM_UNROLL for (int a = 0; a < D; ++a) {
        TM_UNROLL for (int b = 0; b < D; ++b) k[a][b] = cached_k[(s * (D * D) + a * D + b) * kColumn];
      }
    } else {
      load_matrix<D, D, S>(node_k + s * stride * (D * D), k);
    }
  }

  // acc += the elastic force terms over the node's slots [first, end) along the field read by
  // value(j, out[D]); wi: the node's own value. The slots whose neighbour and Kdir are both on
  // chip first, in a loop with no test of where they are, then the others (slot order kept).
  template <class Value>
  __device__ void add_forces(int first, int end, const S (&wi)[D], const Value& value, S (&acc)[D]) const {
    const int on_chip = max(first, min(end, min(cached_neighbors, cached_ks)));
    add_range<true>(first, on_chip, wi, value, acc);
    add_range<false>(on_chip, end, wi, value, acc);
  }

  template <bool OnChip, class Value>
  __device__ void add_range(int first, int end, const S (&wi)[D], const Value& value, S (&acc)[D]) const {
    for (int s0 = first; s0 < end; s0 += kBatch) {
      int64_t j[kBatch];
      S k[kBatch][D][D], wj[kBatch][D];
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        j[q] = s0 + q >= end ? -1 : OnChip ? static_cast<int64_t>(cached_neighbor[(s0 + q) * kColumn]) : neighbor_at(s0 + q);
      }
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (j[q] < 0) continue;
        value(j[q], wj[q]);
        k_at<OnChip>(s0 + q, k[q]);
      }
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (s0 + q >= end) break;
        S f[2][D];
        tensor_hooke_edge<D, S>(k[q], wi, wj[q], f);
        TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += f[0][a];
      }
    }
  }
};

// A thread's share of the chunk's slots in either layout. Shared: its node's slots in the block's
// shared memory, from the node's first slot, every kLanes-th from its lane. Streamed: its node's
// rows, shared with the node of the mirror row of the chunk (row c pairs with row
// kStreamChunkNodes - 1 - c): the pair's slots are halved, the heavier row's owner walks the
// first half of its own, the other owner its own and the rest of the heavier row's, leaving that
// sum in shared memory. Rows sorted by slot count within windows (ops.node_graph.node_graph_rows) pair
// the heaviest with the lightest: on the paper beam a warp walks 18 slots instead of 26 or 10,
// and the block's warps reach its barrier together instead of half of them waiting.
template <bool InShared, int D, typename S, typename I>
struct NodeSlots {
  SharedGraph<D, S> shared;
  int first, lane;
  int count;  // the node's slots; 0 where the thread has no node (or its chunk does not fit)
  // streamed: the columns in shared memory, the graph's arrays, and the rows of this thread's
  // node and of its partner (the slots of a row: StreamedSlots, made where they are walked)
  int32_t* columns_neighbor;
  S* columns_k;
  int cached_neighbors, cached_ks;
  const I* neighbor;
  const S* node_k;
  int64_t stride;
  int column;
  int64_t row, partner_row, partner_node;
  int own_end;               // this node's slots [0, own_end) here, the rest by the partner
  int help_first, help_end;  // the partner row's slots walked here
  S (*help)[D];              // [kStreamChunkNodes][D] shared: each thread's sum over its partner's slots

  __device__ StreamedSlots<D, S, I> row_slots(int at_column, int64_t at_row) const {
    return {columns_neighbor + at_column, columns_k + at_column, cached_neighbors, cached_ks, neighbor + at_row,
            node_k + at_row * (D * D), stride};
  }

  // acc += the elastic force terms over this thread's slots along the field read by
  // value(j, out[D]); wi: the node's own value. Called by every thread of the block at once
  // (streamed: the partners' sums cross a block barrier).
  template <class Value>
  __device__ void add_forces(const S (&wi)[D], const Value& value, S (&acc)[D]) const {
    if constexpr (InShared) {
      if (count > 0) shared.template add_forces<kLanes>(first, count, lane, wi, value, acc);
    } else {
      // The partner's slots first: its sum leaves the registers before this node's slots are walked.
      const int partner_column = kStreamChunkNodes - 1 - column;
      if (help_first < help_end) {
        S wp[D], sum[D];
        value(partner_node, wp);
        TM_UNROLL for (int a = 0; a < D; ++a) sum[a] = S(0);
        row_slots(partner_column, partner_row).add_forces(help_first, help_end, wp, value, sum);
        TM_UNROLL for (int a = 0; a < D; ++a) help[partner_column][a] = sum[a];
      }
      row_slots(column, row).add_forces(0, own_end, wi, value, acc);
      __syncthreads();
      if (own_end < count) {
        TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += help[column][a];
      }
    }
  }

  // acc += the same terms over ALL of the node's slots in slot order, by one thread (lane 0; the
  // streamed layout's own thread, no partner): HookeNodeGraph::add_forces's arithmetic, bitwise
  // (the step's right-hand side: StepRhs). No barrier inside.
  template <class Value>
  __device__ void add_forces_in_order(const S (&wi)[D], const Value& value, S (&acc)[D]) const {
    if (count == 0) return;
    if constexpr (InShared) {
      if (lane == 0) shared.template add_forces<1>(first, count, 0, wi, value, acc);
    } else {
      row_slots(column, row).add_forces(0, count, wi, value, acc);
    }
  }
};

// The sum over a node's Lanes lanes (adjacent threads), in every lane.
template <int Lanes, int D, typename S>
__device__ inline void lanes_total(S (&acc)[D]) {
  TM_UNROLL for (int o = Lanes / 2; o > 0; o >>= 1) {
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += __shfl_xor_sync(0xffffffffu, acc[a], o);
  }
}

// The exclusive prefix sums of `value` over the block's threads (kReduceBlock of them), in every
// thread: a warp scan by shuffles, then one of the warp totals.
__device__ inline int32_t block_exclusive_scan(int32_t value) {
  __shared__ int32_t warp_totals[kReduceBlock / 32];
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  int32_t inclusive = value;
  for (int o = 1; o < 32; o <<= 1) {
    const int32_t up = __shfl_up_sync(0xffffffffu, inclusive, o);
    if (lane >= o) inclusive += up;
  }
  if (lane == 31) warp_totals[warp] = inclusive;
  __syncthreads();
  if (warp == 0) {
    int32_t total = lane < kReduceBlock / 32 ? warp_totals[lane] : 0;
    for (int o = 1; o < 32; o <<= 1) {
      const int32_t up = __shfl_up_sync(0xffffffffu, total, o);
      if (lane >= o) total += up;
    }
    if (lane < kReduceBlock / 32) warp_totals[lane] = total;  // inclusive over warps
  }
  __syncthreads();
  const int32_t out = inclusive - value + (warp > 0 ? warp_totals[warp - 1] : 0);
  __syncthreads();  // warp_totals may be written again
  return out;
}

// Block sums of two values, the result in thread 0 (a fixed order).
__device__ inline double2 block_sum_pair(double a, double b) {
  __shared__ double2 warp_sums[kReduceBlock / 32];
  for (int o = 16; o > 0; o >>= 1) {
    a += __shfl_down_sync(0xffffffffu, a, o);
    b += __shfl_down_sync(0xffffffffu, b, o);
  }
  if ((threadIdx.x & 31) == 0) warp_sums[threadIdx.x >> 5] = make_double2(a, b);
  __syncthreads();
  double2 t = make_double2(0.0, 0.0);
  if (threadIdx.x < 32) {
    t = threadIdx.x < kReduceBlock / 32 ? warp_sums[threadIdx.x] : t;
    for (int o = 16; o > 0; o >>= 1) {
      t.x += __shfl_down_sync(0xffffffffu, t.x, o);
      t.y += __shfl_down_sync(0xffffffffu, t.y, o);
    }
  }
  __syncthreads();  // warp_sums may be written again
  return t;
}

// The object's totals over its chunk sums (gamma, delta of one parity), in every thread: the
// whole block loads them at once (one L2 round trip), then one reduction of both.
__device__ inline double2 object_totals(const CGPlan& plan, int64_t object, const double* gamma_sums,
                                        const double* delta_sums) {
  __shared__ double2 total;
  double a = 0.0, b = 0.0;
  for (int64_t c = plan.object_chunk[object] + threadIdx.x; c < plan.object_chunk[object + 1]; c += kReduceBlock) {
    a += gamma_sums[c];
    b += delta_sums[c];
  }
  const double2 t = block_sum_pair(a, b);
  if (threadIdx.x == 0) total = t;
  __syncthreads();
  const double2 out = total;
  __syncthreads();
  return out;
}

template <class K, typename S, bool InShared>
__global__ void __launch_bounds__(kReduceBlock, 2) pipelined_cg_kernel(const K k, const CGPlan plan,
                                                                        const PipelinedSolve<S> s) {
  constexpr int D = K::kDim;
  constexpr int Lanes = InShared ? kLanes : 1;
  constexpr int ChunkNodes = kReduceBlock / Lanes;
  constexpr int W = ExchangeRow<D, S>::kWidth;
  using Row = ExchangeRow<D, S>;
  namespace coop = cooperative_groups;
  coop::grid_group grid = coop::this_grid();
  const int64_t V = plan.num_nodes, K_chunks = plan.num_chunks;
  const int tid = threadIdx.x, lane = tid % Lanes;
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  const bool first_chunk = chunk == plan.object_chunk[object];
  const int64_t begin = plan.chunk_start[chunk], end = plan.chunk_start[chunk + 1];
  const int64_t row = begin + tid / Lanes;  // of the node graph (HookeNodeGraph): the chunk's rows are its nodes
  const bool own = row < end;
  const bool single_object = plan.num_objects == 1;

  const auto& graph = k.graph;
  const int64_t i = own ? graph.node_of(row) : row;  // this thread's node
  const int count = own ? static_cast<int>(ld(graph.incidences + row)) : 0;
  // A chunk beyond the layout the caller promised (more nodes or slots) solves nothing: its
  // object's b.b is made NaN, so the object stops at the start as non-finite and says so.
  bool layout_ok = end - begin <= ChunkNodes;
  // The shared layout: the chunk's slots into shared memory, each node's first slot by a scan of
  // the slot counts (the streamed layout reads them from the graph: nothing to do).
  extern __shared__ __align__(16) unsigned char solve_shared[];
  __shared__ int32_t slot_offset[ChunkNodes + 1];
  S* shared_k = reinterpret_cast<S*>(solve_shared);
  int32_t* shared_neighbor = reinterpret_cast<int32_t*>(shared_k + s.chunk_slots * (D * D));
  int first = 0;
  if (InShared) {
    {
      const int32_t mine = lane == 0 ? count : 0;  // counted once per node
      const int32_t before = block_exclusive_scan(mine);
      if (lane == 0) slot_offset[tid / Lanes] = before;
      if (tid == kReduceBlock - 1) slot_offset[ChunkNodes] = before + mine;
      __syncthreads();
    }
    layout_ok = layout_ok && slot_offset[ChunkNodes] <= s.chunk_slots;
    first = own ? slot_offset[row - begin] : 0;
    if (own && layout_ok) {
      for (int q = lane; q < count; q += Lanes) {
        shared_neighbor[first + q] = static_cast<int32_t>(ld(graph.neighbor + q * V + row));
        TM_UNROLL for (int e = 0; e < D * D; ++e) shared_k[(first + q) * (D * D) + e] = ld(graph.node_k + (q * V + row) * (D * D) + e);
      }
    }
    __syncthreads();
  }
  // The streamed layout: each thread's first slots into its own columns of shared memory
  // (neighbours [cached_neighbors][kStreamChunkNodes] int32, then Kdir [cached_ks][D * D][kStreamChunkNodes]),
  // read by its partner too (after the barrier below).
  const int column = tid / Lanes;
  int32_t* const columns_neighbor = reinterpret_cast<int32_t*>(solve_shared);
  S* const columns_k = reinterpret_cast<S*>(columns_neighbor + s.cached_neighbors * kStreamChunkNodes);
  const int cached_neighbors = InShared ? 0 : static_cast<int>(s.cached_neighbors);
  const int cached_ks = InShared ? 0 : static_cast<int>(s.cached_ks);
  if (!InShared && own && layout_ok) {
    for (int q = 0; q < count && q < cached_neighbors; ++q) {
      columns_neighbor[q * kStreamChunkNodes + column] = static_cast<int32_t>(ld(graph.neighbor + q * V + row));
    }
    for (int q = 0; q < count && q < cached_ks; ++q) {
      TM_UNROLL for (int e = 0; e < D * D; ++e) columns_k[(q * (D * D) + e) * kStreamChunkNodes + column] = ld(graph.node_k + (q * V + row) * (D * D) + e);
    }
  }
  // The streamed layout's pairs (NodeSlots): the mirror row, when it is a node of the chunk.
  __shared__ S help[InShared ? 1 : kStreamChunkNodes][D];
  const int partner_column = kStreamChunkNodes - 1 - column;
  const int64_t partner_row = begin + partner_column;
  const bool paired = !InShared && s.pair_rows && own && layout_ok && partner_row < end;
  const int partner_count = paired ? static_cast<int>(ld(graph.incidences + partner_row)) : 0;
  const int pair_half = (count + partner_count + 1) / 2;
  const bool heavier = count > partner_count || (count == partner_count && column < partner_column);
  const int node_count = own && layout_ok ? count : 0;
  using Index = std::remove_cv_t<std::remove_pointer_t<decltype(graph.neighbor)>>;
  const NodeSlots<InShared, D, S, Index> slots{
      SharedGraph<D, S>{shared_k, shared_neighbor}, first, lane, node_count, columns_neighbor, columns_k,
      cached_neighbors, cached_ks, graph.neighbor, graph.node_k, V, column, row, partner_row,
      paired ? graph.node_of(partner_row) : 0, paired && heavier ? pair_half : node_count, pair_half,
      paired && !heavier ? partner_count : 0, help};
  if (!InShared) __syncthreads();  // the columns are read by the partners

  // The node's own constants, in registers for the whole solve, and its CG vectors x, p, s, r,
  // w: in registers too in the shared layout; streamed, in the block's shared memory by vector
  // and column (only the thread's own column is touched), so that the slot loops, with their
  // loads in flight for two rows, have the registers.
  S k_own[D][D], m_own = S(0), f_own = S(0);
  enum { kX, kP, kS, kR, kW, kVectors };
  S vector_registers[kVectors][D];
  __shared__ S vector_columns[InShared ? 1 : kVectors * D][InShared ? 1 : kStreamChunkNodes];
  auto vec = [&](int v, int a) -> S& {
    if constexpr (InShared) return vector_registers[v][a]; else return vector_columns[v * D + a][column];
  };
  if (own) k.epilogue.load_node(i, k_own, m_own, f_own);
  const S c_stiff = k.epilogue.c_stiff;
  const S* rhs = s.rhs;
  const S* free = k.epilogue.free;
  auto projected_rhs = [=](int64_t j, S (&out)[D]) {
    const S fj = free != nullptr ? free[j] : S(1);
    TM_UNROLL for (int a = 0; a < D; ++a) out[a] = free != nullptr ? rhs[j * D + a] * fj : rhs[j * D + a];
  };

  // One solve, or (StepRhs) a run of implicit Euler steps, each a right-hand side, a solve and
  // the step's end, a grid barrier between steps (the next right-hand side reads the neighbours'
  // carried state). The graph in shared memory and the node's constants serve every step.
  const StepRhs<S>& step_rhs = s.step_rhs;
  const int64_t steps = step_rhs.rest != nullptr ? s.steps : 1;
  for (int64_t step = 0; step < steps; ++step) {
    if (blockIdx.x == 0 && tid < 3) s.counters[tid] = 0;  // before the step's first barrier; counted after it

    // The step's right-hand side at the carried state (x, v: written by the last step's end, read
    // with plain loads after the barrier), as hooke_node_step_rhs computes it, then a grid barrier:
    // the start reads the neighbours' rhs.
    if (step_rhs.rest != nullptr) {
      const S* xs = s.end.update.x;
      const S* vs = s.end.update.v;
      const S* rest = step_rhs.rest;
      const S c_w = step_rhs.c_w;
      auto displacement = [=](int64_t j, S (&out)[D]) {
        TM_UNROLL for (int a = 0; a < D; ++a) {
          out[a] = step_displacement(xs[j * D + a], ld(rest + j * D + a), vs[j * D + a], c_w);
        }
      };
      S total[D], wi[D];
      TM_UNROLL for (int a = 0; a < D; ++a) total[a] = wi[a] = S(0);
      if (own && layout_ok) displacement(i, wi);
      slots.add_forces_in_order(wi, displacement, total);
      if (own && layout_ok) {
        constexpr bool kPlanes = std::decay_t<decltype(k.epilogue)>::kHasNodeK;  // contact: its stiffness
        const PenaltyPlanes<S> planes{step_rhs.plane_normals, step_rhs.plane_offsets, step_rhs.plane_stiffness,
                                      step_rhs.planes};
        S xi[D], vi[D], external_i[D], out[D];
        TM_UNROLL for (int a = 0; a < D; ++a) {
          xi[a] = xs[i * D + a];
          vi[a] = vs[i * D + a];
          external_i[a] = ld(step_rhs.external + i * D + a);
        }
        const S damping = step_rhs.rayleigh_mass * ld(k.epilogue.mass + i);
        step_rhs_node<D, S, kPlanes>(planes, step_rhs.h, c_w, damping, xi, vi, external_i, total, k_own,
                                     out);  // k_own: this step's Kc in the products
        if (lane == 0) {
          TM_UNROLL for (int a = 0; a < D; ++a) {
            step_rhs.u[i * D + a] = xi[a] - ld(rest + i * D + a);
            step_rhs.rhs[i * D + a] = out[a];
            if constexpr (kPlanes) {
              TM_UNROLL for (int b = 0; b < D; ++b) step_rhs.node_stiffness[(i * D + a) * D + b] = k_own[a][b];
            }
          }
        }
      }
      grid.sync();
    }

    // Start: x = p = s = 0, r_0 = projected rhs, w_0 = A r_0 (the neighbours' r_0 read from rhs).
    // From an iterate (s.from_iterate): x = the iterate, rhs its residual (CG from x0 is CG on
    // A d = r0 from 0, plus x0; the threshold stays the start's, relative to b).
    double gamma_part = 0.0, delta_part = 0.0;
    S acc[D], r0[D], zero[D];
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] = r0[a] = zero[a] = S(0);
    if (own) projected_rhs(i, r0);
    slots.add_forces(r0, projected_rhs, acc);  // by every thread (streamed: a block barrier inside)
    lanes_total<Lanes, D, S>(acc);  // by every thread: the shuffles take whole warps, a chunk's last may be part-empty
    {
      S w0[D];
      TM_UNROLL for (int a = 0; a < D; ++a) w0[a] = S(0);
      if (own) {
        k.epilogue.row(k_own, m_own, f_own, c_stiff, r0, acc, w0);
        if (lane == 0) {
          Row::store(s.exchange + i * W, r0, w0, zero);
          TM_UNROLL for (int a = 0; a < D; ++a) {
            gamma_part += static_cast<double>(r0[a]) * static_cast<double>(r0[a]);
            delta_part += static_cast<double>(w0[a]) * static_cast<double>(r0[a]);
          }
        }
      }
      TM_UNROLL for (int a = 0; a < D; ++a) {
        vec(kX, a) = s.from_iterate && own ? s.x[i * D + a] : S(0);  // own node's: written back at the end
        vec(kP, a) = vec(kS, a) = S(0);
        vec(kR, a) = r0[a];
        vec(kW, a) = w0[a];
      }
    }
    {
      const double2 t = block_sum_pair(gamma_part, delta_part);
      if (tid == 0) {
        s.sums[chunk] = layout_ok ? t.x : __longlong_as_double(0x7ff8000000000000LL);
        s.sums[K_chunks + chunk] = t.y;
      }
    }
    grid.sync();

    // The object's scalars, the same in every block of the object (computed from the same sums).
    int32_t status = kActive, iterations = 0;
    S rr = S(0), alpha = S(0), beta = S(0), threshold = S(0);
    for (int64_t it = 0;; ++it) {
      const int parity = static_cast<int>(it & 1);
      if (it > 0 && !single_object) {  // every object stopped in the last iteration: all leave together
        if (*reinterpret_cast<volatile int32_t*>(s.counters + (it - 1) % 3) == 0) break;
        if (blockIdx.x == 0 && tid == 0) s.counters[(it + 1) % 3] = 0;  // read two iterations ago
      }
      bool stepping = false;
      if (it == 0 || status == kActive) {
        const double2 totals = object_totals(plan, object, s.sums + parity * 2 * K_chunks,
                                             s.sums + parity * 2 * K_chunks + K_chunks);
        if (it == 0) {
          rr = static_cast<S>(totals.x);
          threshold = s.from_iterate ? s.threshold[object] : rr * s.tol_sq;  // the start wrote it, before the kernel
          status = cg_start_status<S>(rr, threshold, s.max_iter);
          if (first_chunk && tid == 0 && !s.from_iterate) {
            s.rhs_sq[object] = rr;
            s.threshold[object] = threshold;
          }
          beta = S(0);
        } else {
          beta = cg_beta_step<S>(totals.x, rr, threshold, s.max_iter, status, iterations);
        }
        if (status == kActive) {
          alpha = cg_pipelined_alpha<S>(totals.x, totals.y, beta, alpha, it == 0, rr, status);
          stepping = status == kActive;
        }
      }
      if (single_object && !stepping) break;  // every block knows: the one object stopped
      if (stepping) {
        const S* row_in = s.exchange + parity * V * W;
        S* row_out = s.exchange + (1 - parity) * V * W;
        double g = 0.0, dl = 0.0;
        S r_next[D], w_next[D];
        TM_UNROLL for (int a = 0; a < D; ++a) {
          r_next[a] = next_residual(vec(kR, a), vec(kW, a), vec(kS, a), alpha, beta);
          acc[a] = S(0);
        }
        // The object's last step (its next beta step reaches the cap, if it does not converge or
        // fail first: it stops either way) needs no w = A r: only r.r is read after it. Skipping
        // that product saves one of the max_iter + 1 a fixed budget runs (one of 11 on the SOFA
        // beam). The same in every thread of the block (one object's).
        const bool last_step = iterations + 1 >= s.max_iter;
        if (!last_step) {  // the same in every thread of the block
          const S a_step = alpha, b_step = beta;
          slots.add_forces(r_next, [=](int64_t j, S (&out)[D]) {
            S rj[D], wj[D], sj[D];
            Row::load(row_in + j * W, rj, wj, sj);
            TM_UNROLL for (int a = 0; a < D; ++a) out[a] = next_residual(rj[a], wj[a], sj[a], a_step, b_step);
          }, acc);
        }
        lanes_total<Lanes, D, S>(acc);
        if (own) {
          if (last_step) {
            TM_UNROLL for (int a = 0; a < D; ++a) w_next[a] = S(0);
          } else {
            k.epilogue.row(k_own, m_own, f_own, c_stiff, r_next, acc, w_next);
          }
          S s_next[D];
          TM_UNROLL for (int a = 0; a < D; ++a) {
            const S p_next = vec(kR, a) + beta * vec(kP, a);
            vec(kP, a) = p_next;
            vec(kX, a) += alpha * p_next;
            s_next[a] = fma(beta, vec(kS, a), vec(kW, a));
            vec(kS, a) = s_next[a];
            vec(kR, a) = r_next[a];
            vec(kW, a) = w_next[a];
          }
          if (lane == 0) {
            Row::store(row_out + i * W, r_next, w_next, s_next);
            TM_UNROLL for (int a = 0; a < D; ++a) {
              g += static_cast<double>(r_next[a]) * static_cast<double>(r_next[a]);
              dl += static_cast<double>(w_next[a]) * static_cast<double>(r_next[a]);
            }
          }
        }
        const double2 t = block_sum_pair(g, dl);
        if (tid == 0) {
          const int out = 1 - parity;
          s.sums[out * 2 * K_chunks + chunk] = t.x;
          s.sums[out * 2 * K_chunks + K_chunks + chunk] = t.y;
          if (first_chunk && !single_object) atomicAdd(s.counters + it % 3, 1);
        }
      }
      grid.sync();
    }

    // The solve's outcome: the iterates, and the object's scalars from its first chunk's block.
    if (own && lane == 0) {
      TM_UNROLL for (int a = 0; a < D; ++a) {
        s.x[i * D + a] = vec(kX, a);
        s.r[i * D + a] = vec(kR, a);
        s.p[i * D + a] = vec(kP, a);
      }
    }
    if (first_chunk && tid == 0) {
      s.rr[object] = rr;
      s.status[object] = status;
      s.iterations[object] = iterations;
      s.alpha[object] = alpha;
      s.beta[object] = beta;
    }
    // The step's end (hooke_node_solve_step): each node's new velocity and position from its dv,
    // still in registers, then the object's |v_new|^2 and summary column from its last block to get
    // here. No grid barrier: the solve reads neither the state nor the velocities it updates, and
    // every block of an object holds the object's scalars once it leaves the loop. (The start
    // wrote rhs_sq before the first grid barrier.)
    if (s.end.update.x != nullptr) {
      double norm_part = 0.0;
      if (own && lane == 0) {
        TM_UNROLL for (int a = 0; a < D; ++a) {
          const S vn = s.end.update.apply(i * D + a, vec(kX, a));
          norm_part += static_cast<double>(vn) * static_cast<double>(vn);
        }
      }
      const StepSummary<S>& out = s.end.summary;
      finish_step_summary<S>(out, plan, chunk, object, block_sum(norm_part), s.end.sums, s.end.counter,
                             [&](int64_t pos, double total) {
                               out.write_values(object, plan.num_objects, status, iterations, rr,
                                                __ldcg(s.rhs_sq + object), total, pos);
                             });
    }
    if (step + 1 < steps) grid.sync();  // the next right-hand side reads the neighbours' carried state
  }
}

// Launches the pipelined solve in one layout: one block per chunk, all resident at once (a
// cooperative launch). Returns false, having launched nothing, where the device cannot hold every
// block at once with shared_bytes of dynamic shared memory each.
template <class K, typename S, bool InShared>
bool launch_pipelined_layout(const CGPlan& plan, const K& k, const PipelinedSolve<S>& s, size_t shared_bytes) {
  constexpr int D = K::kDim;
  if (!InShared) {  // the columns streamed_cache chose
    shared_bytes = static_cast<size_t>(kStreamChunkNodes) *
                   (s.cached_neighbors * sizeof(int32_t) + s.cached_ks * D * D * sizeof(S));
  }
  const auto* props = at::cuda::getCurrentDeviceProperties();
  if (shared_bytes > props->sharedMemPerBlockOptin) return false;
  const void* kernel = reinterpret_cast<const void*>(&pipelined_cg_kernel<K, S, InShared>);
  static size_t shared_allowed = 0;  // per kernel instantiation
  if (shared_bytes > shared_allowed) {
    C10_CUDA_CHECK(cudaFuncSetAttribute(kernel, cudaFuncAttributeMaxDynamicSharedMemorySize,
                                        static_cast<int>(shared_bytes)));
    shared_allowed = shared_bytes;
  }
  int blocks_per_sm = 0;
  C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks_per_sm, kernel, kReduceBlock, shared_bytes));
  if (static_cast<int64_t>(blocks_per_sm) * props->multiProcessorCount < plan.num_chunks) return false;
  K kernel_k = k;
  CGPlan kernel_plan = plan;
  PipelinedSolve<S> kernel_s = s;
  void* args[] = {&kernel_k, &kernel_plan, &kernel_s};
  C10_CUDA_CHECK(cudaLaunchCooperativeKernel(kernel, dim3(static_cast<unsigned>(plan.num_chunks)), dim3(kReduceBlock),
                                             args, shared_bytes, at::cuda::getCurrentCUDAStream()));
  return true;
}

// The streamed layout's shared memory: as many of each node's first slots as fit the share of
// an SM that each of the plan's blocks gets (the blocks must all be resident: ceil(chunks / SMs)
// of them an SM), neighbours first (each heads a dependent chain), then Kdir blocks. On an H100
// the paper beam's 220 blocks of 256 nodes (2 an SM) keep each node's neighbours (26 at most) and
// first 9 Kdir blocks: half of the graph's Kdir bytes (its nodes have 10 or 26 slots) stay on chip.
template <class K, typename S>
PipelinedSolve<S> streamed_cache(const CGPlan& plan, const K& k, PipelinedSolve<S> s) {
  constexpr int D = K::kDim;
  const auto* props = at::cuda::getCurrentDeviceProperties();
  static int static_bytes = -1;  // per kernel instantiation
  if (static_bytes < 0) {
    cudaFuncAttributes attributes;
    C10_CUDA_CHECK(cudaFuncGetAttributes(&attributes, pipelined_cg_kernel<K, S, false>));
    static_bytes = static_cast<int>(attributes.sharedSizeBytes);
  }
  const int64_t sms = props->multiProcessorCount;
  const int64_t blocks_per_sm = std::max<int64_t>(1, (plan.num_chunks + sms - 1) / sms);
  const int64_t share = static_cast<int64_t>(props->sharedMemPerMultiprocessor) / blocks_per_sm -
                        static_cast<int64_t>(props->reservedSharedMemPerBlock) - static_bytes;
  const int64_t budget = std::max<int64_t>(0, std::min<int64_t>(share, static_cast<int64_t>(props->sharedMemPerBlockOptin) - static_bytes));
  // s.cache_slots >= 0 caps the slots of each kind (the op's cache_slots; 0 streams every slot).
  int64_t slots = s.max_slots;
  if (s.cache_slots >= 0) slots = std::min<int64_t>(slots, s.cache_slots);
  const int64_t neighbor_level = kStreamChunkNodes * sizeof(int32_t), k_level = kStreamChunkNodes * D * D * sizeof(S);
  s.cached_neighbors = std::min<int64_t>(slots, budget / neighbor_level);
  s.cached_ks = std::min<int64_t>(slots, (budget - s.cached_neighbors * neighbor_level) / k_level);
  return s;
}

// Launches the pipelined solve in the first layout that fits one wave: shared (chunks of at most
// kSolveChunkNodes nodes, their slots in shared memory), then streamed (chunks of at most
// kStreamChunkNodes). Returns false, having launched nothing, where neither fits (too many chunks
// or nodes, or chunks larger than both layouts take): the caller solves another way.
template <class K, typename S>
bool launch_pipelined_cg(const CGPlan& plan, const K& k, const PipelinedSolve<S>& s) {
  constexpr int D = K::kDim;
  if (plan.num_chunks == 0 || plan.num_nodes > INT32_MAX) return false;
  if (s.chunk_nodes <= kSolveChunkNodes && s.chunk_slots <= INT32_MAX / (D * D)) {
    const size_t shared_bytes = static_cast<size_t>(s.chunk_slots) * (D * D * sizeof(S) + sizeof(int32_t)) + 16;
    if (launch_pipelined_layout<K, S, true>(plan, k, s, shared_bytes)) return true;
  }
  if (s.chunk_nodes > kStreamChunkNodes) return false;
  return launch_pipelined_layout<K, S, false>(plan, k, streamed_cache(plan, k, s), 0);
}

}  // namespace tensormass
