"""How the node graph's rebuilt rows (``node_graph_rebuild_hooke_rows``: RebuildRowNeighbors, then
RebuildRowBlocks) scale with the rows a cut touches: the SOFA beam cut on the device by a scalpel
for ``--steps`` steps, then the op run again on its current elements with 1, 10, 100, ... of the
touched rows (and every row), each kernel's GPU time (torch.profiler, the mean of ``--repeats``
calls). The rows nearest the cut come first. The slowest thread sets a kernel's time, so this
shows how the time follows the rows' star sizes and how the threads of neighbouring rows interfere
(benchmarks/results/h100/device_cuts.md, fourth pass: what three versions of the neighbours'
pass measured).

    python benchmarks/probes/rebuild_rows_probe.py [--steps 40] [--repeats 20]
"""
import argparse

import torch
from torch.profiler import ProfilerActivity, profile

import tensormass_torch as tm
from tensormass_torch.ops import library
from tensormass_torch.sim import builtin


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--repeats", type=int, default=20)
    args = parser.parse_args()
    built = builtin.sofa_beam(model="hooke", device="cuda").simulator
    sim = tm.Simulator(built.bodies, **dict(built._init_args, cut_on_device=True))
    x = sim.bodies[0].mesh.vertices
    middle = float(x[:, 0].min() + x[:, 0].max()) / 2
    sim.add_scalpel(tm.Scalpel(0, times=[0.0, 72 * sim.options.dt],
                               edges=[[[middle, 6.1, -3.0], [middle, 6.1, 3.0]], [[middle, 11.0, -3.0], [middle, 11.0, 3.0]]]))
    sim.step(args.steps)
    cuts = sim._device_cuts
    neighbor, node_k, incidences = cuts.graph
    rebuild = library.op_or_reference("node_graph_rebuild_hooke_rows", cuts.device)
    group, model = cuts.group, cuts.model
    # the rows of nodes near the cut first (those a cut touches), then the others
    used = sim.used_nodes[0]
    near = torch.nonzero(model.node_slots[0, :used] >= 0).flatten()
    distance = (sim.x[near, 0] - middle).abs()
    order = near[torch.argsort(distance)]
    print(f"rows {neighbor.shape[1]}, used {used}, slots {model.node_slots.shape[0]}, graph slots {neighbor.shape[0]}, "
          f"nodes added so far {cuts.added}")
    firsts = torch.empty_like(model.node_slots, dtype=torch.int32)  # the op's scratch
    for count in (1, 10, 100, 300, 1000, 3000, int(order.numel())):
        touched = torch.zeros_like(cuts.touched)
        touched[order[:count]] = 1

        def run():
            rebuild(cuts.pair_k, group.elements, model.node_slots, cuts.alive, touched, cuts.row_of,
                    neighbor.shape[0], neighbor, node_k, incidences, cuts.status, firsts)
        for _ in range(3):
            run()
        torch.cuda.synchronize()
        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            for _ in range(args.repeats):
                run()
            torch.cuda.synchronize()
        times = {e.key.split("<")[1][:34] if "<" in e.key else e.key[:34]: (getattr(e, "device_time_total", None) or e.cuda_time_total) / e.count
                 for e in prof.key_averages() if "Rebuild" in e.key}
        print(f"{count:6d} rows: " + ", ".join(f"{k} {v:.1f} us" for k, v in sorted(times.items())))


if __name__ == "__main__":
    main()
