"""Where a graphed SOFA-beam step spends its time: wall per step over 100 steps, then the CUDA
kernels of 5 steps (torch.profiler table, to stdout).

    python benchmarks/profile_step.py [MODEL ...] > profile.txt   # on the GPU machine (hooke corotational)
"""
import sys, time, torch
sys.path.insert(0, "benchmarks")
from tensormass_torch.scenes import sofa_beam
for model in sys.argv[1:] or ("hooke", "corotational"):
    sim = sofa_beam(model=model, device="cuda").simulator
    sim.options.cg_tol = 0.0
    sim.options.check_every = 1000
    sim.step(20); torch.cuda.synchronize()  # captures the graphs of 1 and 8 chained steps
    t = time.perf_counter(); sim.step(100); torch.cuda.synchronize()
    print(f"{model}: {(time.perf_counter() - t) / 100 * 1e3:.3f} ms/step", flush=True)
    from torch.profiler import profile, ProfilerActivity
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        sim.step(5); torch.cuda.synchronize()
    print(prof.key_averages().table(sort_by="cuda_time_total", row_limit=25, max_name_column_width=60), flush=True)
