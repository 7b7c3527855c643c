// How the per-item kernel bodies load and write (ld, load_block, gather_nodes, Writer). The bodies
// (each family's kernels.h, and common/ for those several families share) are shared by the CPU
// (at::parallel_for) and CUDA (one thread per item) implementations: load one element (or edge,
// or node), call the element math of element_math.h, write the result. Each body is a small
// functor with a host/device `operator()(int64_t item)`; the launchers (common/cpu_launcher.h,
// common/cuda_launcher.cuh) only decide how the items are iterated.
//
// The paper's Algorithm 1, no atomics:
//   kernel 1 (one thread per element e): partial force on each local node v written to
//            PartialForce[ForceIndex[e][v]][index[e][v]]   (padded buffer [N_n, V, d])
//            or, for the element-level ops, to out[e][v]    (compact [N, n, d]);
//   kernel 2 (one thread per node i): TotalForce[i] = (node term) + sum_{s < incidences[i]}
//            PartialForce[s][i]: every slot it reads was written once, in a fixed order, so
//            the result is bitwise reproducible and the unused slots are never read (the
//            buffer is allocated uninitialised; common/gather.h).
// The hooke tensor form's CG matvec also has a one-kernel variant (NodeHookeSystemKernel,
// common/node_graph.h): one thread per node reads its slots' neighbours and edge tensors and sums
// the same terms in the same slot order, bitwise equal to kernels 1 + 2, without the PartialForce
// round trip.
//
// Layouts (all row-major contiguous, as the Python groups store them):
//   u, du [V, D]; elements / force_index [N, NN] (int32 or int64); shape_vectors [N, NN, D];
//   measure, lam, mu [N]; projector [N, D, D]; PartialForce [N_n, V, D]; out [V, D];
//   corotational: rest element nodes [N, NN, 3], rotations [N, D, D].
// The per-element blocks (shape vectors, indices, projector) are contiguous per element, so a
// thread reads its own contiguous bytes; on the GPU they are read with 16-byte vector loads when
// aligned (see load_block). PartialForce [N_n, V, D] makes kernel 2 coalesced: the threads of a
// warp read consecutive nodes of one slot.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <cstring>

#include "common/element_math.h"

namespace tensormass {

// Read-only load: through the read-only data cache on the GPU.
template <typename T>
TM_HD T ld(const T* p) {
#if defined(__CUDA_ARCH__)
  return __ldg(p);
#else
  return *p;
#endif
}

struct Loader {
  template <typename T>
  TM_HD T operator()(const T* p) const { return ld(p); }
};

// Load 16 bytes (16 / sizeof(T) values) from a 16-byte aligned p: one vector load on the GPU.
template <typename T>
TM_HD void load16(const T* p, T* out) {
#if defined(__CUDA_ARCH__)
  const int4 v = __ldg(reinterpret_cast<const int4*>(p));
  const T* t = reinterpret_cast<const T*>(&v);
  TM_UNROLL for (int k = 0; k < int(16 / sizeof(T)); ++k) out[k] = t[k];
#else
  std::memcpy(out, p, 16);
#endif
}

// Load K contiguous values starting at p into out: with 16-byte loads when K * sizeof(T) is a
// multiple of 16 and p is 16-byte aligned (a runtime check, uniform across a warp for the
// per-element blocks of contiguous tensors), else one value at a time. The same path runs on
// the CPU (memcpy), so the CPU tests exercise its indexing.
template <int K, typename T>
TM_HD void load_block(const T* p, T (&out)[K]) {
  constexpr int kPer = int(16 / sizeof(T));
  if ((K * sizeof(T)) % 16 == 0 && (reinterpret_cast<uintptr_t>(p) & 15) == 0) {
    TM_UNROLL for (int i = 0; i < K / kPer; ++i) load16<T>(p + i * kPer, out + i * kPer);
    return;
  }
  TM_UNROLL for (int k = 0; k < K; ++k) out[k] = ld(p + k);
}

template <int NN, int D, typename T>
TM_HD void load_matrix(const T* p, T (&out)[NN][D]) {
  T flat[NN * D];
  load_block<NN * D, T>(p, flat);
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int a = 0; a < D; ++a) out[j][a] = flat[j * D + a];
  }
}

// Gather the D-vectors of the NN nodes idx[] from a [V, D] field.
template <int NN, int D, typename S, typename I>
TM_HD void gather_nodes(const S* field, const I (&idx)[NN], S (&out)[NN][D]) {
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    const S* p = field + static_cast<int64_t>(idx[j]) * D;
    TM_UNROLL for (int a = 0; a < D; ++a) out[j][a] = ld(p + a);
  }
}

// Where kernel 1 writes: compact [N, NN, D] (element-level ops) or padded [N_n, V, D].
template <int NN, int D, typename S, typename I, bool PADDED>
struct Writer;

template <int NN, int D, typename S, typename I>
struct Writer<NN, D, S, I, false> {
  S* out;
  TM_HD void operator()(int64_t e, const I (&)[NN], const S (&f)[NN][D]) const {
    S* p = out + e * (NN * D);
    TM_UNROLL for (int j = 0; j < NN; ++j) {
      TM_UNROLL for (int a = 0; a < D; ++a) p[j * D + a] = f[j][a];
    }
  }
};

template <int NN, int D, typename S, typename I>
struct Writer<NN, D, S, I, true> {
  S* out;                  // PartialForce [N_n, V, D]
  const I* force_index;    // [N, NN]
  int64_t num_nodes;       // V
  TM_HD void operator()(int64_t e, const I (&idx)[NN], const S (&f)[NN][D]) const {
    I slot[NN];
    load_block<NN, I>(force_index + e * NN, slot);
    TM_UNROLL for (int j = 0; j < NN; ++j) {
      S* p = out + (static_cast<int64_t>(slot[j]) * num_nodes + static_cast<int64_t>(idx[j])) * D;
      TM_UNROLL for (int a = 0; a < D; ++a) p[a] = f[j][a];
    }
  }
};

// Padded writers also need the slots and V.
template <int NN, int D, typename S, typename I>
void set_padded(Writer<NN, D, S, I, false>&, const at::Tensor&, int64_t) {}

template <int NN, int D, typename S, typename I>
void set_padded(Writer<NN, D, S, I, true>& w, const at::Tensor& force_index, int64_t num_nodes) {
  w.force_index = force_index.data_ptr<I>();
  w.num_nodes = num_nodes;
}

}  // namespace tensormass
