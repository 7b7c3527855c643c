"""Where a latency-bound CG iteration's time goes: standalone kernels (CuPy, NVRTC) over the SOFA
beam's node graph, timed per iteration, in variants of what the persistent CG could do:

    alg   "std"  two grid barriers an iteration (the library's persistent CG: p.Ap, then r.r)
          "cg1"  one barrier an iteration (Chronopoulos-Gear: r.r and w.r in one reduction,
                 w = A r with each neighbour's r formed on the fly from the last iterate)
    lanes threads per node (its slots split among them, the sums shuffled together)
    ks    1: the block's node_k and neighbours kept in shared memory for the whole solve
    bar   "coop" cooperative groups' grid.sync, "own" a counter barrier
    ablate "none" | "nomatvec" (barriers and sums only) | "nobarrier" (wrong results, timing only)

Each variant is checked against a float64 CG in torch (same iteration count) before it is timed.
A probe for deciding what to build, not a library path.

    python benchmarks/probes/cg_latency_probe.py [--out DIR]   # on the GPU machine (needs cupy)
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # common, measure
from step_bench import paper_beam, sofa  # noqa: E402

from tensormass_torch.ops import library, node_graph  # noqa: E402

KERNEL = r"""
#include <cooperative_groups.h>
namespace coop = cooperative_groups;

#ifndef LANES
#define LANES 1
#endif
#ifndef MIN_BLOCKS
#define MIN_BLOCKS 1
#endif
#ifndef SLOT_BATCH
#define SLOT_BATCH 4
#endif
#define NB (256 / LANES)

__device__ __forceinline__ void grid_barrier(unsigned* counter, unsigned& target) {
#if OWN_BARRIER
  __syncthreads();
  target += gridDim.x;
  if (threadIdx.x == 0) {
    __threadfence();
    atomicAdd(counter, 1u);
    while (*((volatile unsigned*)counter) < target) {}
    __threadfence();
  }
  __syncthreads();
#elif NO_BARRIER
  __syncthreads();
#else
  coop::this_grid().sync();
#endif
}

// Sum of v over the block into thread 0 (others: garbage); red: 8 doubles of shared memory.
__device__ __forceinline__ double block_sum0(double v, double* red) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(0xffffffffu, v, o);
  if ((threadIdx.x & 31) == 0) red[threadIdx.x >> 5] = v;
  __syncthreads();
  double t = 0.0;
  if (threadIdx.x < 32) {
    t = threadIdx.x < 8 ? red[threadIdx.x] : 0.0;
    for (int o = 4; o > 0; o >>= 1) t += __shfl_xor_sync(0xffffffffu, t, o);
  }
  return t;
}

// Total over the blocks' partial sums (partial[0..G)), in every thread (warp 0 adds them up).
__device__ __forceinline__ double grid_total(const double* partial, double* slot) {
  if (threadIdx.x < 32) {
    double t = 0.0;
    for (int q = threadIdx.x; q < gridDim.x; q += 32) t += ((volatile const double*)partial)[q];
    for (int o = 16; o > 0; o >>= 1) t += __shfl_xor_sync(0xffffffffu, t, o);
    if (threadIdx.x == 0) *slot = t;
  }
  __syncthreads();
  return *slot;
}

// The totals of two per-block partial arrays, every thread loading some in parallel (one L2
// round trip), then a block sum of both at once; in every thread.
__device__ __forceinline__ void grid_total2(const double* pa, const double* pb, double2* slot, double2* red2,
                                            double& ta, double& tb) {
  double a = 0.0, b = 0.0;
  for (int q = threadIdx.x; q < gridDim.x; q += blockDim.x) {
    a += ((volatile const double*)pa)[q];
    b += ((volatile const double*)pb)[q];
  }
  for (int o = 16; o > 0; o >>= 1) {
    a += __shfl_xor_sync(0xffffffffu, a, o);
    b += __shfl_xor_sync(0xffffffffu, b, o);
  }
  if ((threadIdx.x & 31) == 0) red2[threadIdx.x >> 5] = make_double2(a, b);
  __syncthreads();
  if (threadIdx.x < 32) {
    double2 t = threadIdx.x < 8 ? red2[threadIdx.x] : make_double2(0.0, 0.0);
    for (int o = 4; o > 0; o >>= 1) {
      t.x += __shfl_xor_sync(0xffffffffu, t.x, o);
      t.y += __shfl_xor_sync(0xffffffffu, t.y, o);
    }
    if (threadIdx.x == 0) *slot = t;
  }
  __syncthreads();
  ta = slot->x;
  tb = slot->y;
}

// Block sums of two values into thread 0.
__device__ __forceinline__ double2 block_sum2(double a, double b, double2* red2) {
  for (int o = 16; o > 0; o >>= 1) {
    a += __shfl_xor_sync(0xffffffffu, a, o);
    b += __shfl_xor_sync(0xffffffffu, b, o);
  }
  if ((threadIdx.x & 31) == 0) red2[threadIdx.x >> 5] = make_double2(a, b);
  __syncthreads();
  double2 t = make_double2(0.0, 0.0);
  if (threadIdx.x < 32) {
    t = threadIdx.x < 8 ? red2[threadIdx.x] : make_double2(0.0, 0.0);
    for (int o = 4; o > 0; o >>= 1) {
      t.x += __shfl_xor_sync(0xffffffffu, t.x, o);
      t.y += __shfl_xor_sync(0xffffffffu, t.y, o);
    }
  }
  return t;
}

__device__ __forceinline__ float r_next(float r, float w, float s, float alpha, float beta) {
  return __fmaf_rn(-alpha, __fmaf_rn(beta, s, w), r);
}

struct Args {
  int V;
  const int* row_ptr; const int* nbr; const float* kc;
  const float* mass; const float* freem; const float* nodek;
  float cM, cK;
  const float* b;
  float* x; float* p; float* rr[2]; float* ww[2]; float* ss[2]; float* ap;
  double* partial;  // [4][G]
  unsigned* counter;
  int iters;
  double* hist;
};

// acc += -sum_slots K (v_j - v_i) over this lane's slots of node i; vj(j, out[3]) reads neighbour j.
template <class VJ>
__device__ __forceinline__ void lane_slots(int cnt, int lane, const int* nb, const float* kk, const float (&vi)[3],
                                           const VJ& vj, float (&acc)[3]) {
  constexpr int B = SLOT_BATCH;
  for (int t0 = 0; t0 * LANES < cnt; t0 += B) {
    int j[B]; float v[B][3];
#pragma unroll
    for (int q = 0; q < B; ++q) {
      const int s = lane + (t0 + q) * LANES;
      j[q] = s < cnt ? nb[s] : -1;
    }
#pragma unroll
    for (int q = 0; q < B; ++q) if (j[q] >= 0) vj(j[q], v[q]);
#pragma unroll
    for (int q = 0; q < B; ++q) {
      const int s = lane + (t0 + q) * LANES;
      if (s >= cnt) break;
      const float* k = kk + s * 9;
      float w0 = v[q][0] - vi[0], w1 = v[q][1] - vi[1], w2 = v[q][2] - vi[2];
      acc[0] -= k[0] * w0 + k[1] * w1 + k[2] * w2;
      acc[1] -= k[3] * w0 + k[4] * w1 + k[5] * w2;
      acc[2] -= k[6] * w0 + k[7] * w1 + k[8] * w2;
    }
  }
}

__device__ __forceinline__ void lane_total(float (&acc)[3]) {
#pragma unroll
  for (int o = LANES / 2; o > 0; o >>= 1) {
#pragma unroll
    for (int a = 0; a < 3; ++a) acc[a] += __shfl_xor_sync(0xffffffffu, acc[a], o);
  }
}

// A v_i from the stiffness sum acc: c_M m v - c_K (acc - Kc v), projected.
__device__ __forceinline__ void epilogue(const Args& A, int i, const float (&v)[3], float (&acc)[3], float (&out)[3]) {
  const float* kc = A.nodek + i * 9;
#pragma unroll
  for (int a = 0; a < 3; ++a) acc[a] -= kc[3 * a] * v[0] + kc[3 * a + 1] * v[1] + kc[3 * a + 2] * v[2];
  const float m = A.cM * A.mass[i], f = A.freem[i];
#pragma unroll
  for (int a = 0; a < 3; ++a) out[a] = (m * v[a] - A.cK * acc[a]) * f;
}

extern "C" __global__ void __launch_bounds__(256, MIN_BLOCKS) probe(
    int V, const int* row_ptr, const int* nbr, const float* kc, const float* mass, const float* freem,
    const float* nodek, float cM, float cK, const float* b, float* x, float* p, float* r0, float* r1, float* w0,
    float* w1, float* s0, float* s1, float* ap, double* partial, unsigned* counter, int iters, double* hist) {
  const Args A{V, row_ptr, nbr, kc, mass, freem, nodek, cM, cK, b, x, p, {r0, r1}, {w0, w1}, {s0, s1}, ap,
               partial, counter, iters, hist};
  extern __shared__ float smem[];
  __shared__ double red[8];
  __shared__ double totals[8];
  const int tid = threadIdx.x, lane = tid % LANES;
  const int first = blockIdx.x * NB;
  const int i = first + tid / LANES;
  const bool own = i < A.V;
  const int e0 = A.row_ptr[first], e1 = A.row_ptr[min(first + NB, A.V)];
  int* snb = reinterpret_cast<int*>(smem);
  float* sk = smem + (e1 - e0);
  for (int e = e0 + tid; e < e1; e += 256) snb[e - e0] = A.nbr[e];
#if KS
  for (int e = e0 * 9 + tid; e < e1 * 9; e += 256) sk[e - e0 * 9] = A.kc[e];
#endif
  __syncthreads();
  const int off = own ? A.row_ptr[i] - e0 : 0, cnt = own ? A.row_ptr[i + 1] - A.row_ptr[i] : 0;
  const int* nb = snb + off;
#if KS
  const float* kk = sk + off * 9;
#else
  const float* kk = A.kc + (e0 + off) * 9;
#endif
  unsigned target = 0;
  const int G = gridDim.x;
  double* part0 = A.partial;
  double* part1 = A.partial + G;

#if ALG == 0
  // r = p = b, x = 0, b.b
  double acc_bb = 0.0;
  if (own && lane == 0) {
    for (int a = 0; a < 3; ++a) {
      const float bv = A.b[3 * i + a] * A.freem[i];
      A.x[3 * i + a] = 0.f; A.rr[0][3 * i + a] = bv; A.p[3 * i + a] = bv;
      acc_bb += (double)bv * bv;
    }
  }
  double t = block_sum0(acc_bb, red);
  if (tid == 0) part1[blockIdx.x] = t;
  grid_barrier(A.counter, target);
  double rr = grid_total(part1, &totals[0]);
  if (blockIdx.x == 0 && tid == 0) A.hist[0] = rr;
  float beta = 0.f;
  float* r = A.rr[0];
  for (int it = 0; it < A.iters; ++it) {
    // M: Ap along p_t = r + beta p (formed on the fly), p_t.Ap
    double dot = 0.0;
    float pt[3] = {0.f, 0.f, 0.f};
    if (own) {
#pragma unroll
      for (int a = 0; a < 3; ++a) pt[a] = __fmaf_rn(beta, A.p[3 * i + a], r[3 * i + a]);
      float acc[3] = {0.f, 0.f, 0.f};
#if !NO_MATVEC
      const float* P = A.p; const float* R = r; const float be = beta;
      lane_slots(cnt, lane, nb, kk, pt, [=](int j, float (&o)[3]) {
        for (int a = 0; a < 3; ++a) o[a] = __fmaf_rn(be, P[3 * j + a], R[3 * j + a]); }, acc);
#endif
      lane_total(acc);
      float out[3];
      epilogue(A, i, pt, acc, out);
      if (lane == 0) {
        for (int a = 0; a < 3; ++a) { A.ap[3 * i + a] = out[a]; dot += (double)pt[a] * out[a]; }
      }
    }
    t = block_sum0(dot, red);
    if (tid == 0) part0[blockIdx.x] = t;
    grid_barrier(A.counter, target);
    const double pap = grid_total(part0, &totals[1 + (it & 1)]);
    const float alpha = (float)(rr / pap);
    // U: p = p_t, x += alpha p, r -= alpha Ap, r.r
    double acc_rr = 0.0;
    if (own && lane == 0) {
      for (int a = 0; a < 3; ++a) {
        A.p[3 * i + a] = pt[a];
        A.x[3 * i + a] += alpha * pt[a];
        const float rn = r[3 * i + a] - alpha * A.ap[3 * i + a];
        r[3 * i + a] = rn;
        acc_rr += (double)rn * rn;
      }
    }
    t = block_sum0(acc_rr, red);
    if (tid == 0) part1[blockIdx.x] = t;
    grid_barrier(A.counter, target);
    const double rr_new = grid_total(part1, &totals[3 + (it & 1)]);
    beta = (float)(rr_new / rr);
    rr = rr_new;
    if (blockIdx.x == 0 && tid == 0) A.hist[it + 1] = rr;
  }
#elif ALG == 2
  // Chronopoulos-Gear with the node's own state in registers for the whole solve; only what the
  // neighbours read (r, w, s) goes through memory, double-buffered.
  __shared__ double2 red2[8];
  __shared__ double2 tot2[2];
  float xo[3] = {0.f, 0.f, 0.f}, po[3] = {0.f, 0.f, 0.f}, so[3] = {0.f, 0.f, 0.f}, ro[3], wo[3];
  float alpha = 0.f, beta = 0.f;
  double gamma_old = 0.0;
  int cur = 0;
  {
    double g = 0.0, dl = 0.0;
    if (own) {
      const float fi = A.freem[i];
      for (int a = 0; a < 3; ++a) ro[a] = A.b[3 * i + a] * fi;
      float acc[3] = {0.f, 0.f, 0.f};
      const float* Bv = A.b; const float* F = A.freem;
      lane_slots(cnt, lane, nb, kk, ro, [=](int j, float (&o)[3]) {
        const float fj = F[j]; for (int a = 0; a < 3; ++a) o[a] = Bv[3 * j + a] * fj; }, acc);
      lane_total(acc);
      epilogue(A, i, ro, acc, wo);
      if (lane == 0) {
        for (int a = 0; a < 3; ++a) {
          A.rr[0][3 * i + a] = ro[a]; A.ww[0][3 * i + a] = wo[a]; A.ss[0][3 * i + a] = 0.f;
          g += (double)ro[a] * ro[a]; dl += (double)wo[a] * ro[a];
        }
      }
    } else {
      for (int a = 0; a < 3; ++a) { ro[a] = 0.f; wo[a] = 0.f; }
    }
    const double2 t2 = block_sum2(g, dl, red2);
    if (tid == 0) { part0[blockIdx.x] = t2.x; part1[blockIdx.x] = t2.y; }
    grid_barrier(A.counter, target);
  }
  // own constants in registers
  float kc_own[9], m_own = 0.f, f_own = 0.f;
  if (own) {
    for (int q = 0; q < 9; ++q) kc_own[q] = A.nodek[9 * i + q];
    m_own = A.cM * A.mass[i]; f_own = A.freem[i];
  }
  for (int it = 0; it <= A.iters; ++it) {
    double gamma, delta;
    grid_total2(part0 + (it & 1) * 2 * G, part1 + (it & 1) * 2 * G, &tot2[it & 1], red2, gamma, delta);
    if (blockIdx.x == 0 && tid == 0) A.hist[it] = gamma;
    if (it == A.iters) break;
    if (it == 0) {
      beta = 0.f; alpha = (float)(gamma / delta);
    } else {
      const double b = gamma / gamma_old;
      beta = (float)b;
      alpha = (float)(gamma / (delta - b * gamma / (double)alpha));
    }
    gamma_old = gamma;
    const float* R = cur ? A.rr[1] : A.rr[0]; const float* W = cur ? A.ww[1] : A.ww[0];
    const float* Sv = cur ? A.ss[1] : A.ss[0];
    float* Rn = cur ? A.rr[0] : A.rr[1]; float* Wn = cur ? A.ww[0] : A.ww[1]; float* Sn = cur ? A.ss[0] : A.ss[1];
    double g = 0.0, dl = 0.0;
    if (own) {
      float vi[3];
      for (int a = 0; a < 3; ++a) vi[a] = r_next(ro[a], wo[a], so[a], alpha, beta);
      float acc[3] = {0.f, 0.f, 0.f};
#if !NO_MATVEC
      const float al = alpha, be = beta;
      lane_slots(cnt, lane, nb, kk, vi, [=](int j, float (&o)[3]) {
        for (int a = 0; a < 3; ++a) o[a] = r_next(R[3 * j + a], W[3 * j + a], Sv[3 * j + a], al, be); }, acc);
#endif
      lane_total(acc);
#pragma unroll
      for (int a = 0; a < 3; ++a) acc[a] -= kc_own[3 * a] * vi[0] + kc_own[3 * a + 1] * vi[1] + kc_own[3 * a + 2] * vi[2];
      float wn[3];
#pragma unroll
      for (int a = 0; a < 3; ++a) wn[a] = (m_own * vi[a] - A.cK * acc[a]) * f_own;
#pragma unroll
      for (int a = 0; a < 3; ++a) {
        po[a] = __fmaf_rn(beta, po[a], ro[a]);
        xo[a] += alpha * po[a];
        so[a] = __fmaf_rn(beta, so[a], wo[a]);
        ro[a] = vi[a];
        wo[a] = wn[a];
      }
      if (lane == 0) {
        for (int a = 0; a < 3; ++a) {
          Rn[3 * i + a] = ro[a]; Wn[3 * i + a] = wo[a]; Sn[3 * i + a] = so[a];
          g += (double)ro[a] * ro[a]; dl += (double)wo[a] * ro[a];
        }
      }
    }
    const double2 t2 = block_sum2(g, dl, red2);
    const int q = (it + 1) & 1;
    if (tid == 0) { part0[q * 2 * G + blockIdx.x] = t2.x; part1[q * 2 * G + blockIdx.x] = t2.y; }
    cur ^= 1;
    grid_barrier(A.counter, target);
  }
  if (own && lane == 0) for (int a = 0; a < 3; ++a) A.x[3 * i + a] = xo[a];
#else
  // Chronopoulos-Gear. r0 = b (projected), w0 = A r0 read from b directly; gamma0 = r.r, delta0 = w.r
  float alpha = 0.f, beta = 0.f;
  double gamma_old = 0.0;
  int cur = 0;
  {
    double g = 0.0, dl = 0.0;
    if (own) {
      float vi[3];
      const float fi = A.freem[i];
      for (int a = 0; a < 3; ++a) vi[a] = A.b[3 * i + a] * fi;
      float acc[3] = {0.f, 0.f, 0.f};
      const float* Bv = A.b; const float* F = A.freem;
      lane_slots(cnt, lane, nb, kk, vi, [=](int j, float (&o)[3]) {
        const float fj = F[j]; for (int a = 0; a < 3; ++a) o[a] = Bv[3 * j + a] * fj; }, acc);
      lane_total(acc);
      float out[3];
      epilogue(A, i, vi, acc, out);
      if (lane == 0) {
        for (int a = 0; a < 3; ++a) {
          A.x[3 * i + a] = 0.f; A.p[3 * i + a] = 0.f;
          A.rr[0][3 * i + a] = vi[a]; A.ww[0][3 * i + a] = out[a]; A.ss[0][3 * i + a] = 0.f;
          g += (double)vi[a] * vi[a]; dl += (double)out[a] * vi[a];
        }
      }
    }
    const double tg = block_sum0(g, red);
    __syncthreads();
    const double td = block_sum0(dl, red);
    if (tid == 0) { part0[blockIdx.x] = tg; part1[blockIdx.x] = td; }
    grid_barrier(A.counter, target);
  }
  for (int it = 0; it <= A.iters; ++it) {
    const double gamma = grid_total(part0 + (it & 1) * 2 * G, &totals[0 + 2 * (it & 1)]);
    const double delta = grid_total(part1 + (it & 1) * 2 * G, &totals[1 + 2 * (it & 1)]);
    if (blockIdx.x == 0 && tid == 0) A.hist[it] = gamma;
    if (it == A.iters) break;
    if (it == 0) {
      beta = 0.f; alpha = (float)(gamma / delta);
    } else {
      const double b = gamma / gamma_old;
      beta = (float)b;
      alpha = (float)(gamma / (delta - b * gamma / (double)alpha));
    }
    gamma_old = gamma;
    // parity by selects (an array indexed at run time would live in local memory)
    const float* R = cur ? A.rr[1] : A.rr[0]; const float* W = cur ? A.ww[1] : A.ww[0];
    const float* Sv = cur ? A.ss[1] : A.ss[0];
    float* Rn = cur ? A.rr[0] : A.rr[1]; float* Wn = cur ? A.ww[0] : A.ww[1]; float* Sn = cur ? A.ss[0] : A.ss[1];
    double g = 0.0, dl = 0.0;
    if (own) {
      float vi[3];
      for (int a = 0; a < 3; ++a) vi[a] = r_next(R[3 * i + a], W[3 * i + a], Sv[3 * i + a], alpha, beta);
      float acc[3] = {0.f, 0.f, 0.f};
#if !NO_MATVEC
      const float al = alpha, be = beta;
      lane_slots(cnt, lane, nb, kk, vi, [=](int j, float (&o)[3]) {
        for (int a = 0; a < 3; ++a) o[a] = r_next(R[3 * j + a], W[3 * j + a], Sv[3 * j + a], al, be); }, acc);
#endif
      lane_total(acc);
      float out[3];
      epilogue(A, i, vi, acc, out);
      if (lane == 0) {
        for (int a = 0; a < 3; ++a) {
          const float pa = __fmaf_rn(beta, A.p[3 * i + a], R[3 * i + a]);
          A.p[3 * i + a] = pa;
          A.x[3 * i + a] += alpha * pa;
          Sn[3 * i + a] = __fmaf_rn(beta, Sv[3 * i + a], W[3 * i + a]);
          Rn[3 * i + a] = vi[a];
          Wn[3 * i + a] = out[a];
          g += (double)vi[a] * vi[a]; dl += (double)out[a] * vi[a];
        }
      }
    }
    const double tg = block_sum0(g, red);
    __syncthreads();
    const double td = block_sum0(dl, red);
    const int q = (it + 1) & 1;
    if (tid == 0) { part0[q * 2 * G + blockIdx.x] = tg; part1[q * 2 * G + blockIdx.x] = td; }
    cur ^= 1;
    grid_barrier(A.counter, target);
  }
#endif
}
"""


def scene_graph(device, scene="sofa_beam"):
    """The node graph of ``scene`` (the SOFA beam, or the paper's 307,200-tet beam) as CSR
    (node-major) arrays and the step's system coefficients."""
    sim = (paper_beam if scene == "paper_beam" else sofa)("hooke", device, torch.float32)
    system = sim.system
    group = system.model.groups[0]
    neighbor, node_k = node_graph.hooke_node_graph(group)
    _, _, incidences = library.plan_indices(group.plan)
    V = neighbor.shape[1]
    counts = incidences.long()
    slot = torch.arange(neighbor.shape[0], device=device)[:, None].expand_as(neighbor)
    used = slot < counts[None, :]
    # node-major: transpose to [V, N_n], keep used slots in slot order
    nbr = neighbor.t()[used.t()].int().contiguous()
    kc = node_k.permute(1, 0, 2, 3)[used.t()].reshape(-1, 9).float().contiguous()
    row_ptr = torch.zeros(V + 1, dtype=torch.int32, device=device)
    row_ptr[1:] = torch.cumsum(counts, 0).int()
    h, opts = sim.options.dt, sim.options
    c_mass = 1.0 + h * opts.rayleigh_mass
    c_stiff = h * (h + opts.rayleigh_stiffness)
    mass = system.mass.reshape(-1).float().contiguous()
    free = system.free.reshape(-1).float().contiguous()
    # a contact stiffness on the nodes below the plane at rest (none): a small k n n^T everywhere
    # keeps the read in the timing
    nodek = torch.zeros(V, 9, device=device)
    return dict(V=V, row_ptr=row_ptr, nbr=nbr, kc=kc, mass=mass, free=free, nodek=nodek, c_mass=c_mass,
                c_stiff=c_stiff, counts=counts)


def reference_cg(g, b, iters):
    """float64 CG, the same iteration count; returns x and the r.r history."""
    V = g["V"]
    rows = torch.repeat_interleave(torch.arange(V, device=b.device), g["counts"])
    cols = g["nbr"].long()
    K = g["kc"].double().reshape(-1, 3, 3)
    mass, free = g["mass"].double(), g["free"].double()

    def A(v):
        w = v[cols] - v[rows]
        acc = torch.zeros_like(v).index_add_(0, rows, -(K @ w[:, :, None])[:, :, 0])
        return (g["c_mass"] * mass[:, None] * v - g["c_stiff"] * acc) * free[:, None]

    b = b.double() * free[:, None]
    x = torch.zeros_like(b)
    r = b.clone()
    p = r.clone()
    rr = float((r * r).sum())
    hist = [rr]
    for _ in range(iters):
        ap = A(p)
        alpha = rr / float((p * ap).sum())
        x += alpha * p
        r -= alpha * ap
        rr_new = float((r * r).sum())
        p = r + (rr_new / rr) * p
        rr = rr_new
        hist.append(rr)
    return x, hist


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=None)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--scene", default="sofa_beam", choices=("sofa_beam", "paper_beam"))
    args = parser.parse_args(argv)
    import cupy as cp

    dev = "cuda"
    g = scene_graph(dev, args.scene)
    V = g["V"]
    max_count = int(g["counts"].max())
    print(f"{args.scene} graph: {V} nodes, {g['nbr'].numel()} slots, max {max_count} per node", flush=True)
    torch.manual_seed(0)
    b = torch.randn(V, 3, device=dev)
    x_ref, hist_ref = reference_cg(g, b, 10)

    bufs = {k: torch.zeros(V * 3, device=dev) for k in ("x", "p", "r0", "r1", "w0", "w1", "s0", "s1", "ap")}
    counter = torch.zeros(1, dtype=torch.int32, device=dev)
    results = []
    variants = [dict(alg="std", lanes=1, ks=0, batch=4, ablate="none"),   # today's structure
                dict(alg="cg1", lanes=4, ks=1, batch=4, ablate="none")]   # the best of the first probe
    for lanes, batch in ((1, 4), (2, 4), (2, 8), (4, 4), (4, 8)):
        for ks in (0, 1):
            variants.append(dict(alg="reg", lanes=lanes, ks=ks, batch=batch, ablate="none"))
    variants.append(dict(alg="reg", lanes=4, ks=1, batch=8, ablate="none", min_blocks=3))
    variants.append(dict(alg="reg", lanes=4, ks=0, batch=8, ablate="none", min_blocks=3))
    variants.append(dict(alg="reg", lanes=4, ks=1, batch=8, ablate="none", bar="own", min_blocks=3))
    for lanes in (1, 2, 4):
        for ablate in ("nomatvec", "nobarrier"):
            variants.append(dict(alg="reg", lanes=lanes, ks=1, batch=8 if lanes > 1 else 4, ablate=ablate,
                                 min_blocks=3 if lanes == 4 else 1))
    if args.scene == "paper_beam":  # 56k nodes: one wave at 256 nodes a block, or 2 lanes at 4 blocks an SM
        variants = [dict(alg="std", lanes=1, ks=0, batch=4, ablate=a) for a in ("none", "nomatvec", "nobarrier")]
        variants += [dict(alg="reg", lanes=1, ks=0, batch=b, ablate="none") for b in (4, 8)]
        variants += [dict(alg="reg", lanes=1, ks=0, batch=4, ablate=a) for a in ("nomatvec", "nobarrier")]
        variants += [dict(alg=a, lanes=2, ks=0, batch=b, ablate="none", min_blocks=4)
                     for a in ("reg", "cg1") for b in (2, 4)]
    for var in variants:
        var.setdefault("bar", "coop")
        var.setdefault("min_blocks", 1)

    def kernel_args(iters, hist, partial):
        ptr = lambda t: np.uint64(t.data_ptr())  # noqa: E731
        return (np.int32(V), ptr(g["row_ptr"]), ptr(g["nbr"]), ptr(g["kc"]), ptr(g["mass"]), ptr(g["free"]),
                ptr(g["nodek"]), np.float32(g["c_mass"]), np.float32(g["c_stiff"]), ptr(b),
                *(ptr(bufs[k]) for k in ("x", "p", "r0", "r1", "w0", "w1", "s0", "s1", "ap")), ptr(partial),
                ptr(counter), np.int32(iters), ptr(hist))

    for var in variants:
        lanes = var["lanes"]
        nb = 256 // lanes
        grid = (V + nb - 1) // nb
        edges_per_block = max(int(g["row_ptr"][min((q + 1) * nb, V)] - g["row_ptr"][q * nb]) for q in range(grid))
        smem = edges_per_block * 4 * (1 + (9 if var["ks"] else 0))
        opts = ("-std=c++17", f"-DLANES={lanes}", f"-DKS={var['ks']}", f"-DALG={dict(std=0, cg1=1, reg=2)[var['alg']]}", f"-DSLOT_BATCH={var['batch']}", f"-DMIN_BLOCKS={var['min_blocks']}",
                f"-DOWN_BARRIER={int(var['bar'] == 'own')}", f"-DNO_BARRIER={int(var['ablate'] == 'nobarrier')}",
                f"-DNO_MATVEC={int(var['ablate'] == 'nomatvec')}", "-arch=sm_90")
        row = {**var, "blocks": grid, "smem_bytes": smem}
        try:
            kernel = cp.RawKernel(KERNEL, "probe", options=opts, enable_cooperative_groups=True)
            kernel.max_dynamic_shared_size_bytes = smem
            row["registers"] = kernel.num_regs
            resident = cp.cuda.driver.occupancyMaxActiveBlocksPerMultiprocessor(kernel.kernel.ptr, 256, smem)
            row["blocks_per_sm"] = resident
            sms = torch.cuda.get_device_properties(0).multi_processor_count
            row["resident_blocks"] = resident * sms
            if resident * sms < grid:
                row["error"] = f"{grid} blocks, {resident * sms} resident"
                results.append(row)
                print(row, flush=True)
                continue

            def launch(iters):
                hist = torch.zeros(iters + 1, dtype=torch.float64, device=dev)
                partial = torch.zeros(8 * grid, dtype=torch.float64, device=dev)
                counter.zero_()
                kernel((grid,), (256,), kernel_args(iters, hist, partial), shared_mem=smem)
                return hist, partial

            hist, _ = launch(10)
            torch.cuda.synchronize()
            if var["ablate"] == "none":
                x = bufs["x"].reshape(V, 3).double()
                err = float((x - x_ref).norm() / x_ref.norm())
                h = hist.cpu().tolist()
                row["x_rel_err"] = err
                row["rr_ratio_10"] = h[10] / h[0]
                row["rr_ratio_ref"] = hist_ref[10] / hist_ref[0]
            times = {}
            for iters in (10, 40):
                samples = []
                for _ in range(args.repeats):
                    hist = torch.zeros(iters + 1, dtype=torch.float64, device=dev)
                    partial = torch.zeros(8 * grid, dtype=torch.float64, device=dev)
                    counter.zero_()
                    packed = kernel_args(iters, hist, partial)
                    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                    start.record()
                    kernel((grid,), (256,), packed, shared_mem=smem)
                    end.record()
                    end.synchronize()
                    samples.append(start.elapsed_time(end) * 1e3)
                times[iters] = statistics.median(samples)
            row["us_10"] = times[10]
            row["us_per_iteration"] = (times[40] - times[10]) / 30
        except Exception as exc:  # noqa: BLE001 -- a probe: record and go on
            row["error"] = f"{type(exc).__name__}: {exc}"[:300]
        results.append(row)
        print(json.dumps(row), flush=True)
    if args.out:
        os.makedirs(args.out, exist_ok=True)
        with open(os.path.join(args.out, "cg_latency_probe.json"), "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
