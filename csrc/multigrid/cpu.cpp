// CPU implementations of the multigrid ops (ops.h, kernels.h): one iteration a block row, its
// blocks summed in order (one lane).
#include <ATen/Parallel.h>
#include <c10/core/Device.h>
#include <torch/library.h>

#include "common/cpu_launcher.h"
#include "multigrid/ops.h"

namespace tensormass {
namespace {

struct MultigridCpu : CpuLauncher {  // (run: an item a thread, for the block scaling)

  template <class K>
  static void run_rows(int64_t rows, const K& k, int /*group*/) {
    if (rows <= 0) return;
    at::parallel_for(0, rows, 256, [&](int64_t begin, int64_t end) {
      for (int64_t row = begin; row < end; ++row) {
        typename K::Scalar sum[K::kRows];
        k.partial(row, 0, 1, sum);
        k.finish(row, sum);
      }
    });
  }
};

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_multigrid_ops<tensormass::MultigridCpu>(m); }
