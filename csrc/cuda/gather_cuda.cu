// CUDA implementations of the gather ops (see ops_impl.h, kernels.h).
#include "cuda/launcher.cuh"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_gather_ops<tensormass::CudaLauncher>(m); }
