// CUDA implementations of the topology ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "topology/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_topology_ops<tensormass::CudaLauncher>(m); }
