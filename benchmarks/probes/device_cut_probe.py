"""The cut on the device (``ops.cutting.cut_on_device``: three passes and a prefix sum) against
the host cut the simulator runs today (``near_elements`` where the positions are, the positions
read back, ``cutting_cut_mesh`` on the host), on the SOFA beam: a scalpel's strips across its
middle, one cut per strip, as a scalpel cuts before each step. The device cut timed eagerly (each
call synchronised) and replayed from a CUDA graph (the blade written into the captured buffer);
both cuts checked to give the same elements and parents at every strip.

    python benchmarks/probes/device_cut_probe.py [--strips 20] [--dtype float32]
"""
import argparse
import time

import torch

import tensormass_torch as tm
from tensormass_torch.errors import MeshError
from tensormass_torch.ops import cutting, topology
from tensormass_torch.sim import builtin


def med(values):
    return sorted(values)[len(values) // 2]


def strips(count):
    """The blades of a scalpel whose edge (along z) goes down through the beam's whole height (y from
    10.2 to 5.8) at x = 9.55, in overlapping strips (t - dt .. t + dt) as ``Simulator.add_scalpel``
    cuts them."""
    top, bottom = 10.2, 5.8
    step = (top - bottom) / count
    for k in range(count):
        y0, y1 = top - max(k - 1, 0) * step, top - (k + 1) * step
        yield tm.Blade.swept((9.55, y0, -3), (9.55, y0, 3), (9.55, y1, -3), (9.55, y1, 3))


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--strips", type=int, default=20)
    parser.add_argument("--dtype", default="float32")
    parser.add_argument("--spare", type=int, default=4096)
    args = parser.parse_args()
    device, dtype = torch.device("cuda"), getattr(torch, args.dtype)
    mesh = builtin.sofa_beam(model="hooke", device="cpu").simulator.bodies[0].mesh
    num_nodes, n = mesh.num_vertices, mesh.elements.shape[1]
    print(f"SOFA beam: {mesh.elements.shape[0]} tets, {num_nodes} nodes; {args.strips} strips; {args.dtype}")

    # the host cut, as Simulator.cut runs it on a GPU
    host_elements, host_x = mesh.elements.clone(), torch.cat([mesh.vertices, mesh.vertices[:1].expand(
        args.spare, 3)]).to(device, dtype)
    used, slit, host_ms, results = num_nodes, None, [], []
    for blade in strips(args.strips):
        torch.cuda.synchronize()
        start = time.perf_counter()
        near = cutting.near_elements(host_elements.to(device), host_x[:used], blade, slit)
        try:
            result = cutting.cut_mesh(host_elements, used, host_x[:used].to("cpu"), blade, None, slit,
                                      alive=near.to("cpu"))
        except MeshError:  # a strip that crosses no face
            results.append((host_elements.clone(), results[-1][1] if results else torch.zeros(0, dtype=torch.long)))
            continue
        host_ms.append(1e3 * (time.perf_counter() - start))
        added = result.new_nodes
        parents = result.parents[used:].to(device)
        host_x[used:used + added] = host_x[parents]
        # the parents of this cut's new nodes after the earlier cuts' (a result lists every earlier
        # node as its own parent)
        earlier = results[-1][1] if results else torch.zeros(0, dtype=torch.long)
        results.append((result.elements.clone(), torch.cat([earlier, result.parents[used:]])))
        host_elements, slit, used = result.elements, result.slit, used + added
    num_host = used

    # the device cut: tables made once
    elements = mesh.elements.to(device)
    torch.cuda.synchronize()
    start = time.perf_counter()
    faces = cutting.face_table(elements)
    torch.cuda.synchronize()
    table_ms = 1e3 * (time.perf_counter() - start)
    x = torch.cat([mesh.vertices, mesh.vertices[:1].expand(args.spare, 3)]).to(device, dtype)
    alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
    parents = torch.arange(num_nodes + args.spare, device=device)
    ids = torch.arange(elements.shape[0], dtype=elements.dtype, device=device).repeat_interleave(n)

    def node_slots_of(e):
        return topology.incidence_table(e.reshape(-1).long(), ids, num_nodes + args.spare)

    node_slots = node_slots_of(elements)
    used = torch.tensor([num_nodes], device=device)
    limits = torch.tensor([num_nodes, args.spare], device=device)
    scratch, eager_ms, same = {}, [], True
    for k, blade in enumerate(strips(args.strips)):
        vertices, triangles = blade.vertices.to(device, dtype), blade.triangles.to(device)
        torch.cuda.synchronize()
        start = time.perf_counter()
        _, total = cutting.cut_on_device(x, elements, node_slots, alive, faces, vertices, triangles, limits, parents,
                                         scratch)
        torch.cuda.synchronize()
        eager_ms.append(1e3 * (time.perf_counter() - start))
        total = int(total)
        first = int(limits[0])
        x[first:first + total] = x[parents[first:first + total]]
        limits += torch.tensor([total, -total], device=device)
        node_slots = node_slots_of(elements)  # (the lists are edited by the next stage; here made again)
        want_elements, want_parents = results[k]
        strip_same = torch.equal(elements.cpu().long(), want_elements) and torch.equal(
            parents[num_nodes:first + total].cpu(), want_parents)
        if not strip_same:
            differ = int((elements.cpu().long() != want_elements).any(1).sum())
            print(f"strip {k}: {differ} elements differ from the host cut's; nodes so far "
                  f"{first + total - num_nodes} (host {want_parents.numel()})")
        same &= strip_same
    # a captured cut replayed (the same blade buffer rewritten; the tables are the last cut's)
    vertices = next(iter(strips(args.strips))).vertices.to(device, dtype)
    triangles = torch.tensor([[0, 1, 2], [0, 2, 3]], device=device)
    graph = torch.cuda.CUDAGraph()
    torch.cuda.synchronize()
    with torch.cuda.graph(graph):
        cutting.cut_on_device(x, elements, node_slots, alive, faces, vertices, triangles, limits, parents, scratch)
    replays = 200
    torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(replays):
        graph.replay()
    torch.cuda.synchronize()
    replay_us = 1e6 * (time.perf_counter() - start) / replays
    print(f"face table (once): {table_ms:.2f} ms, {faces[0].shape[0]} interior faces")
    print(f"host cut (near_elements + read back + cutting_cut_mesh): median {med(host_ms):.3f} ms, "
          f"min {min(host_ms):.3f} ms")
    print(f"device cut, eager (synchronised): median {med(eager_ms):.3f} ms, min {min(eager_ms):.3f} ms")
    print(f"device cut, replayed from a CUDA graph: {replay_us:.1f} us a cut")
    print(f"same elements and parents as the host cut at every strip: {same}; nodes added "
          f"{int(limits[0]) - num_nodes} (host: {num_host - num_nodes})")


if __name__ == "__main__":
    main()
