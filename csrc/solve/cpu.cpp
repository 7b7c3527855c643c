// CPU implementations of the solve ops (ops.h). The CPU has no persistent kernel: hooke_node_cg runs
// the CG ops' functions in a loop (common/cg_chunks.h: cg_run_cpu), bitwise the op-by-op solve, and
// the pipelined solves (hooke_node_solve, _step, hooke_node_steps) raise NotImplementedError, having
// done nothing.
#include <torch/library.h>

#include "common/cg.h"
#include "common/cg_chunks.h"
#include "common/cpu_launcher.h"
#include "solve/ops.h"

namespace tensormass {

// The CPU launcher with the whole solves of the solve ops (run_cg, run_solve).
struct CpuSolveLauncher : CpuLauncher {
  // A whole CG solve with node kernel K as its matvec: the CG ops' functions in a loop.
  template <class K, typename S>
  static void run_cg(const CGPlan& plan, const K& k, const CGRun<S>& s) {
    cg_run_cpu<K, S>(plan, k, s);
  }

  // The pipelined CG is a GPU kernel (its point is one grid barrier an iteration); the CPU solves
  // with run_cg: false, nothing done (the op raises).
  template <class K, typename S>
  static bool run_solve(const CGPlan&, const K&, const PipelinedSolve<S>&) {
    return false;
  }
};

}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CPU, m) { tensormass::register_solve_ops<tensormass::CpuSolveLauncher>(m); }
