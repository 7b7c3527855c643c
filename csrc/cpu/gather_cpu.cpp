// CPU implementations of the gather ops (see ops_impl.h, kernels.h).
#include "cpu/launcher.h"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_gather_ops<tensormass::CpuLauncher>(m); }
