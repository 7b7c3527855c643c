// CPU implementations of the node graph ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "node_graph/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_node_graph_ops<tensormass::CpuLauncher>(m); }
