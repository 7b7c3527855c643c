// CPU implementations of the cutting ops: the host algorithms (ops.h, tables.h) and the cut on the
// device (device_ops.h, kernels.h).
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "cutting/device_ops.h"
#include "cutting/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) {
  tensormass::register_cutting_ops(m);
  tensormass::cutting::register_device_cutting_ops<tensormass::CpuLauncher>(m);
}
