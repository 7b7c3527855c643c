// CUDA implementations of the stress ops (see ops_impl.h, kernels.h).
#include "cuda/launcher.cuh"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_stress_ops<tensormass::CudaLauncher>(m); }
