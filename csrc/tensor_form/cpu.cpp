// CPU implementations of the tensor-form ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "tensor_form/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_tensor_form_ops<tensormass::CpuLauncher>(m); }
