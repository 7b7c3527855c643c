// CUDA implementations of the tensor ops (see ops_impl.h, kernels.h).
#include "cuda/launcher.cuh"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_tensor_ops<tensormass::CudaLauncher>(m); }
