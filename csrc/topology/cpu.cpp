// CPU implementations of the topology ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "topology/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_topology_ops<tensormass::CpuLauncher>(m); }
