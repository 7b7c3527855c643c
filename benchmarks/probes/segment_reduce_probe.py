"""torch.segment_reduce against the same reduction with its columns laid end to end (one 1-D
reduction, which torch's CUDA kernel hands to CUB's segmented reduction, a thread block a segment;
with trailing dimensions it runs a thread a (segment, column)), at the sizes of the 1,000-block
pile's per-body reductions: microseconds a call, CUDA events over ``--repeats`` calls after a
warm-up (small calls are timed with their launches), and the largest difference between the two
(the figures and what they decided: docs/contact.md).

    python benchmarks/probes/segment_reduce_probe.py [--bodies 1000] [--nodes 726] [--surface 402]
                                                     [--pairs 193720] [--repeats 50] [--device cuda]

Shapes (a block of 10 x 10 x 5 cells has 726 nodes, 402 of them on its surface): the bodies' mean
motion ``[V, 3]`` sum; their surface boxes ``[S, 3]`` min and max; the pairs' diagonal blocks
``[4 P, 9]`` summed by node with offsets that leave the padding out; the rigid correction's own
blocks ``[V, 36]`` and its float64 body sums ``[V, 4]``; its restriction's runs of 64 nodes
``[R, 6]``.
"""
import argparse
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import common  # noqa: E402


def columns_end_to_end(values, reduce, lengths=None, offsets=None, initial=None):
    """``torch.segment_reduce(values [N, ...], reduce, axis=0, unsafe=True)`` as one 1-D reduction:
    the columns laid end to end (a transposed copy), each column's segments shifted by its start,
    one gap segment between columns for the rows ``offsets`` leaves out (discarded)."""
    if offsets is None:
        offsets = torch.cat([lengths.new_zeros(1), torch.cumsum(lengths, 0)])
    rows, shape = values.shape[0], values.shape[1:]
    columns = values.reshape(rows, -1).t().contiguous()  # [C, N]
    starts = torch.arange(columns.shape[0], device=values.device, dtype=offsets.dtype) * rows
    flat = (offsets.view(1, -1) + starts.view(-1, 1)).reshape(-1)  # C (S + 1) offsets
    out = torch.segment_reduce(columns.reshape(-1), reduce, offsets=flat, unsafe=True, initial=initial)
    segments = offsets.numel() - 1
    out = torch.cat([out, out.new_zeros(1)]).view(columns.shape[0], segments + 1)[:, :segments]
    return out.t().reshape(segments, *shape)


def timed_us(fn, repeats: int, device) -> float:
    for _ in range(3):
        fn()
    if device == "cuda":
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        for _ in range(repeats):
            fn()
        end.record()
        torch.cuda.synchronize()
        return 1000.0 * start.elapsed_time(end) / repeats
    import time
    begin = time.perf_counter()
    for _ in range(repeats):
        fn()
    return 1e6 * (time.perf_counter() - begin) / repeats


def cases(bodies: int, nodes: int, surface: int, pairs: int, device):
    generator = torch.Generator(device=device).manual_seed(0)
    node_counts = torch.full((bodies,), nodes, dtype=torch.int64, device=device)
    surface_counts = torch.full((bodies,), surface, dtype=torch.int64, device=device)
    runs = torch.full((bodies,), -(-nodes // 64), dtype=torch.int64, device=device)
    V, S = bodies * nodes, bodies * surface
    # the pairs' entries sorted by node, each node's run at offsets (most nodes without any), padding after
    entries = 4 * pairs
    node_of_entry = torch.sort(torch.randint(0, V, (entries,), generator=generator, device=device)).values
    offsets = torch.searchsorted(node_of_entry, torch.arange(V + 1, device=device))
    padded = entries + entries // 8

    def rand(*shape, dtype=torch.float32):
        return torch.randn(*shape, generator=generator, device=device, dtype=dtype)
    return [
        ("mean motion [V, 3] sum", rand(V, 3), "sum", dict(lengths=node_counts)),
        ("surface box [S, 3] min", rand(S, 3), "min", dict(lengths=surface_counts, initial=float("inf"))),
        ("surface box [S, 3] max", rand(S, 3), "max", dict(lengths=surface_counts, initial=-float("inf"))),
        ("pair blocks [4P, 9] by node", rand(padded, 9), "sum", dict(offsets=offsets)),
        ("own blocks [V, 36] sum", rand(V, 36), "sum", dict(lengths=node_counts)),
        ("body sums [V, 4] float64", rand(V, 4, dtype=torch.float64), "sum", dict(lengths=node_counts)),
        ("restriction runs [R, 6]", rand(int(runs.sum()), 6), "sum", dict(lengths=runs)),
    ]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=1000)
    parser.add_argument("--nodes", type=int, default=726)
    parser.add_argument("--surface", type=int, default=402)
    parser.add_argument("--pairs", type=int, default=193720)
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--device", default=common.default_device())
    args = parser.parse_args(argv)
    print(f"{common.metadata(args.device)['device_name']}: us a call (torch.segment_reduce, columns end to end)")
    rows = []
    for name, values, reduce, kw in cases(args.bodies, args.nodes, args.surface, args.pairs, args.device):
        def ours():
            return columns_end_to_end(values, reduce, **kw)

        def theirs():
            return torch.segment_reduce(values, reduce, axis=0, unsafe=True, **kw)
        difference = float((ours() - theirs()).abs().max())
        rows.append((name, timed_us(theirs, args.repeats, args.device), timed_us(ours, args.repeats, args.device),
                     difference))
        print(f"{name:32s} {rows[-1][1]:9.1f} {rows[-1][2]:9.1f}   largest difference {difference:.2e}", flush=True)
    return rows


if __name__ == "__main__":
    main()
