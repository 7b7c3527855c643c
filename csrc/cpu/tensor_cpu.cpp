// CPU implementations of the tensor ops (see ops_impl.h, kernels.h).
#include "cpu/launcher.h"
#include "register.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_tensor_ops<tensormass::CpuLauncher>(m); }
