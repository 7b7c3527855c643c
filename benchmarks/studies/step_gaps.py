"""The GPU timeline of implicit Euler steps: each kernel's duration and the idle gap before it
(torch.profiler's CUDA events), and the wall time per step, to see what a step costs besides its
kernels. The SOFA beam runs chains (200 steps timed, 16 profiled); the paper's beam single steps
(its stvk tangent breaks down after ~10-20 steps: 4 timed, 3 profiled, as profile_step.py).

    python benchmarks/studies/step_gaps.py [hooke]                 # SOFA beam, on the GPU machine
    python benchmarks/studies/step_gaps.py paper_beam:stvk
"""
import os
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # common, measure
from step_bench import paper_beam, sofa  # noqa: E402

scene, _, model = (sys.argv[1] if len(sys.argv) > 1 else "hooke").rpartition(":")
scene = scene or "sofa_beam"
sim = {"sofa_beam": sofa, "paper_beam": paper_beam}[scene](model, "cuda", torch.float32)
warm_up, timed, profiled = (20, 200, 16) if scene == "sofa_beam" else (3, 4, 3)
sim.step(1)
sim.step(warm_up)
torch.cuda.synchronize()
t = time.perf_counter()
sim.step(timed)
torch.cuda.synchronize()
print(f"{scene} {model}: {(time.perf_counter() - t) / timed * 1e3:.4f} ms/step ({timed} steps in one call)", flush=True)
with profile(activities=[ProfilerActivity.CUDA]) as prof:
    sim.step(profiled)
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
print(f"{profiled} steps: span {span:.1f} us, kernels {busy:.1f} us, gaps {gaps:.1f} us; per step "
      f"{span / profiled:.1f} / {busy / profiled:.1f} / {gaps / profiled:.1f} us")
