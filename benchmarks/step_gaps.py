"""The GPU timeline of chained SOFA-beam steps: each kernel's duration and the idle gap before it
(torch.profiler's CUDA events), and the wall time per step, to see what a step costs besides its
kernels.

    python benchmarks/step_gaps.py [hooke]          # on the GPU machine
"""
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

from tensormass_torch.scenes import sofa_beam

model = sys.argv[1] if len(sys.argv) > 1 else "hooke"
sim = sofa_beam(model=model, device="cuda").simulator
sim.options.cg_tol = 0.0
sim.options.check_every = 1000
sim.step(20)
torch.cuda.synchronize()
t = time.perf_counter()
sim.step(200)
torch.cuda.synchronize()
print(f"{model}: {(time.perf_counter() - t) / 200 * 1e3:.4f} ms/step (200 chained steps)", flush=True)
with profile(activities=[ProfilerActivity.CUDA]) as prof:
    sim.step(16)
    torch.cuda.synchronize()
kernels = sorted((e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA),
                 key=lambda e: e.time_range.start)
last_end = None
busy = gaps = 0.0
for e in kernels:
    start, end = e.time_range.start, e.time_range.end
    gap = 0.0 if last_end is None else start - last_end
    busy += end - start
    if last_end is not None:
        gaps += max(gap, 0.0)
    print(f"{e.name[:60]:60s} {end - start:8.1f} us  gap before {gap:8.1f} us")
    last_end = end
span = kernels[-1].time_range.end - kernels[0].time_range.start
print(f"16 steps: span {span:.1f} us, kernels {busy:.1f} us, gaps {gaps:.1f} us; per step {span / 16:.1f} / "
      f"{busy / 16:.1f} / {gaps / 16:.1f} us")
