// The tensor form's per-item kernels (how they load and write: common/kernel_io.h): kernel 1 of the
// hooke tensor form, one edge an item (TensorHookeEdgeKernel), and of the stvk tensor form, one
// element an item (TensorStvkKernel), into the compact or the padded layout.
#pragma once

#include <cstdint>

#include "common/element_math.h"
#include "common/kernel_io.h"

namespace tensormass {

// hooke: one item per edge [Ed, 2] with tensor edge_k [Ed, D, D].
template <int D, typename S, typename I, bool PADDED>
struct TensorHookeEdgeKernel {
  const S* u;       // [V, D]
  const I* edges;   // [Ed, 2]
  const S* edge_k;  // [Ed, D, D]
  Writer<2, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[2];
    load_block<2, I>(edges + e * 2, idx);
    S k[D][D];
    load_matrix<D, D, S>(edge_k + e * (D * D), k);
    S x[2][D], f[2][D];
    gather_nodes<2, D, S, I>(u, idx, x);
    tensor_hooke_edge<D, S>(k, x[0], x[1], f);
    write(e, idx, f);
  }
};

// stvk: one item per element with B [N, NN, NN, D, D], C [N, NN, NN, NN, D], D [N, NN, NN, NN, NN].
template <bool DFORCE, int NN, int D, typename S, typename I, bool PADDED>
struct TensorStvkKernel {
  const S* u;         // [V, D]
  const S* du;        // [V, D] (dforces only)
  const I* elements;  // [N, NN]
  const S* tb;
  const S* tc;
  const S* td;
  Writer<NN, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(elements + e * NN, idx);
    S x[NN][D], f[NN][D];
    gather_nodes<NN, D, S, I>(u, idx, x);
    const S* b = tb + e * (NN * NN * D * D);
    const S* c = tc + e * (NN * NN * NN * D);
    const S* d = td + e * (NN * NN * NN * NN);
    if (DFORCE) {
      S dx[NN][D];
      gather_nodes<NN, D, S, I>(du, idx, dx);
      tensor_stvk_dforces<NN, D, S>(x, dx, b, c, d, Loader{}, f);
    } else {
      tensor_stvk_forces<NN, D, S>(x, b, c, d, Loader{}, f);
    }
    write(e, idx, f);
  }
};

}  // namespace tensormass
