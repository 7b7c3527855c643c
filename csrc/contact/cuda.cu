// CUDA implementations of the contact ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "contact/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_contact_ops<tensormass::CudaLauncher>(m); }
