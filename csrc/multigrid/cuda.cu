// CUDA implementations of the multigrid ops (ops.h, kernels.h): a group of G lanes (G of 1, 4, 8
// or 32, from the matrix's blocks per row: ops.h's row_group) sums a block row, the lanes'
// partial sums added by shuffles in a fixed tree, lane 0 writes the row. On the current stream,
// no allocation: capturable in CUDA graphs.
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "common/cuda_launcher.cuh"
#include "multigrid/ops.h"

namespace tensormass {
namespace {

constexpr int kRowsBlock = 256;

template <int G, class K>
__global__ void __launch_bounds__(kRowsBlock) bsr_rows_kernel(const K k, int64_t rows) {
  using S = typename K::Scalar;
  const int64_t thread = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  const int64_t row = thread / G;
  const int lane = static_cast<int>(thread % G);
  S sum[K::kRows];
  if (row < rows) {
    k.partial(row, lane, G, sum);
  } else {
    TM_UNROLL for (int i = 0; i < K::kRows; ++i) sum[i] = S(0);
  }
  if (G > 1) {  // every lane of the warp takes part (rows past the end with zeros)
    TM_UNROLL for (int i = 0; i < K::kRows; ++i) {
      TM_UNROLL for (int offset = G / 2; offset > 0; offset >>= 1) {
        sum[i] += __shfl_down_sync(0xffffffffu, sum[i], offset, G);
      }
    }
  }
  if (lane == 0 && row < rows) k.finish(row, sum);
}

struct MultigridCuda : CudaLauncher {  // (run: an item a thread, for the block scaling)

  template <int G, class K>
  static void launch(int64_t rows, const K& k) {
    const int64_t threads = rows * G;
    const int64_t grid = (threads + kRowsBlock - 1) / kRowsBlock;
    bsr_rows_kernel<G, K><<<static_cast<unsigned int>(grid), kRowsBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        k, rows);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  template <class K>
  static void run_rows(int64_t rows, const K& k, int group) {
    if (rows <= 0) return;
    switch (group) {
      case 32: launch<32>(rows, k); break;
      case 8: launch<8>(rows, k); break;
      case 4: launch<4>(rows, k); break;
      default: launch<1>(rows, k); break;
    }
  }
};

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_multigrid_ops<tensormass::MultigridCuda>(m); }
