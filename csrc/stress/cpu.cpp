// CPU implementations of the stress-form ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "stress/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_stress_ops<tensormass::CpuLauncher>(m); }
