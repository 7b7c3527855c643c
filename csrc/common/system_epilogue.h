// The implicit-Euler system epilogue of the CG matvecs (A = c_M M - c_K K, projected on the free
// nodes), shared by the gather family's SystemGatherKernel and the node graph's
// NodeHookeSystemKernel (common/node_graph.h): the arithmetic of a node (SystemEpilogue) and its
// host side (the optional inputs' checks, the epilogue's pointers, the dispatch of a system kernel).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <tuple>
#include <type_traits>

#include "common/checks.h"
#include "common/dispatch.h"
#include "common/kernel_io.h"

namespace tensormass {

// The implicit-Euler system epilogue of node i, shared by the CG matvec kernels (the padded
// SystemGatherKernel and the node-centric NodeHookeSystemKernel), given acc = the stiffness
// product's sum (K p)_i over the node's slots and pv = p_i:
//   (K p)_i -= K_ii p_i  (node stiffness K_ii [V, D, D]: contact penalties k n n^T)
//   Ap[i] = free_i * (c_M m_i p_i - c_K (K p)_i),   pAp[i] = sum_a p[i][a] Ap[i][a]
//   (plus free_i add[i] where another product's rows are given (HAS_ADD): the contact pairs' in a
//   step's CG; a compile-time choice, so that the products without them compile as they did before)
// The arithmetic follows the torch expression (c_M m_i) p_i - c_K (K p)_i, then the projection,
// so that the result equals the composed path to rounding.
template <int D, typename S, bool HAS_FREE, bool HAS_NODE_K, bool HAS_ADD = false>
struct SystemEpilogue {
  static constexpr bool kHasNodeK = HAS_NODE_K;
  const S* mass;            // [V]
  const S* free;            // [V] 0/1 (HAS_FREE)
  const S* node_stiffness;  // [V, D, D] (HAS_NODE_K)
  S c_mass;
  S c_stiff;
  S* ap;                    // [V, D]
  S* p_dot_ap;              // [V], or nullptr (the CG step-length kernels use the returned dot)
  const S* add;             // [V, D] another product's rows added to Ap, projected likewise (HAS_ADD)

  // Node i's inputs to the row: its own stiffness (HAS_NODE_K), c_M m_i and free_i (1 without).
  TM_HD void load_node(int64_t i, S (&k_own)[D][D], S& m, S& f) const {
    if (HAS_NODE_K) load_matrix<D, D, S>(node_stiffness + i * (D * D), k_own);
    m = c_mass * ld(mass + i);
    f = HAS_FREE ? ld(free + i) : S(1);
  }

  // (A p)_i from the stiffness sum acc = (K p)_i without the node's own stiffness k_own, m = c_M m_i,
  // f = free_i: the arithmetic of every CG matvec of the hooke node graph (acc is updated).
  static TM_HD void row(const S (&k_own)[D][D], S m, S f, S c_stiff_, const S (&pv)[D], S (&acc)[D], S (&out)[D]) {
    if (HAS_NODE_K) {
      TM_UNROLL for (int a = 0; a < D; ++a) {
        S s = S(0);
        TM_UNROLL for (int b = 0; b < D; ++b) s += k_own[a][b] * pv[b];
        acc[a] -= s;
      }
    }
    TM_UNROLL for (int a = 0; a < D; ++a) {
      const S mp = m * pv[a];
      const S kp = c_stiff_ * acc[a];
      S v = mp - kp;
      if (HAS_FREE) v = v * f;
      out[a] = v;
    }
  }

  // Writes Ap_i (and p_dot_ap[i] when that buffer is given) and returns p_i . Ap_i.
  TM_HD S operator()(int64_t i, const S (&pv)[D], S (&acc)[D]) const {
    S k_own[D][D], m, f, out[D];
    load_node(i, k_own, m, f);
    row(k_own, m, f, c_stiff, pv, acc, out);
    if (HAS_ADD) {  // free_i (c_M m_i p_i - c_K (K p)_i) + free_i add_i (free_i is 0 or 1)
      TM_UNROLL for (int a = 0; a < D; ++a) out[a] += HAS_FREE ? ld(add + i * D + a) * f : ld(add + i * D + a);
    }
    S dot = S(0);
    TM_UNROLL for (int a = 0; a < D; ++a) {
      ap[i * D + a] = out[a];
      dot += pv[a] * out[a];
    }
    if (p_dot_ap != nullptr) p_dot_ap[i] = dot;
    return dot;
  }
};

// The epilogue's pointers and coefficients (fr, nk: undefined when absent).
template <int D, typename S, bool HAS_FREE, bool HAS_NODE_K, bool HAS_ADD>
void set_epilogue(SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K, HAS_ADD>& e, const at::Tensor& mass, const at::Tensor& fr,
                  const at::Tensor& nk, double c_mass, double c_stiff, at::Tensor& ap, at::Tensor& p_dot_ap) {
  e.mass = mass.data_ptr<S>();
  e.free = HAS_FREE ? fr.data_ptr<S>() : nullptr;
  e.node_stiffness = HAS_NODE_K ? nk.data_ptr<S>() : nullptr;
  e.c_mass = static_cast<S>(c_mass);
  e.c_stiff = static_cast<S>(c_stiff);
  e.ap = ap.data_ptr<S>();
  e.p_dot_ap = p_dot_ap.defined() ? p_dot_ap.data_ptr<S>() : nullptr;
  e.add = nullptr;
}

// The optional epilogue inputs, checked against `like` ([V, d]): free [V], node_stiffness [V, d, d].
inline std::tuple<at::Tensor, at::Tensor> optional_epilogue_inputs(
    const c10::optional<at::Tensor>& free, const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& like,
    int64_t num_nodes, int64_t dim, const char* like_name) {
  at::Tensor fr, nk;
  if (free.has_value() && free->defined()) {
    fr = *free;
    check_node_tensor(fr, "free", like, {num_nodes}, like_name);
  }
  if (node_stiffness.has_value() && node_stiffness->defined()) {
    nk = *node_stiffness;
    check_node_tensor(nk, "node_stiffness", like, {num_nodes, dim, dim}, like_name);
  }
  return std::make_tuple(fr, nk);
}

// The dispatch of the system kernels (K = SystemGatherKernel or NodeHookeSystemKernel): scalar S,
// index I, dimension D and the epilogue's HAS_FREE / HAS_NODE_K (fr, nk defined or not) and
// HAS_ADD (has_add; only where MAY_ADD: the other ops instantiate no kernel with it); f gets the
// kernel with its epilogue set (add left null), to fill in its own inputs and launch.
template <template <int, typename, typename, bool, bool, bool> class K, bool MAY_ADD = false, class F>
void dispatch_system(at::ScalarType scalar, at::ScalarType index, int64_t dim, const at::Tensor& mass,
                     const at::Tensor& fr, const at::Tensor& nk, double c_mass, double c_stiff, at::Tensor& ap,
                     at::Tensor& p_dot_ap, bool has_add, const F& f) {
  dispatch_scalar(scalar, [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_dim(dim, [&](auto d_c) {
        constexpr int D = decltype(d_c)::value;
        dispatch_bool(fr.defined(), [&](auto free_c) {
          dispatch_bool(nk.defined(), [&](auto node_k_c) {
            const auto with_add = [&](auto add_c) {
              K<D, S, I, decltype(free_c)::value, decltype(node_k_c)::value, decltype(add_c)::value> k;
              set_epilogue(k.epilogue, mass, fr, nk, c_mass, c_stiff, ap, p_dot_ap);
              f(k);
            };
            if constexpr (MAY_ADD) {
              dispatch_bool(has_add, with_add);
            } else {
              TORCH_CHECK(!has_add, "tensormass: this system product takes no add");
              with_add(std::false_type{});
            }
          });
        });
      });
    });
  });
}

}  // namespace tensormass
