"""Where a graphed step spends its time: wall per step over 100 steps, then the CUDA kernels of 5
steps (torch.profiler table, to stdout), for the SOFA beam or the paper's 307,200-tet beam.

    python benchmarks/probes/profile_step.py [MODEL ...] > profile.txt        # SOFA beam (hooke corotational)
    python benchmarks/probes/profile_step.py paper_beam:stvk paper_beam:corotational
"""
import os
import sys
import time

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # common, measure
from step_bench import paper_beam, sofa  # noqa: E402

SCENES = {"sofa_beam": sofa, "paper_beam": paper_beam}

for spec in sys.argv[1:] or ("hooke", "corotational"):
    scene, _, model = spec.rpartition(":")
    scene = scene or "sofa_beam"
    sim = SCENES[scene](model, "cuda", torch.float32)
    # the paper's beam sags metres under gravity (E = 1e5 Pa): stvk's exact tangent turns
    # indefinite after ~10-20 steps (a CG breakdown), so it runs single steps, 10 in all
    warm_up, steps, profiled = (20, 100, 5) if scene == "sofa_beam" else (3, 4, 3)
    sim.step(warm_up)  # captures the step graphs (of 1 and 8 chained steps on the SOFA beam)
    torch.cuda.synchronize()
    t = time.perf_counter()
    sim.step(steps)
    torch.cuda.synchronize()
    print(f"{scene} {model}: {(time.perf_counter() - t) / steps * 1e3:.3f} ms/step", flush=True)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        sim.step(profiled)
        torch.cuda.synchronize()
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25, max_name_column_width=60), flush=True)
