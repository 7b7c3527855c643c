// CPU implementations of the cutting ops (ops.h, tables.h); they have no CUDA ones (schema.cpp says why).
#include <torch/library.h>

#include "cutting/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_cutting_ops(m); }
