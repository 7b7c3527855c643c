// Element math of tensormass, written once for the CPU and the GPU.
//
// Every function here is a host/device inline function on fixed-size arrays: the loops have
// compile-time bounds and are unrolled, so under nvcc the arrays live in registers (no local
// memory). Templates:
//   NN  nodes per element (4 tetrahedra, 3 triangles; 2 for the edges of the hooke tensor form)
//   D   dimension of the node coordinates (3, or 2 for planar triangles)
//   S   scalar type (float, double)
//   M   membrane (triangles in 3-D): strains are projected on the rest plane, P E P
//
// The formulas are those of the pure-torch reference (tensormass_torch/reference/*.py), which is
// the oracle of the tests:
//   stress form   grad U = sum_j u_j (x) m_j
//     hooke       eps = P sym(grad U) P,                     sigma = lam tr(eps) P + 2 mu eps,
//                 f_j = -vol sigma m_j;  dforce(du) = forces(du)
//     stvk        E = P (sym(grad U) + 1/2 grad U^T grad U) P, S = lam tr(E) P + 2 mu E,
//                 f_j = -vol (I + grad U) S m_j
//                 df_j = -vol (dG S + dS + G dS) m_j,  dS = C : P sym(dG + G^T dG) P
//     corotational (SOFA's "large" QR frame, 3-D only; x0 the rest nodes, x = x0 + u)
//                 frame(p): rows ex = p1 - p0, ez = ex x (p2 - p0), ey = ez x ex, normalised;
//                 R = frame(x)^T frame(x0); eps' = P sym(R^T (P + grad U) - P) P,
//                 f_j = -vol R sigma(eps') m_j;  df_j = -vol R sigma(P sym(R^T grad dU) P) m_j
//                 (R held fixed in the differential, as SOFA does; R is recomputed per call)
//   tensor form   hooke: per edge (i<j) f_i = -K u_j, f_j = -K^T u_i; per node -K_ii u_i
//                 stvk:  Picinbono's B [n,n,d,d], C [n,n,n,d], D [n,n,n,n] (see tensor_form.py)
// (P = I for tetrahedra and planar triangles.)
#pragma once

#include <cstdint>
#include <math.h>

#if defined(__CUDACC__) || defined(__HIPCC__)
#define TM_HOST_DEVICE __host__ __device__
#define TM_INLINE __forceinline__
#define TM_UNROLL _Pragma("unroll")
#else
#define TM_HOST_DEVICE
#if defined(__GNUC__) || defined(__clang__)
#define TM_INLINE inline __attribute__((always_inline))
#else
#define TM_INLINE inline
#endif
#if defined(__clang__)
#define TM_UNROLL _Pragma("unroll")
#elif defined(__GNUC__)
#define TM_UNROLL  // g++ -O3 peels these small constant loops itself; forcing it only slows the build
#else
#define TM_UNROLL
#endif
#endif

#define TM_HD TM_HOST_DEVICE TM_INLINE

namespace tensormass {

// Model ids: the `model` integer of the op schemas (Python: tensormass_torch.native.MODEL_IDS).
enum Model : int { kHooke = 0, kStvk = 1, kCorotational = 2 };

// The tangent plane of an element: the identity (tetrahedra, planar triangles) or the rest
// projector P of a membrane. Same interface, so the formulas are written once.
template <int D, typename S, bool M>
struct Plane;

template <int D, typename S>
struct Plane<D, S, false> {
  TM_HD S id(int a, int b) const { return a == b ? S(1) : S(0); }
  TM_HD void project(S (&)[D][D]) const {}
};

template <int D, typename S>
struct Plane<D, S, true> {
  S p[D][D];
  TM_HD S id(int a, int b) const { return p[a][b]; }
  // e <- P e P
  TM_HD void project(S (&e)[D][D]) const {
    S t[D][D];
    TM_UNROLL for (int a = 0; a < D; ++a) {
      TM_UNROLL for (int b = 0; b < D; ++b) {
        S s = S(0);
        TM_UNROLL for (int c = 0; c < D; ++c) s += e[a][c] * p[c][b];
        t[a][b] = s;
      }
    }
    TM_UNROLL for (int a = 0; a < D; ++a) {
      TM_UNROLL for (int b = 0; b < D; ++b) {
        S s = S(0);
        TM_UNROLL for (int c = 0; c < D; ++c) s += p[a][c] * t[c][b];
        e[a][b] = s;
      }
    }
  }
};

// ------------------------------------------------------------------ small matrix helpers

// g = sum_j u_j (x) m_j
template <int NN, int D, typename S>
TM_HD void displacement_gradient(const S (&u)[NN][D], const S (&m)[NN][D], S (&g)[D][D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) {
    TM_UNROLL for (int b = 0; b < D; ++b) {
      S s = S(0);
      TM_UNROLL for (int j = 0; j < NN; ++j) s += u[j][a] * m[j][b];
      g[a][b] = s;
    }
  }
}

// out = a b
template <int D, typename S>
TM_HD void matmul(const S (&a)[D][D], const S (&b)[D][D], S (&out)[D][D]) {
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) {
      S s = S(0);
      TM_UNROLL for (int k = 0; k < D; ++k) s += a[i][k] * b[k][j];
      out[i][j] = s;
    }
  }
}

// out = a^T b
template <int D, typename S>
TM_HD void matmul_tn(const S (&a)[D][D], const S (&b)[D][D], S (&out)[D][D]) {
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) {
      S s = S(0);
      TM_UNROLL for (int k = 0; k < D; ++k) s += a[k][i] * b[k][j];
      out[i][j] = s;
    }
  }
}

// e = sym(a)
template <int D, typename S>
TM_HD void sym(const S (&a)[D][D], S (&e)[D][D]) {
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) e[i][j] = S(0.5) * (a[i][j] + a[j][i]);
  }
}

// s = lam tr(e) P + 2 mu e
template <int D, typename S, bool M>
TM_HD void isotropic(const S (&e)[D][D], S lam, S mu, const Plane<D, S, M>& plane, S (&s)[D][D]) {
  S tr = S(0);
  TM_UNROLL for (int i = 0; i < D; ++i) tr += e[i][i];
  const S lt = lam * tr;
  const S two_mu = S(2) * mu;
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) s[i][j] = lt * plane.id(i, j) + two_mu * e[i][j];
  }
}

// f_j = -vol p m_j
template <int NN, int D, typename S>
TM_HD void nodal(const S (&p)[D][D], const S (&m)[NN][D], S vol, S (&f)[NN][D]) {
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int a = 0; a < D; ++a) {
      S s = S(0);
      TM_UNROLL for (int b = 0; b < D; ++b) s += p[a][b] * m[j][b];
      f[j][a] = -vol * s;
    }
  }
}

// ------------------------------------------------------------------ stress form

// hooke: f_j = -vol sigma(eps(u)) m_j. Linear: the differential along du is hooke_forces(du).
template <int NN, int D, typename S, bool M>
TM_HD void hooke_forces(const S (&u)[NN][D], const S (&m)[NN][D], S vol, S lam, S mu,
                        const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S g[D][D], e[D][D], s[D][D];
  displacement_gradient<NN, D, S>(u, m, g);
  sym<D, S>(g, e);
  plane.project(e);
  isotropic<D, S, M>(e, lam, mu, plane, s);
  nodal<NN, D, S>(s, m, vol, f);
}

// Second Piola-Kirchhoff stress of St Venant-Kirchhoff at displacement gradient g.
template <int D, typename S, bool M>
TM_HD void stvk_second_pk(const S (&g)[D][D], S lam, S mu, const Plane<D, S, M>& plane, S (&s)[D][D]) {
  S gtg[D][D], e[D][D];
  matmul_tn<D, S>(g, g, gtg);
  sym<D, S>(g, e);
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) e[i][j] += S(0.5) * gtg[i][j];
  }
  plane.project(e);
  isotropic<D, S, M>(e, lam, mu, plane, s);
}

// stvk: f_j = -vol (I + G) S m_j
template <int NN, int D, typename S, bool M>
TM_HD void stvk_forces(const S (&u)[NN][D], const S (&m)[NN][D], S vol, S lam, S mu,
                       const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S g[D][D], s[D][D], gs[D][D];
  displacement_gradient<NN, D, S>(u, m, g);
  stvk_second_pk<D, S, M>(g, lam, mu, plane, s);
  matmul<D, S>(g, s, gs);
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) gs[i][j] += s[i][j];
  }
  nodal<NN, D, S>(gs, m, vol, f);
}

// stvk differential: df_j = -vol (dG S + dS + G dS) m_j, dS = C : P sym(dG + G^T dG) P
template <int NN, int D, typename S, bool M>
TM_HD void stvk_dforces(const S (&u)[NN][D], const S (&du)[NN][D], const S (&m)[NN][D], S vol, S lam,
                        S mu, const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S g[D][D], dg[D][D], s[D][D];
  displacement_gradient<NN, D, S>(u, m, g);
  displacement_gradient<NN, D, S>(du, m, dg);
  stvk_second_pk<D, S, M>(g, lam, mu, plane, s);
  S t[D][D], de[D][D], ds[D][D];
  matmul_tn<D, S>(g, dg, t);  // G^T dG
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) t[i][j] += dg[i][j];
  }
  sym<D, S>(t, de);
  plane.project(de);
  isotropic<D, S, M>(de, lam, mu, plane, ds);
  S p[D][D], q[D][D];
  matmul<D, S>(dg, s, p);   // dG S
  matmul<D, S>(g, ds, q);   // G dS
  TM_UNROLL for (int i = 0; i < D; ++i) {
    TM_UNROLL for (int j = 0; j < D; ++j) p[i][j] += ds[i][j] + q[i][j];
  }
  nodal<NN, D, S>(p, m, vol, f);
}

// Dispatch on the model at compile time.
template <int MODEL, int NN, int D, typename S, bool M>
TM_HD void stress_forces(const S (&u)[NN][D], const S (&m)[NN][D], S vol, S lam, S mu,
                         const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  if (MODEL == kHooke) {
    hooke_forces<NN, D, S, M>(u, m, vol, lam, mu, plane, f);
  } else {
    stvk_forces<NN, D, S, M>(u, m, vol, lam, mu, plane, f);
  }
}

template <int MODEL, int NN, int D, typename S, bool M>
TM_HD void stress_dforces(const S (&u)[NN][D], const S (&du)[NN][D], const S (&m)[NN][D], S vol, S lam,
                          S mu, const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  if (MODEL == kHooke) {
    hooke_forces<NN, D, S, M>(du, m, vol, lam, mu, plane, f);
  } else {
    stvk_dforces<NN, D, S, M>(u, du, m, vol, lam, mu, plane, f);
  }
}

// ------------------------------------------------------------------ corotational (QR frame)

TM_HD float tm_sqrt(float x) { return sqrtf(x); }
TM_HD double tm_sqrt(double x) { return sqrt(x); }

template <typename S>
TM_HD void cross3(const S (&a)[3], const S (&b)[3], S (&c)[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

// SOFA's frame of the nodes (p0, p1, p2): rows ex, ey, ez (normalised).
template <typename S>
TM_HD void qr_frame(const S (&p0)[3], const S (&p1)[3], const S (&p2)[3], S (&axes)[3][3]) {
  S ex[3], e2[3], ey[3], ez[3];
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    ex[a] = p1[a] - p0[a];
    e2[a] = p2[a] - p0[a];
  }
  cross3<S>(ex, e2, ez);
  cross3<S>(ez, ex, ey);
  const S nx = tm_sqrt(ex[0] * ex[0] + ex[1] * ex[1] + ex[2] * ex[2]);
  const S ny = tm_sqrt(ey[0] * ey[0] + ey[1] * ey[1] + ey[2] * ey[2]);
  const S nz = tm_sqrt(ez[0] * ez[0] + ez[1] * ez[1] + ez[2] * ez[2]);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    axes[0][a] = ex[a] / nx;
    axes[1][a] = ey[a] / ny;
    axes[2][a] = ez[a] / nz;
  }
}

// R = frame(x0 + u)^T frame(x0), from the first three nodes of the element.
template <int NN, typename S>
TM_HD void qr_rotation(const S (&u)[NN][3], const S (&x0)[NN][3], S (&r)[3][3]) {
  S x[3][3];
  TM_UNROLL for (int j = 0; j < 3; ++j) {
    TM_UNROLL for (int a = 0; a < 3; ++a) x[j][a] = x0[j][a] + u[j][a];
  }
  S cur[3][3], rest[3][3];
  qr_frame<S>(x[0], x[1], x[2], cur);
  qr_frame<S>(x0[0], x0[1], x0[2], rest);
  matmul_tn<3, S>(cur, rest, r);
}

// f_j = -vol R sigma(eps) m_j with eps = P sym(R^T g) P (g = R^T F - P already folded in by the
// caller for forces, g = grad dU for dforces).
template <int NN, typename S, bool M>
TM_HD void corotational_nodal(const S (&r)[3][3], const S (&t)[3][3], const S (&m)[NN][3], S vol, S lam,
                              S mu, const Plane<3, S, M>& plane, S (&f)[NN][3]) {
  S e[3][3], s[3][3], rs[3][3];
  sym<3, S>(t, e);
  plane.project(e);
  isotropic<3, S, M>(e, lam, mu, plane, s);
  matmul<3, S>(r, s, rs);
  nodal<NN, 3, S>(rs, m, vol, f);
}

template <int NN, typename S, bool M>
TM_HD void corotational_forces(const S (&u)[NN][3], const S (&x0)[NN][3], const S (&m)[NN][3], S vol, S lam,
                               S mu, const Plane<3, S, M>& plane, S (&f)[NN][3]) {
  S r[3][3], g[3][3], t[3][3];
  qr_rotation<NN, S>(u, x0, r);
  displacement_gradient<NN, 3, S>(u, m, g);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int b = 0; b < 3; ++b) g[a][b] += plane.id(a, b);  // F = P + grad U
  }
  matmul_tn<3, S>(r, g, t);  // R^T F
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int b = 0; b < 3; ++b) t[a][b] -= plane.id(a, b);
  }
  corotational_nodal<NN, S, M>(r, t, m, vol, lam, mu, plane, f);
}

template <int NN, typename S, bool M>
TM_HD void corotational_dforces(const S (&u)[NN][3], const S (&du)[NN][3], const S (&x0)[NN][3],
                                const S (&m)[NN][3], S vol, S lam, S mu, const Plane<3, S, M>& plane,
                                S (&f)[NN][3]) {
  S r[3][3], dg[3][3], t[3][3];
  qr_rotation<NN, S>(u, x0, r);
  displacement_gradient<NN, 3, S>(du, m, dg);
  matmul_tn<3, S>(r, dg, t);  // R^T grad dU
  corotational_nodal<NN, S, M>(r, t, m, vol, lam, mu, plane, f);
}

// ------------------------------------------------------------------ tensor form, hooke

// Edge (i < j) with tensor K mapping u_j to the force on i: f_i = -K u_j, f_j = -K^T u_i.
template <int D, typename S>
TM_HD void tensor_hooke_edge(const S (&k)[D][D], const S (&ui)[D], const S (&uj)[D], S (&f)[2][D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) {
    S si = S(0), sj = S(0);
    TM_UNROLL for (int b = 0; b < D; ++b) {
      si += k[a][b] * uj[b];
      sj += k[b][a] * ui[b];
    }
    f[0][a] = -si;
    f[1][a] = -sj;
  }
}

// ------------------------------------------------------------------ tensor form, stvk
//
// Picinbono's tensors of one element, read through a loader `ld(ptr)` (global memory: they are
// too many to keep in registers, 592 scalars for a tetrahedron) with the layouts
//   B [NN][NN][D][D], C [NN][NN][NN][D], Dt [NN][NN][NN][NN].
// forces  f_p = -( 2 sum_k B_pk u_k + 2 sum_k (sum_l C_pkl.u_l) u_k + sum_jk (u_j.u_k) C_jkp
//                  + 4 sum_k (sum_lm D_pklm (u_l.u_m)) u_k )
// dforces: the derivative of that along du (d_gram = du_j.u_k + u_j.du_k).
// C is read once: the contraction with u and the one with the Gram matrix share one pass.

template <int NN, int D, typename S, class Load>
TM_HD void tensor_stvk_forces(const S (&u)[NN][D], const S* b, const S* c, const S* dt, Load ld,
                              S (&f)[NN][D]) {
  S gram[NN][NN];
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0);
      TM_UNROLL for (int a = 0; a < D; ++a) s += u[j][a] * u[k][a];
      gram[j][k] = s;
    }
  }
  S grad[NN][D];
  // 2 sum_k B_pk u_k
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int a = 0; a < D; ++a) {
      S s = S(0);
      TM_UNROLL for (int k = 0; k < NN; ++k) {
        TM_UNROLL for (int bb = 0; bb < D; ++bb) s += ld(b + ((p * NN + k) * D + a) * D + bb) * u[k][bb];
      }
      grad[p][a] = S(2) * s;
    }
  }
  // one pass over C: cu[j][k] = sum_l C_jkl . u_l ; t3[l] = sum_jk gram_jk C_jkl
  S cu[NN][NN];
  S t3[NN][D];
  TM_UNROLL for (int l = 0; l < NN; ++l) {
    TM_UNROLL for (int a = 0; a < D; ++a) t3[l][a] = S(0);
  }
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0);
      TM_UNROLL for (int l = 0; l < NN; ++l) {
        TM_UNROLL for (int a = 0; a < D; ++a) {
          const S cv = ld(c + ((j * NN + k) * NN + l) * D + a);
          s += cv * u[l][a];
          t3[l][a] += gram[j][k] * cv;
        }
      }
      cu[j][k] = s;
    }
  }
  // dg[p][k] = sum_lm D_pklm gram_lm
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0);
      TM_UNROLL for (int l = 0; l < NN; ++l) {
        TM_UNROLL for (int mm = 0; mm < NN; ++mm) s += ld(dt + ((p * NN + k) * NN + l) * NN + mm) * gram[l][mm];
      }
      // grad_p += (2 cu_pk + 4 dg_pk) u_k
      const S w = S(2) * cu[p][k] + S(4) * s;
      TM_UNROLL for (int a = 0; a < D; ++a) grad[p][a] += w * u[k][a];
    }
  }
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int a = 0; a < D; ++a) f[p][a] = -(grad[p][a] + t3[p][a]);
  }
}

template <int NN, int D, typename S, class Load>
TM_HD void tensor_stvk_dforces(const S (&u)[NN][D], const S (&du)[NN][D], const S* b, const S* c,
                               const S* dt, Load ld, S (&f)[NN][D]) {
  S gram[NN][NN], dgram[NN][NN];
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0), t = S(0);
      TM_UNROLL for (int a = 0; a < D; ++a) {
        s += u[j][a] * u[k][a];
        t += du[j][a] * u[k][a] + u[j][a] * du[k][a];
      }
      gram[j][k] = s;
      dgram[j][k] = t;
    }
  }
  S grad[NN][D];
  // 2 sum_k B_pk du_k
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int a = 0; a < D; ++a) {
      S s = S(0);
      TM_UNROLL for (int k = 0; k < NN; ++k) {
        TM_UNROLL for (int bb = 0; bb < D; ++bb) s += ld(b + ((p * NN + k) * D + a) * D + bb) * du[k][bb];
      }
      grad[p][a] = S(2) * s;
    }
  }
  // one pass over C: cu = C.u, cdu = C.du, t3[l] = sum_jk dgram_jk C_jkl
  S cu[NN][NN], cdu[NN][NN];
  S t3[NN][D];
  TM_UNROLL for (int l = 0; l < NN; ++l) {
    TM_UNROLL for (int a = 0; a < D; ++a) t3[l][a] = S(0);
  }
  TM_UNROLL for (int j = 0; j < NN; ++j) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0), t = S(0);
      TM_UNROLL for (int l = 0; l < NN; ++l) {
        TM_UNROLL for (int a = 0; a < D; ++a) {
          const S cv = ld(c + ((j * NN + k) * NN + l) * D + a);
          s += cv * u[l][a];
          t += cv * du[l][a];
          t3[l][a] += dgram[j][k] * cv;
        }
      }
      cu[j][k] = s;
      cdu[j][k] = t;
    }
  }
  // D . gram and D . dgram in one pass over D
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int k = 0; k < NN; ++k) {
      S s = S(0), t = S(0);
      TM_UNROLL for (int l = 0; l < NN; ++l) {
        TM_UNROLL for (int mm = 0; mm < NN; ++mm) {
          const S dv = ld(dt + ((p * NN + k) * NN + l) * NN + mm);
          s += dv * gram[l][mm];
          t += dv * dgram[l][mm];
        }
      }
      // grad_p += (2 cu_pk + 4 Dg_pk) du_k + (2 cdu_pk + 4 Ddg_pk) u_k
      const S wdu = S(2) * cu[p][k] + S(4) * s;
      const S wu = S(2) * cdu[p][k] + S(4) * t;
      TM_UNROLL for (int a = 0; a < D; ++a) grad[p][a] += wdu * du[k][a] + wu * u[k][a];
    }
  }
  TM_UNROLL for (int p = 0; p < NN; ++p) {
    TM_UNROLL for (int a = 0; a < D; ++a) f[p][a] = -(grad[p][a] + t3[p][a]);
  }
}

}  // namespace tensormass
