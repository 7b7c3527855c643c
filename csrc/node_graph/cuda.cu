// CUDA implementations of the node graph ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "node_graph/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_node_graph_ops<tensormass::CudaLauncher>(m); }
