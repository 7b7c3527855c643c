// Compile-time dispatch of the host side: each runtime choice (scalar type, index type, material
// model, element kind, dimension, a flag) calls f with a compile-time tag, so that each kernel is
// instantiated for every combination it serves and nothing is chosen per item.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <string>
#include <type_traits>

#include "common/checks.h"
#include "common/element_math.h"

namespace tensormass {

template <int V>
using IC = std::integral_constant<int, V>;

template <class F>
void dispatch_scalar(at::ScalarType t, F&& f) {
  if (t == at::kDouble) {
    f(double{});
  } else if (t == at::kFloat) {
    f(float{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported dtype ", dtype_str(t), " (float32 or float64)");
  }
}

template <class F>
void dispatch_index(at::ScalarType t, F&& f) {
  if (t == at::kLong) {
    f(int64_t{});
  } else if (t == at::kInt) {
    f(int32_t{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported index dtype ", dtype_str(t), " (int32 or int64)");
  }
}

template <class F>
void dispatch_model(int64_t model, F&& f) {
  if (model == kHooke) {
    f(IC<kHooke>{});
  } else if (model == kStvk) {
    f(IC<kStvk>{});
  } else if (model == kCorotational) {
    f(IC<kCorotational>{});
  } else if (model == kStvkDefinite) {
    f(IC<kStvkDefinite>{});
  } else {
    TORCH_CHECK(false, "tensormass: unknown model id ", std::to_string(model),
                " (0 = hooke, 1 = stvk, 2 = corotational, 3 = stvk with a definite tangent)");
  }
}

// Element kinds: (nodes per element, dimension) = (4, 3) tetrahedra, (3, 2) planar triangles,
// (3, 3) membranes.
template <class F>
void dispatch_kind(int64_t nn, int64_t d, F&& f) {
  if (nn == 4 && d == 3) {
    f(IC<4>{}, IC<3>{});
  } else if (nn == 3 && d == 2) {
    f(IC<3>{}, IC<2>{});
  } else if (nn == 3 && d == 3) {
    f(IC<3>{}, IC<3>{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported element kind: ", std::to_string(nn), " nodes per element in dimension ", std::to_string(d),
                " (tetrahedra in 3-D, triangles in 2-D or 3-D)");
  }
}

template <class F>
void dispatch_dim(int64_t d, F&& f) {
  if (d == 3) {
    f(IC<3>{});
  } else if (d == 2) {
    f(IC<2>{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported dimension ", std::to_string(d), " (2 or 3)");
  }
}

template <class F>
void dispatch_bool(bool b, F&& f) {
  if (b) {
    f(std::true_type{});
  } else {
    f(std::false_type{});
  }
}

}  // namespace tensormass
