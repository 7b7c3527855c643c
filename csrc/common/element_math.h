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
// The formulas are those of the pure-torch reference (tensormass_torch/ops/reference/*.py), which is
// the oracle of the tests:
//   stress form   grad U = sum_j u_j (x) m_j
//     hooke       eps = P sym(grad U) P,                     sigma = lam tr(eps) P + 2 mu eps,
//                 f_j = -vol sigma m_j;  dforce(du) = forces(du)
//     stvk        E = P (sym(grad U) + 1/2 grad U^T grad U) P, S = lam tr(E) P + 2 mu E,
//                 f_j = -vol (I + grad U) S m_j
//                 df_j = -vol (dG S + dS + G dS) m_j,  dS = C : P sym(dG + G^T dG) P
//     corotational  eps' = P sym(R^T (P + grad U) - P) P,  f_j = -vol R sigma(eps') m_j,
//                 df_j = -vol R sigma(P sym(R^T grad dU) P) m_j   (R held fixed, as SOFA does)
//                 with the element rotation R [D, D] (computed once per linearisation, or per call):
//       QR frame  (SOFA's "large", 3-D only; x0 the rest nodes, x = x0 + u)
//                 frame(p): rows ex = p1 - p0, ez = ex x (p2 - p0), ey = ez x ex, normalised;
//                 R = frame(x)^T frame(x0)
//       polar     R = the closest proper rotation to F = P + grad U (the rotation factor of
//                 F = R S; inverted elements: the singular vector of the smallest singular value
//                 flipped); membranes map the rest normal n0 onto the current normal n first,
//                 F + n n0^T (reference: corotational.polar_rotations, ops.linearize)
//   tensor form   hooke: per edge (i<j) w = u_j - u_i, f_i = -K w, f_j = K^T w (K_ii = -sum_j K_ij)
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

// Model ids: the `model` integer of the op schemas (Python: tensormass_torch.ops.library.MODEL_IDS).
// kStvkDefinite: stvk's forces with a positive semi-definite tangent (see stvk_definite_dforces).
enum Model : int { kHooke = 0, kStvk = 1, kCorotational = 2, kStvkDefinite = 3 };

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

template <int D, typename S>
TM_HD void positive_part(const S (&s)[D][D], S (&sp)[D][D]);

// stvk differential: df_j = -vol (dG S + dS + G dS) m_j, dS = C : P sym(dG + G^T dG) P.
// DEFINITE: the geometric term dG S uses S+, the positive part of S (its negative eigenvalues
// set to 0). The material part (dS, G dS) is positive semi-definite whatever the strain, and
// dG S+ is too (its quadratic form is vol sum (m_i . S+ m_j) du_i . du_j), so the implicit system
// M - h^2 K stays positive definite under compression, where S has negative eigenvalues and the
// exact tangent is indefinite (a CG breakdown). Forces and energy are unchanged.
template <int NN, int D, typename S, bool M, bool DEFINITE = false>
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
  if (DEFINITE) {
    S sp[D][D];
    positive_part<D, S>(s, sp);
    TM_UNROLL for (int i = 0; i < D; ++i) {
      TM_UNROLL for (int j = 0; j < D; ++j) s[i][j] = sp[i][j];
    }
  }
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
  } else if (MODEL == kStvkDefinite) {
    stvk_dforces<NN, D, S, M, true>(u, du, m, vol, lam, mu, plane, f);
  } else {
    stvk_dforces<NN, D, S, M, false>(u, du, m, vol, lam, mu, plane, f);
  }
}

// ------------------------------------------------------------------ corotational rotations

TM_HD float tm_sqrt(float x) { return sqrtf(x); }
TM_HD double tm_sqrt(double x) { return sqrt(x); }
TM_HD float tm_floor(float x) { return floorf(x); }
TM_HD double tm_floor(double x) { return floor(x); }
TM_HD float tm_abs(float x) { return fabsf(x); }
TM_HD double tm_abs(double x) { return fabs(x); }

template <typename S>
TM_HD void cross3(const S (&a)[3], const S (&b)[3], S (&c)[3]) {
  c[0] = a[1] * b[2] - a[2] * b[1];
  c[1] = a[2] * b[0] - a[0] * b[2];
  c[2] = a[0] * b[1] - a[1] * b[0];
}

template <typename S>
TM_HD S dot3(const S (&a)[3], const S (&b)[3]) {
  return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

// v / |v| (v != 0)
template <typename S>
TM_HD void normalize3(S (&v)[3]) {
  const S inv = S(1) / tm_sqrt(dot3<S>(v, v));
  TM_UNROLL for (int a = 0; a < 3; ++a) v[a] *= inv;
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

// ---- polar decomposition, 3 x 3
//
// Method: one-sided (Hestenes) Jacobi SVD of F, then R = U V^T built from the two largest
// singular directions only.
//   * One-sided Jacobi rotates the columns of B = F V (V accumulates the rotations) until they
//     are orthogonal; it never forms F^T F, so the conditioning is that of F, not its square:
//     nearly flat elements (tiny sigma_3) keep full accuracy in float32 too.
//   * A fixed number of cyclic sweeps (3 rotations each) and selects instead of branches: every
//     thread of a warp runs the same instructions, and the result is deterministic. Quadratic
//     convergence: 4 sweeps reach double rounding on 3e5 random matrices (3 do not); float32
//     uses 4, double 5 (one spare).
//   * The columns are sorted by norm (a 3-comparator network), then u1 = b1/|b1|,
//     u2 = b2 orthonormalised against u1, u3 = u1 x u2, v3 = v1 x v2: U and V are proper by
//     construction, so R = U V^T is a proper rotation, and it is the closest one to F (Kabsch):
//     when det F < 0 the sign goes to the smallest singular direction, exactly what the
//     reference's SVD sign fix does. sigma_3 itself is never used, so its sign and accuracy do
//     not matter; R is only ill-determined where the problem is (sigma_2 ~ sigma_3 with det F <
//     0, or rank F < 2), and stays a finite proper rotation there.
//   * F is scaled by 1 / max|F_ab| first (R(a F) = R(F) for a > 0): no overflow or underflow in
//     the squared norms, whatever the element size. F = 0 gives R = I.
template <typename S>
struct PolarSweeps {
  static constexpr int value = 5;
};
template <>
struct PolarSweeps<float> {
  static constexpr int value = 4;
};

// One Jacobi rotation of the columns P < Q of b (and of v): makes b_P . b_Q = 0.
template <int P, int Q, typename S>
TM_HD void jacobi_columns(S (&b)[3][3], S (&v)[3][3]) {
  S alpha = S(0), beta = S(0), gamma = S(0);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    alpha += b[a][P] * b[a][P];
    beta += b[a][Q] * b[a][Q];
    gamma += b[a][P] * b[a][Q];
  }
  // t = tan(theta), the smaller root of t^2 + 2 zeta t - 1 = 0 with zeta = (beta - alpha) / (2 gamma),
  // written without dividing by gamma: t = sgn(h) gamma / (|h| + hypot(h, gamma)), h = (beta - alpha) / 2.
  const S h = S(0.5) * (beta - alpha);
  const S den = tm_abs(h) + tm_sqrt(h * h + gamma * gamma);
  const S num = h >= S(0) ? gamma : -gamma;
  const S t = den > S(0) ? num / den : S(0);
  const S c = S(1) / tm_sqrt(S(1) + t * t);
  const S s = c * t;
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    const S bp = b[a][P], bq = b[a][Q];
    b[a][P] = c * bp - s * bq;
    b[a][Q] = s * bp + c * bq;
    const S vp = v[a][P], vq = v[a][Q];
    v[a][P] = c * vp - s * vq;
    v[a][Q] = s * vp + c * vq;
  }
}

// Orders the columns P < Q of b and v (and their squared norms n) by decreasing norm.
template <int P, int Q, typename S>
TM_HD void order_columns(S (&b)[3][3], S (&v)[3][3], S (&n)[3]) {
  const bool swap = n[P] < n[Q];
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    const S bp = b[a][P], bq = b[a][Q], vp = v[a][P], vq = v[a][Q];
    b[a][P] = swap ? bq : bp;
    b[a][Q] = swap ? bp : bq;
    v[a][P] = swap ? vq : vp;
    v[a][Q] = swap ? vp : vq;
  }
  const S np = n[P], nq = n[Q];
  n[P] = swap ? nq : np;
  n[Q] = swap ? np : nq;
}

// One-sided Jacobi SVD of f / scale (scale = max |f_ab|; f = 0 is taken as I): on return the
// columns of b = (f / scale) v are orthogonal, v is orthogonal; returns scale (0 for f = 0).
template <typename S>
TM_HD S jacobi_svd3(const S (&f)[3][3], S (&b)[3][3], S (&v)[3][3]) {
  S scale = S(0);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int k = 0; k < 3; ++k) scale = tm_abs(f[a][k]) > scale ? tm_abs(f[a][k]) : scale;
  }
  const bool zero = !(scale > S(0));
  const S inv = zero ? S(1) : S(1) / scale;
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int k = 0; k < 3; ++k) {
      v[a][k] = a == k ? S(1) : S(0);
      b[a][k] = zero ? v[a][k] : f[a][k] * inv;
    }
  }
  TM_UNROLL for (int sweep = 0; sweep < PolarSweeps<S>::value; ++sweep) {
    jacobi_columns<0, 1, S>(b, v);
    jacobi_columns<0, 2, S>(b, v);
    jacobi_columns<1, 2, S>(b, v);
  }
  return zero ? S(0) : scale;
}

// R = the closest proper rotation to f (the polar factor, sign-fixed for det f < 0); see above.
template <typename S>
TM_HD void polar_rotation(const S (&f)[3][3], S (&r)[3][3]) {
  S b[3][3], v[3][3];
  jacobi_svd3<S>(f, b, v);
  S n[3];
  TM_UNROLL for (int k = 0; k < 3; ++k) n[k] = b[0][k] * b[0][k] + b[1][k] * b[1][k] + b[2][k] * b[2][k];
  order_columns<0, 1, S>(b, v, n);
  order_columns<1, 2, S>(b, v, n);
  order_columns<0, 1, S>(b, v, n);
  // n[0] >= |F / scale|_F^2 / 3 >= 1/3: u1 is well defined.
  S u1[3], u2[3], u3[3], v1[3], v2[3], v3[3];
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    u1[a] = b[a][0];
    u2[a] = b[a][1];
    v1[a] = v[a][0];
    v2[a] = v[a][1];
  }
  normalize3<S>(u1);
  const S proj = dot3<S>(u1, u2);
  TM_UNROLL for (int a = 0; a < 3; ++a) u2[a] -= proj * u1[a];
  // rank F < 2: any unit vector orthogonal to u1 (u1 x the axis it is least aligned with)
  const S w2 = dot3<S>(u2, u2);
  const S ax = tm_abs(u1[0]), ay = tm_abs(u1[1]), az = tm_abs(u1[2]);
  const int axis = (ax <= ay && ax <= az) ? 0 : (ay <= az ? 1 : 2);
  S e[3] = {S(0), S(0), S(0)};
  e[axis] = S(1);
  S perp[3];
  cross3<S>(u1, e, perp);
  const bool degenerate = !(w2 > S(1e-30) * n[0]);
  TM_UNROLL for (int a = 0; a < 3; ++a) u2[a] = degenerate ? perp[a] : u2[a];
  normalize3<S>(u2);
  cross3<S>(u1, u2, u3);
  cross3<S>(v1, v2, v3);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int k = 0; k < 3; ++k) r[a][k] = u1[a] * v1[k] + u2[a] * v2[k] + u3[a] * v3[k];
  }
}

// 2 x 2: the rotation by angle atan2(f10 - f01, f00 + f11) maximises tr(R^T F) over SO(2), which
// is the closest proper rotation (the SVD sign fix included). f00 + f11 = f10 - f01 = 0 (no
// unique answer) gives R = I.
template <typename S>
TM_HD void polar_rotation(const S (&f)[2][2], S (&r)[2][2]) {
  const S c = f[0][0] + f[1][1], s = f[1][0] - f[0][1];
  const S scale = tm_abs(c) > tm_abs(s) ? tm_abs(c) : tm_abs(s);
  const bool zero = !(scale > S(0));
  const S cs = zero ? S(1) : c / scale, ss = zero ? S(0) : s / scale;
  const S inv = S(1) / tm_sqrt(cs * cs + ss * ss);
  r[0][0] = cs * inv;
  r[0][1] = -ss * inv;
  r[1][0] = ss * inv;
  r[1][1] = cs * inv;
}

// ---- positive part of a symmetric matrix (stvk's definite tangent)
//
// S+ = (S + |S|) / 2 with |S| = sqrt(S^T S) = V diag(sigma) V^T from the one-sided Jacobi SVD
// above (b = S V with orthogonal columns of norms sigma_k). |S| is unique even where V is not
// (eigenvalues +l and -l), so S+ is exact up to the sweeps' rounding. 2 x 2: in closed form.
template <typename S>
TM_HD void positive_part3(const S (&s)[3][3], S (&sp)[3][3]) {
  S b[3][3], v[3][3];
  const S scale = jacobi_svd3<S>(s, b, v);
  const bool zero = !(scale > S(0));
  S sigma[3];
  TM_UNROLL for (int k = 0; k < 3; ++k) sigma[k] = tm_sqrt(b[0][k] * b[0][k] + b[1][k] * b[1][k] + b[2][k] * b[2][k]);
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    TM_UNROLL for (int c = 0; c < 3; ++c) {
      S abs_ac = S(0);
      TM_UNROLL for (int k = 0; k < 3; ++k) abs_ac += sigma[k] * v[a][k] * v[c][k];
      sp[a][c] = zero ? S(0) : S(0.5) * (s[a][c] + scale * abs_ac);
    }
  }
}

// 2 x 2: eigenvalues l+ >= l-; S+ = S (l- >= 0), 0 (l+ <= 0), else l+ (S - l- I) / (l+ - l-).
template <typename S>
TM_HD void positive_part2(const S (&s)[2][2], S (&sp)[2][2]) {
  const S half_tr = S(0.5) * (s[0][0] + s[1][1]);
  const S half_diff = S(0.5) * (s[0][0] - s[1][1]);
  const S off = S(0.5) * (s[0][1] + s[1][0]);
  const S rad = tm_sqrt(half_diff * half_diff + off * off);
  const S lp = half_tr + rad, lm = half_tr - rad;
  const S w = (lp > S(0) && lm < S(0)) ? lp / (lp - lm) : (lm >= S(0) ? S(1) : S(0));
  const S shift = (lp > S(0) && lm < S(0)) ? lm : S(0);
  TM_UNROLL for (int a = 0; a < 2; ++a) {
    TM_UNROLL for (int c = 0; c < 2; ++c) sp[a][c] = w * (s[a][c] - (a == c ? shift : S(0)));
  }
}

template <int D, typename S>
TM_HD void positive_part(const S (&s)[D][D], S (&sp)[D][D]) {
  if constexpr (D == 3) {
    positive_part3<S>(s, sp);
  } else {
    positive_part2<S>(s, sp);
  }
}

// Rotation methods: the `method` integer of tensormass::corotational_rotations.
enum RotationMethod : int { kQr = 0, kPolar = 1 };

// Whether the rotation of an element needs its rest nodes x0: the QR frame, and polar membranes
// (their rest normal).
template <int METHOD, bool M>
struct RotationNeedsRest {
  static constexpr bool value = METHOD == kQr || M;
};

// The rotation of one element at displacements u: METHOD kQr (3-D) or kPolar. F = P + grad U;
// membranes (M) add n n0^T, n0 / n the unit normals of the rest / current triangle, so that F
// maps the whole space (the reference's linearize does the same).
template <int METHOD, int NN, int D, typename S, bool M>
TM_HD void element_rotation(const S (&u)[NN][D], const S (&x0)[NN][D], const S (&m)[NN][D],
                            const Plane<D, S, M>& plane, S (&r)[D][D]) {
  if constexpr (METHOD == kQr) {
    static_assert(D == 3, "the QR frame needs 3-D elements");
    qr_rotation<NN, S>(u, x0, r);
  } else {
    S f[D][D];
    displacement_gradient<NN, D, S>(u, m, f);
    TM_UNROLL for (int a = 0; a < D; ++a) {
      TM_UNROLL for (int b = 0; b < D; ++b) f[a][b] += plane.id(a, b);
    }
    if constexpr (M) {
      S e1[3], e2[3], n[3], r1[3], r2[3], n0[3];
      TM_UNROLL for (int a = 0; a < 3; ++a) {
        e1[a] = (x0[1][a] + u[1][a]) - (x0[0][a] + u[0][a]);
        e2[a] = (x0[2][a] + u[2][a]) - (x0[0][a] + u[0][a]);
        r1[a] = x0[1][a] - x0[0][a];
        r2[a] = x0[2][a] - x0[0][a];
      }
      cross3<S>(e1, e2, n);
      cross3<S>(r1, r2, n0);
      normalize3<S>(n);
      normalize3<S>(n0);
      TM_UNROLL for (int a = 0; a < 3; ++a) {
        TM_UNROLL for (int b = 0; b < 3; ++b) f[a][b] += n[a] * n0[b];
      }
    }
    polar_rotation<S>(f, r);
  }
}

// ------------------------------------------------------------------ corotational forces

// f_j = -vol R sigma(eps) m_j with eps = P sym(t) P (t = R^T F - P for forces, R^T grad dU for
// dforces).
template <int NN, int D, typename S, bool M>
TM_HD void corotational_nodal(const S (&r)[D][D], const S (&t)[D][D], const S (&m)[NN][D], S vol, S lam,
                              S mu, const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S e[D][D], s[D][D], rs[D][D];
  sym<D, S>(t, e);
  plane.project(e);
  isotropic<D, S, M>(e, lam, mu, plane, s);
  matmul<D, S>(r, s, rs);
  nodal<NN, D, S>(rs, m, vol, f);
}

// Forces with the rotation r given.
template <int NN, int D, typename S, bool M>
TM_HD void corotational_forces(const S (&u)[NN][D], const S (&r)[D][D], const S (&m)[NN][D], S vol, S lam,
                               S mu, const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S g[D][D], t[D][D];
  displacement_gradient<NN, D, S>(u, m, g);
  TM_UNROLL for (int a = 0; a < D; ++a) {
    TM_UNROLL for (int b = 0; b < D; ++b) g[a][b] += plane.id(a, b);  // F = P + grad U
  }
  matmul_tn<D, S>(r, g, t);  // R^T F
  TM_UNROLL for (int a = 0; a < D; ++a) {
    TM_UNROLL for (int b = 0; b < D; ++b) t[a][b] -= plane.id(a, b);
  }
  corotational_nodal<NN, D, S, M>(r, t, m, vol, lam, mu, plane, f);
}

// Differential along du with the rotation r given (held fixed).
template <int NN, int D, typename S, bool M>
TM_HD void corotational_dforces(const S (&du)[NN][D], const S (&r)[D][D], const S (&m)[NN][D], S vol, S lam,
                                S mu, const Plane<D, S, M>& plane, S (&f)[NN][D]) {
  S dg[D][D], t[D][D];
  displacement_gradient<NN, D, S>(du, m, dg);
  matmul_tn<D, S>(r, dg, t);  // R^T grad dU
  corotational_nodal<NN, D, S, M>(r, t, m, vol, lam, mu, plane, f);
}

// ------------------------------------------------------------------ tensor form, hooke

// Edge (i < j) with tensor K = K_ij mapping u_j to the force on i. Since every row of an element's
// blocks sums to zero (sum_k m_k = 0), K_ii = -sum_j K_ij and F_i = -sum_j K_ij (u_j - u_i): the
// edge acts on the difference w = u_j - u_i, f_i = -K w, f_j = K^T w, with no vertex term. In
// differences a rigid translation cancels exactly and float32 keeps its digits (summing
// -K_ii u_i and -K_ij u_j cancels the large absolute displacements: 0.3-0.6 % errors).
template <int D, typename S>
TM_HD void tensor_hooke_edge(const S (&k)[D][D], const S (&ui)[D], const S (&uj)[D], S (&f)[2][D]) {
  S w[D];
  TM_UNROLL for (int a = 0; a < D; ++a) w[a] = uj[a] - ui[a];
  TM_UNROLL for (int a = 0; a < D; ++a) {
    S si = S(0), sj = S(0);
    TM_UNROLL for (int b = 0; b < D; ++b) {
      si += k[a][b] * w[b];
      sj += k[b][a] * w[b];
    }
    f[0][a] = -si;
    f[1][a] = sj;
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

// ------------------------------------------------------------------ element tensors from the rest shape

// The shape vectors m [NN][D] of an element from its rest nodes x0 [NN][D] (the gradients of its
// barycentric coordinates: with the edges E = x0_j - x0_0 (j >= 1) and their Gram matrix
// G = E E^T, m_j = (G^-1 E)_j and m_0 = -sum_j m_j, as mesh.geometry.shape_vectors), and the
// tangent projector P = E^T G^-1 E (the identity for tetrahedra and planar triangles, the rest
// plane's projector for membranes). G is 2x2 or 3x3, inverted through its adjugate.
template <int NN, int D, typename S>
TM_HD void rest_shape_vectors(const S (&x0)[NN][D], S (&m)[NN][D], S (&proj)[D][D]) {
  constexpr int K = NN - 1;
  S e[K][D];
  TM_UNROLL for (int j = 0; j < K; ++j) {
    TM_UNROLL for (int a = 0; a < D; ++a) e[j][a] = x0[j + 1][a] - x0[0][a];
  }
  S g[K][K];
  TM_UNROLL for (int i = 0; i < K; ++i) {
    TM_UNROLL for (int j = 0; j < K; ++j) {
      S s = S(0);
      TM_UNROLL for (int a = 0; a < D; ++a) s += e[i][a] * e[j][a];
      g[i][j] = s;
    }
  }
  S inv[K][K];
  if (K == 2) {
    const S det = g[0][0] * g[1][1] - g[0][1] * g[1][0];
    inv[0][0] = g[1][1] / det;
    inv[0][1] = -g[0][1] / det;
    inv[1][0] = -g[1][0] / det;
    inv[1][1] = g[0][0] / det;
  } else {
    // adjugate of a 3x3 (indices taken mod 3 so that the 2x2 instantiation compiles too)
    S c[K][K];
    TM_UNROLL for (int i = 0; i < K; ++i) {
      TM_UNROLL for (int j = 0; j < K; ++j) {
        const int i1 = (i + 1) % K, i2 = (i + 2) % K, j1 = (j + 1) % K, j2 = (j + 2) % K;
        c[i][j] = g[i1][j1] * g[i2][j2] - g[i1][j2] * g[i2][j1];
      }
    }
    S det = S(0);
    TM_UNROLL for (int j = 0; j < K; ++j) det += g[0][j] * c[0][j];
    TM_UNROLL for (int i = 0; i < K; ++i) {
      TM_UNROLL for (int j = 0; j < K; ++j) inv[i][j] = c[j][i] / det;
    }
  }
  TM_UNROLL for (int a = 0; a < D; ++a) m[0][a] = S(0);
  TM_UNROLL for (int i = 0; i < K; ++i) {
    TM_UNROLL for (int a = 0; a < D; ++a) {
      S s = S(0);
      TM_UNROLL for (int j = 0; j < K; ++j) s += inv[i][j] * e[j][a];
      m[i + 1][a] = s;
      m[0][a] -= s;
    }
  }
  // P = E^T (G^-1 E) = sum_i e_i (x) m_{i+1}; exactly the identity where E is square
  TM_UNROLL for (int a = 0; a < D; ++a) {
    TM_UNROLL for (int b = 0; b < D; ++b) {
      S s = S(0);
      if (K == D) {
        s = a == b ? S(1) : S(0);
      } else {
        TM_UNROLL for (int i = 0; i < K; ++i) s += e[i][a] * m[i + 1][b];
      }
      proj[a][b] = s;
    }
  }
}

// Lame constants (lam, mu) from E and nu; plane stress (lam = E nu / (1 - nu^2)) for triangles,
// as physics.materials.lame with plane_stress = (kind == "tri").
template <int NN, typename S>
TM_HD void lame_of(S young, S poisson, S& lam, S& mu) {
  mu = young / (S(2) * (S(1) + poisson));
  lam = NN == 3 ? young * poisson / (S(1) - poisson * poisson)
                : young * poisson / ((S(1) + poisson) * (S(1) - S(2) * poisson));
}

// Cotin's element tensor of the local pair (j, k):
//   K_jk = vol (lam m_j (x) m_k + mu m_k (x) m_j + mu (m_j . m_k) P)     [D][D]
// (reference: ops.reference.tensor_form.element_stiffness).
template <int NN, int D, typename S>
TM_HD void hooke_pair_tensor(const S (&m)[NN][D], const S (&proj)[D][D], S vol, S lam, S mu, int j, int k,
                             S (&out)[D][D]) {
  S dot = S(0);
  TM_UNROLL for (int a = 0; a < D; ++a) dot += m[j][a] * m[k][a];
  TM_UNROLL for (int a = 0; a < D; ++a) {
    TM_UNROLL for (int b = 0; b < D; ++b) {
      out[a][b] = vol * (lam * m[j][a] * m[k][b] + mu * m[k][a] * m[j][b] + mu * dot * proj[a][b]);
    }
  }
}

}  // namespace tensormass
