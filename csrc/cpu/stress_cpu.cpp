// CPU implementations of the stress ops (see ops_impl.h, kernels.h).
#include "cpu/launcher.h"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_stress_ops<tensormass::CpuLauncher>(m); }
