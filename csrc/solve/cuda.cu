// CUDA implementations of the solve ops (ops.h): a whole CG solve in one persistent kernel
// (cg_persistent.cuh: hooke_node_cg) or by the pipelined CG (cg_pipelined.cuh: hooke_node_solve,
// hooke_node_solve_step, hooke_node_steps).
#include <torch/library.h>

#include "common/cg.h"
#include "common/cuda_launcher.cuh"
#include "solve/cg_persistent.cuh"
#include "solve/cg_pipelined.cuh"
#include "solve/ops.h"

namespace tensormass {

// The CUDA launcher with the whole solves of the solve ops (run_cg, run_solve).
struct CudaSolveLauncher : CudaLauncher {
  // A whole CG solve with node kernel K as its matvec: one persistent kernel (cg_persistent.cuh).
  template <class K, typename S>
  static void run_cg(const CGPlan& plan, const K& k, const CGRun<S>& s) {
    launch_persistent_cg<K, S>(plan, k, s);
  }

  // A whole solve by the pipelined CG (cg_pipelined.cuh); false where it does not fit one wave.
  template <class K, typename S>
  static bool run_solve(const CGPlan& plan, const K& k, const PipelinedSolve<S>& s) {
    return launch_pipelined_cg<K, S>(plan, k, s);
  }
};

}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) { tensormass::register_solve_ops<tensormass::CudaSolveLauncher>(m); }
