// CPU implementations of the contact ops (ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "contact/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_contact_ops<tensormass::CpuLauncher>(m); }
