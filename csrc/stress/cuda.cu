// CUDA implementations of the stress-form ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "stress/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_stress_ops<tensormass::CudaLauncher>(m); }
