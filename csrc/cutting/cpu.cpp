// CPU implementation of the cutting op (ops.h); it has no CUDA one (schema.cpp says why).
#include <torch/library.h>

#include "cutting/ops.h"

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_cutting_ops(m); }
