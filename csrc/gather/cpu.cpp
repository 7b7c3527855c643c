// CPU implementations of the gather ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "gather/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_gather_ops<tensormass::CpuLauncher>(m); }
