// Host-side argument checks shared by the ops of every family (their ops.h): floating and index
// tensors against the field they go with, the gather plan of a field's items, node tensors. Each
// failure raises naming the argument and what was expected of it.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>

namespace tensormass {

// Error messages pass only strings to TORCH_CHECK (std::to_string for numbers, these helpers
// for shapes, dtypes and devices): on the GPU machine (torch 2.11, CUDA build) every check that
// streamed an integer (directly or inside sizes()) crashed the process with SIGSEGV instead of
// raising, while checks whose message held only strings raised cleanly. Integer formatting
// through an ostream there goes through locale facets that did not survive; to_string does not.
inline const char* dtype_str(at::ScalarType t) { return c10::toString(t); }

inline std::string shape_str(at::IntArrayRef shape) {
  std::string out = "[";
  for (size_t i = 0; i < shape.size(); ++i) {
    if (i) out += ", ";
    out += std::to_string(shape[i]);
  }
  return out + "]";
}

inline void check_float_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                               at::IntArrayRef shape) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but u is on ",
              like.device().str());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "tensormass: ", name, " is ", dtype_str(t.scalar_type()),
              " but u is ", dtype_str(like.scalar_type()), " (all floating inputs must have one dtype)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ", shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline void check_index_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                               at::ScalarType index_type, at::IntArrayRef shape, const char* like_name = "u") {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but ", like_name,
              " is on ", like.device().str());
  TORCH_CHECK(t.scalar_type() == index_type, "tensormass: ", name, " is ", dtype_str(t.scalar_type()), "; expected ",
              dtype_str(index_type), " (index tensors must all be int32 or all int64)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ", shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

// A [size] bool tensor of flags on like's device (named like_name in messages), contiguous.
inline void check_flags(const at::Tensor& t, const char* name, const at::Tensor& like, int64_t size,
                        const char* like_name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but ", like_name,
              " is on ", like.device().str());
  TORCH_CHECK(t.scalar_type() == at::kBool, "tensormass: ", name, " must be bool, got ", dtype_str(t.scalar_type()));
  TORCH_CHECK(t.dim() == 1 && t.size(0) == size, "tensormass: ", name, " has shape ", shape_str(t.sizes()),
              "; expected [", std::to_string(size), "]");
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline void check_values(const at::Tensor& u, const char* name) {
  TORCH_CHECK(u.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(u.dim() == 2, "tensormass: ", name, " must be [V, d], got shape ", shape_str(u.sizes()));
  TORCH_CHECK(u.scalar_type() == at::kFloat || u.scalar_type() == at::kDouble, "tensormass: ", name,
              " must be float32 or float64, got ", dtype_str(u.scalar_type()));
  TORCH_CHECK(u.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline at::ScalarType index_type_of(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.scalar_type() == at::kLong || t.scalar_type() == at::kInt, "tensormass: ", name,
              " must be int64 or int32, got ", dtype_str(t.scalar_type()));
  return t.scalar_type();
}

// A plan of the items of u (force_index [items_shape] and num_slots; topology.GatherPlan) and its
// slot counts (incidences [V]), with u's device and the items' index type.
inline void check_plan(const at::Tensor& u, const at::Tensor& force_index, int64_t num_slots,
                       at::ScalarType index_type, at::IntArrayRef items_shape) {
  check_index_tensor(force_index, "force_index", u, index_type, items_shape);
  TORCH_CHECK(num_slots >= 0, "tensormass: num_slots must be >= 0, got ", std::to_string(num_slots));
  TORCH_CHECK(items_shape[0] == 0 || num_slots > 0, "tensormass: num_slots is 0 but there are items");
}

inline void check_incidences(const at::Tensor& u, const at::Tensor& incidences, at::ScalarType index_type) {
  check_index_tensor(incidences, "incidences", u, index_type, {u.size(0)});
}

// A floating tensor of the given shape, with the dtype and device of `like` (named like_name in the
// messages).
inline void check_node_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                              at::IntArrayRef shape, const char* like_name = "partial") {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(),
              " but ", like_name, " is on ", like.device().str());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "tensormass: ", name, " is ", dtype_str(t.scalar_type()),
              " but ", like_name, " is ", dtype_str(like.scalar_type()), " (all floating inputs must have one dtype)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ",
              shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

// The data of an optional tensor, or nullptr where it is absent or undefined.
template <typename T>
const T* ptr_or_null(const c10::optional<at::Tensor>& t) {
  return (t.has_value() && t->defined()) ? t->data_ptr<T>() : nullptr;
}

}  // namespace tensormass
