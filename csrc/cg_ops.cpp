// Schemas of the CG ops (implementations: cpu/cg_cpu.cpp, cuda/cg_cuda.cu; the scalar logic and
// the checks: cg.h; the pure-torch reference and the fake kernels: tensormass_torch/ops/cg.py).
// They update the CG state in place and return nothing, so that a fixed sequence of them (one
// CG iteration) can be captured once in a CUDA graph and replayed with no host round trip.
//
//   cg_alpha(p_dot_ap [V], plan, rr [B], status!, alpha!, scratch!, counter!)
//   cg_update(x!, r!, p, ap [V, d], alpha, plan, threshold [B], max_iter, rr!, status!, beta!,
//             iterations!, scratch!, counter!)
//   cg_direction(p!, r, beta, status, plan)
//   cg_dot(a, b [V] or [V, d], plan, out! [B], scratch!, counter!)   per-object a . b
//   euler_update(x!, v!, dv, dv_imposed?, h, x_new!, v_new!, plan, status, iterations, rr, rhs_sq,
//                norms!, summary!, scratch!, counter! [B + 1], ring!?, ring_pos!?, carry)
//                the end of an implicit Euler step after its CG (cg.h: EulerUpdate, StepSummary)
// plan = (chunk_start [K + 1], chunk_object [K], object_chunk [B + 1]) int64; scratch [K] float64;
// status, iterations, counter [B] int32 (counter all zero between calls).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.def("cg_alpha(Tensor p_dot_ap, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, Tensor rr, "
        "Tensor(a!) status, Tensor(b!) alpha, Tensor(c!) scratch, Tensor(d!) counter) -> ()");
  m.def("cg_update(Tensor(a!) x, Tensor(b!) r, Tensor p, Tensor ap, Tensor alpha, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor threshold, int max_iter, Tensor(c!) rr, "
        "Tensor(d!) status, Tensor(e!) beta, Tensor(f!) iterations, Tensor(g!) scratch, Tensor(h!) counter) -> ()");
  m.def("cg_direction(Tensor(a!) p, Tensor r, Tensor beta, Tensor status, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk) -> ()");
  m.def("cg_dot(Tensor a, Tensor b, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "Tensor(a!) out, Tensor(b!) scratch, Tensor(c!) counter) -> ()");
  m.def("euler_update(Tensor(a!) x, Tensor(b!) v, Tensor dv, Tensor? dv_imposed, float h, Tensor(c!) x_new, "
        "Tensor(d!) v_new, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, Tensor status, "
        "Tensor iterations, Tensor rr, Tensor rhs_sq, Tensor(e!) norms, Tensor(f!) summary, Tensor(g!) scratch, "
        "Tensor(h!) counter, Tensor(i!)? ring, Tensor(j!)? ring_pos, bool carry) -> ()");
}
