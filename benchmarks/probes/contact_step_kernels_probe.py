"""Where a step of a pile with body contact spends the GPU's time, and where the GPU waits on the
host: torch's profiler over a few steps (CUDA only), then

- the kernels' time a step, by kernel (the device's own work, which timers around phases cannot
  separate from the waits), against the step's untimed rate;
- the kernels' time by the library frame that launched them (innermost, and every open frame);
- the host's own time by library frame (nested frames left out), less its waits for the device;
- the idle gaps between kernels, each given to the innermost ``tensormass_torch`` Python frame
  that was running when the kernel after it was launched (the host work the GPU waited for: its
  reads, its launches, the Python between them).

    python benchmarks/probes/contact_step_kernels_probe.py [--columns 10] [--steps 150] [--timed 3]
                                                           [--state DIR] [--contact '{}']
                                                           [--preconditioner auto]

The pile is ``contact_piles``' (see ``contact_step_phases_probe.py``). The Python tracer the gaps
need slows the host: the gaps are larger than untimed (their sum is reported beside the untimed
rate); they say where the waits are, not what they cost. The kernel times are the device's.
"""
import collections
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import common  # noqa: E402
import contact_piles  # noqa: E402

#: trace categories of device work, and of the host calls that launch it (their "correlation" ties the two)
DEVICE_WORK = ("kernel", "gpu_memcpy", "gpu_memset")
LAUNCHES = ("cuda_runtime", "cuda_driver")
#: rows of each table
TOP = 25


def trace_events(prof) -> list:
    """The profiler's trace as a list of complete ("X") events (through its Chrome trace)."""
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, "trace.json")
        prof.export_chrome_trace(path)
        with open(path) as f:
            events = json.load(f)["traceEvents"]
    return [e for e in events if e.get("ph") == "X"]


def library_frames(events: list) -> list:
    """(start, end, name) of the library's Python frames, sorted by start (µs)."""
    frames = [(float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0)), e["name"].split("tensormass_torch/")[-1])
              for e in events if e.get("cat") == "python_function" and "tensormass_torch/" in e["name"]]
    return sorted(frames)


def _open_frames(frames: list, times: list) -> list:
    """For each of ``times`` (µs, ascending), the library frames open then, outermost first (a list
    of names; frames nest on one thread, so a sweep keeps the open ones)."""
    opened, stack, i = [], [], 0
    for at in times:
        while i < len(frames) and frames[i][0] <= at:
            while stack and stack[-1][1] < frames[i][0]:
                stack.pop()
            stack.append(frames[i])
            i += 1
        while stack and stack[-1][1] < at:
            stack.pop()
        opened.append([name for _, _, name in stack] if at >= 0 else [])
    return opened


def _device_work(events: list) -> tuple:
    """(device work as (start, end, launch time or -1) sorted by start, in µs)."""
    launched = {e.get("args", {}).get("correlation"): float(e["ts"]) for e in events if e.get("cat") in LAUNCHES}
    return sorted((float(e["ts"]), float(e["ts"]) + float(e.get("dur", 0)),
                   launched.get(e.get("args", {}).get("correlation"), -1.0))
                  for e in events if e.get("cat") in DEVICE_WORK)


def gaps_by_frame(events: list) -> tuple:
    """(kernel time, idle time, idle time by the innermost library frame at the next launch) in µs."""
    work = _device_work(events)
    waits, end = [], None
    for start, stop, launch in work:
        if end is not None and start > end:
            waits.append((launch, start - end))
        end = stop if end is None else max(end, stop)
    waits.sort()
    by_frame = collections.Counter()
    for (_, idle), stack in zip(waits, _open_frames(library_frames(events), [at for at, _ in waits])):
        by_frame[stack[-1] if stack else "(no library frame)"] += idle
    return sum(stop - start for start, stop, _ in work), sum(idle for _, idle in waits), by_frame


def kernels_by_frame(events: list) -> tuple:
    """The device's work by the library frame that launched it, in µs: (by the innermost frame open
    at the launch, by every frame open then: a frame's own and its callees' work)."""
    work = sorted((launch, stop - start) for start, stop, launch in _device_work(events))
    inner, inclusive = collections.Counter(), collections.Counter()
    for (_, busy), stack in zip(work, _open_frames(library_frames(events), [at for at, _ in work])):
        inner[stack[-1] if stack else "(no library frame)"] += busy
        for name in set(stack):  # a recursive frame counts once
            inclusive[name] += busy
    return inner, inclusive


#: host calls that wait for the device (a read back, a synchronisation)
WAITS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpyAsync", "cudaMemcpy")


def host_by_frame(events: list) -> tuple:
    """The host's time by the innermost library frame, in µs: (its own time, frames nested in it
    left out; of that, the time in calls that wait for the device). Their difference is the
    host's work there: Python, launches, allocations."""
    frames = library_frames(events)
    own, waited = collections.Counter(), collections.Counter()
    stack = []
    for start, end, name in frames + [(math.inf, math.inf, None)]:  # nested frames take their time off their parent's
        while stack and stack[-1][1] <= start:
            done = stack.pop()
            own[done[2]] += done[1] - done[0] - done[3]
        if name is None:
            break
        if stack:
            stack[-1][3] += end - start
        stack.append([start, end, name, 0.0])
    calls = sorted((float(e["ts"]), float(e.get("dur", 0))) for e in events
                   if e.get("cat") in LAUNCHES and e["name"] in WAITS)
    for (_, wait), opened in zip(calls, _open_frames(frames, [at for at, _ in calls])):
        waited[opened[-1] if opened else "(no library frame)"] += wait
    return own, waited


def extend(parser):
    parser.add_argument("--preconditioner", default="auto", help="the Simulator's preconditioner")


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=3, extend=extend)
    if not str(args.device).startswith("cuda"):
        raise SystemExit("the kernels probe needs a CUDA device (--device cuda)")
    sim = contact_piles.pile_simulator(args)
    sim.step(2)
    rate = contact_piles.rate(sim, 2 * args.timed, args.device)
    from torch.profiler import ProfilerActivity, profile
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA], with_stack=True) as prof:
        start = time.perf_counter()
        sim.step(args.timed)
        common.sync(args.device)
        profiled = (time.perf_counter() - start) / args.timed
    events = trace_events(prof)
    busy, idle, by_frame = gaps_by_frame(events)
    per_kernel = collections.Counter()
    for e in events:
        if e.get("cat") in DEVICE_WORK:
            per_kernel[e["name"][:100]] += float(e.get("dur", 0))
    n = args.timed
    print(f"{sim.num_bodies} blocks, contact {args.contact}: {1e3 / rate:.1f} ms a step untimed; profiled "
          f"{1e3 * profiled:.1f} ms: kernels {busy / n / 1e3:.1f} ms a step, idle between them {idle / n / 1e3:.1f}")
    print("kernels (ms a step):")
    for name, us in per_kernel.most_common(TOP):
        print(f"  {us / n / 1e3:7.2f}  {name}")
    inner, inclusive = kernels_by_frame(events)
    for title, table in (("kernels launched by the innermost library frame (ms a step):", inner),
                         ("kernels launched within a library frame, its callees' too (ms a step):", inclusive)):
        print(title)
        for frame, us in table.most_common(TOP):
            print(f"  {us / n / 1e3:7.2f}  {frame}")
    own, waited = host_by_frame(events)
    print("the host's own time by the innermost library frame, less its waits for the device (ms a step, profiled):")
    for frame, us in sorted(own.items(), key=lambda item: waited[item[0]] - item[1])[:TOP]:
        print(f"  {(us - waited[frame]) / n / 1e3:7.2f}  (waits {waited[frame] / n / 1e3:5.2f})  {frame}")
    print("the GPU idle before a launch from (ms a step, profiled):")
    for frame, us in by_frame.most_common(TOP):
        print(f"  {us / n / 1e3:7.2f}  {frame}")
    return dict(ms_untimed=1e3 / rate, kernels_ms=busy / n / 1e3, idle_ms=idle / n / 1e3,
                kernels=dict(per_kernel), waits=dict(by_frame), kernels_inner=dict(inner),
                kernels_inclusive=dict(inclusive), host_own=dict(own), host_waits=dict(waited))


if __name__ == "__main__":
    main()
