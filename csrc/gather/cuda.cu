// CUDA implementations of the gather ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "gather/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_gather_ops<tensormass::CudaLauncher>(m); }
