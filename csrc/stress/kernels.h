// The stress family's per-item kernels (how they load and write: common/kernel_io.h): kernel 1 of
// the stress form, one element an item (StressElementKernel: the forces or their differential,
// into the compact or the padded layout), and the corotational element rotations (RotationKernel).
#pragma once

#include <cstdint>

#include "common/element_math.h"
#include "common/kernel_io.h"
#include "common/stress_args.h"

namespace tensormass {

template <int MODEL, bool DFORCE, int NN, int D, typename S, typename I, bool PADDED>
struct StressElementKernel {
  static constexpr bool kMembrane = NN - 1 < D;
  StressInputs<S, I> in;
  Writer<NN, D, S, I, PADDED> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    S m[NN][D], vol, lam, mu, u[NN][D], f[NN][D];
    Plane<D, S, kMembrane> plane;
    in.load_element(e, idx, m, vol, lam, mu, plane, u);
    if constexpr (MODEL == kCorotational) {
      // The rotations of the linearisation when given (9 loads, the CG path), else SOFA's QR
      // frame recomputed from u and the rest nodes (a uniform branch: one pointer per launch).
      S r[D][D];
      if (in.rotations != nullptr) {
        load_matrix<D, D, S>(in.rotations + e * (D * D), r);
      } else if constexpr (D == 3) {
        S x0[NN][D];
        load_matrix<NN, D, S>(in.rest + e * (NN * D), x0);
        qr_rotation<NN, S>(u, x0, r);
      }
      if (DFORCE) {
        S du[NN][D];
        gather_nodes<NN, D, S, I>(in.du, idx, du);
        corotational_dforces<NN, D, S, kMembrane>(du, r, m, vol, lam, mu, plane, f);
      } else {
        corotational_forces<NN, D, S, kMembrane>(u, r, m, vol, lam, mu, plane, f);
      }
    } else if (DFORCE) {
      S du[NN][D];
      gather_nodes<NN, D, S, I>(in.du, idx, du);
      stress_dforces<MODEL, NN, D, S, kMembrane>(u, du, m, vol, lam, mu, plane, f);
    } else {
      stress_forces<MODEL, NN, D, S, kMembrane>(u, m, vol, lam, mu, plane, f);
    }
    write(e, idx, f);
  }

};

// One item per element: its rotation R [D, D] at u (element_math.h: element_rotation), written
// to out [N, D, D]. Reads the rest nodes only where the method needs them (QR, polar membranes).
template <int METHOD, int NN, int D, typename S, typename I>
struct RotationKernel {
  static constexpr bool kMembrane = NN - 1 < D;
  static constexpr bool kNeedsRest = RotationNeedsRest<METHOD, kMembrane>::value;
  const S* u;              // [V, D]
  const I* elements;       // [N, NN]
  const S* shape_vectors;  // [N, NN, D] (polar)
  const S* projector;      // [N, D, D] (polar membranes)
  const S* rest;           // [N, NN, D] (QR, polar membranes)
  S* out;                  // [N, D, D]

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(elements + e * NN, idx);
    S x[NN][D], x0[NN][D], m[NN][D];
    gather_nodes<NN, D, S, I>(u, idx, x);
    if constexpr (kNeedsRest) load_matrix<NN, D, S>(rest + e * (NN * D), x0);
    if constexpr (METHOD == kPolar) load_matrix<NN, D, S>(shape_vectors + e * (NN * D), m);
    Plane<D, S, kMembrane> plane;
    if constexpr (kMembrane && METHOD == kPolar) load_matrix<D, D, S>(projector + e * (D * D), plane.p);
    S r[D][D];
    element_rotation<METHOD, NN, D, S, kMembrane>(x, x0, m, plane, r);
    S* p = out + e * (D * D);
    TM_UNROLL for (int a = 0; a < D; ++a) {
      TM_UNROLL for (int b = 0; b < D; ++b) p[a * D + b] = r[a][b];
    }
  }
};

}  // namespace tensormass
