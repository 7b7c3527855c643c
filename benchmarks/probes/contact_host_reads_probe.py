"""Where a step of a pile with body contact makes the host wait for the device: each op that needs a
device value on the host (a scalar read: ``item``, ``int``, ``float``, ``bool`` of a tensor; a
size only the device knows: ``nonzero``, ``unique``, ``masked_select``, indexing by a mask,
``repeat_interleave`` without its output size; ``tolist``), counted a step, by op and by the
library's function that called it (and that function's caller); and the ops a step that are not
views, in the CG's iterations (which the GPU runs captured, a graph a stretch) and outside them
(each a launch from the host on the GPU).

    python benchmarks/probes/contact_host_reads_probe.py [--columns 10] [--shift 0.01] [--steps 120]
                                                         [--timed 5] [--state DIR]
                                                         [--contact '{"friction": 0.5}'] [--device cpu]

The pile is ``contact_piles``' (columns x columns x columns blocks, ``--shift`` 0: straight
stacks), stepped ``--steps`` steps with contact, or taken from a state ``contact_piles.py
--state`` saved, then ``--timed`` steps are counted. On a GPU each such op waits for the queue to
drain, so the host's own work between them is not overlapped with the device's: the count is what
a step's wall time pays beyond its kernels (docs/contact.md, "The cost of body contact"). The ops
are the same on any device (the count needs no GPU); copies to the host made inside the
extension's ops are not seen.
"""
import collections
import sys
import traceback
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode
from torch.utils._python_dispatch import TorchDispatchMode

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "studies"))
import contact_piles  # noqa: E402

#: aten ops that launch nothing (views, allocations)
VIEWS = {"view", "reshape", "_reshape_alias", "as_strided", "expand", "unsqueeze", "squeeze", "select", "slice", "t",
         "transpose", "permute", "detach", "alias", "unbind", "split", "split_with_sizes", "_unsafe_view", "narrow",
         "lift_fresh", "empty", "empty_like", "empty_strided", "new_empty", "resolve_conj", "resolve_neg"}

#: aten ops whose result (or its size) the host reads from the device
READS = {"_local_scalar_dense", "nonzero", "unique", "_unique", "_unique2", "unique_consecutive", "unique_dim",
         "masked_select", "repeat_interleave", "index"}


def _site(stack) -> str:
    """The innermost library function on ``stack`` (``traceback.extract_stack()``) and its caller
    (``file:function``)."""
    frames = [f for f in stack if "tensormass_torch" in f.filename][::-1][:2]
    return " <- ".join(f"{f.filename.rpartition('tensormass_torch/')[2]}:{f.name}" for f in frames) or "(outside)"


def _reads(func, args, kwargs) -> bool:
    name = func.__name__.split(".")[0]
    if name not in READS:
        return False
    if name == "repeat_interleave":  # the repeats tensor's overload, without output_size
        return kwargs.get("output_size") is None and (len(args) < 2 or isinstance(args[1], torch.Tensor))
    if name == "index":  # a mask among the indices
        return any(isinstance(i, torch.Tensor) and i.dtype == torch.bool for i in args[1] if i is not None)
    return True


class HostReads(TorchDispatchMode):
    """Counts the host's reads (``counts[(op, site)]``) and the ops that are not views (``ops["in
    the CG's iterations"]`` and ``ops["outside"]``) while active."""

    def __init__(self):
        super().__init__()
        self.counts = collections.Counter()
        self.ops = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = func.__name__.split(".")[0]
        reads = _reads(func, args, kwargs)
        if name not in VIEWS or reads:
            stack = traceback.extract_stack()  # (once for both counts: the probe's own cost)
            if name not in VIEWS:
                iterating = any(f.name == "run_iterations" for f in stack)
                self.ops["in the CG's iterations" if iterating else "outside"] += 1
            if reads:
                self.counts[(name, _site(stack))] += 1
        return func(*args, **kwargs)


class ListReads(TorchFunctionMode):
    """Counts ``Tensor.tolist`` (which reads the values without an aten op) into ``counts``."""

    def __init__(self, counts: collections.Counter):
        super().__init__()
        self.counts = counts

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if func is torch.Tensor.tolist:
            self.counts[("tolist", _site(traceback.extract_stack()))] += 1
        return func(*args, **(kwargs or {}))


def count(sim, steps: int):
    """The host reads and ops of ``steps`` steps of ``sim``: (a Counter of (op, site) -> reads, a
    Counter of the ops in the CG's iterations and outside, each step's CG iterations per solve).
    The iterations are read after each step, outside the count."""
    reads = HostReads()
    iterations = []
    for _ in range(steps):
        with reads, ListReads(reads.counts):
            report = sim.step()
        iterations.append([int(c.iterations.max()) for c in report.cg])
    return reads.counts, reads.ops, iterations


def main(argv=None):
    args = contact_piles.pile_arguments(argv, __doc__, timed=5)
    sim = contact_piles.pile_simulator(args)
    counts, ops, iterations = count(sim, args.timed)
    per_step = sum(counts.values()) / args.timed
    print(f"{per_step:.1f} host reads a step over {args.timed} steps; CG iterations per solve: {iterations}")
    print("ops a step (not views): " + ", ".join(f"{n / args.timed:.0f} {where}" for where, n in sorted(ops.items())))
    by_op = collections.Counter()
    for (op, _), n in counts.items():
        by_op[op] += n
    for op, n in by_op.most_common():
        print(f"{n / args.timed:7.1f}  {op}")
    print("by site (a step):")
    for (op, site), n in counts.most_common():
        print(f"{n / args.timed:7.1f}  {op:20s} {site}")
    return counts, ops, iterations


if __name__ == "__main__":
    main()
