// CUDA implementations of the cut on the device (device_ops.h, kernels.h). The host algorithms
// (ops.h, tables.h) have none: they run on host copies.
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "cutting/device_ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::cutting::register_device_cutting_ops<tensormass::CudaLauncher>(m); }
