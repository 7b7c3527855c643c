// CUDA implementations of the tensor-form ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "tensor_form/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_tensor_form_ops<tensormass::CudaLauncher>(m); }
