"""Kernel 2 layouts compared (issue 5): the paper's padded PartialForce against the alternatives a
user would write, on the same element forces in one run.

    python benchmarks/studies/gather_variants.py --device cuda --out $OUT       # the paper's beam
    python benchmarks/studies/gather_variants.py --device cpu --quick --out /tmp/g

Variants of one force evaluation (kernel 1 + kernel 2, stress form, float32):

    padded     ours: kernel 1 writes PartialForce [N_n, V, d] at (ForceIndex, index), kernel 2 sums
               each node's used slots (``tensormass::stress_forces``; deterministic, no atomics)
    csr        kernel 1 writes compact [N, n, d] (``stress_element_forces``), then the node lists
               (CSR, ``topology.node_element_lists``) gather and ``segment_reduce`` sums them
               (deterministic)
    atomics    the same compact forces summed with ``index_add_`` (atomic adds on the GPU: the
               order of the additions, hence the last bits, changes from run to run)

Only ``padded`` is a fused native op; ``csr`` and ``atomics`` pair the native kernel 1 with torch's
reductions, what a user would assemble from the ops. The node-centric kernel of the hooke tensor
form (the CG product in one kernel over the node graph, tensormass::hooke_node_system) is timed by
benchmarks/studies/node_system_bench.py and in the step profile (profile_step.py). Writes gather_variants.md / .json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
import common
import torch

import tensormass_torch as tm
from tensormass_torch.mesh.topology import node_element_lists
from tensormass_torch.ops import library, stress

COLUMNS = [("model", "model", None), ("elements", "elements", ",d"), ("backend", "variant", None),
           ("ms", "ms per force evaluation", ".4f"), ("x_padded", "x padded", ".2f"),
           ("deterministic", "bitwise run to run", None), ("max_rel_diff", "max rel diff vs padded", ".1e")]


def variants(group, u):
    """{name: () -> forces [V, d]} for ``group`` at ``u``."""
    index, force_index, incidences = library.plan_indices(group.plan)
    args = stress.stress_args(group, u)
    ops = torch.ops.tensormass
    elements = group.elements
    num_nodes, dim = u.shape
    ptr, element_ids, local_ids = node_element_lists(elements, num_nodes)
    counts = (ptr[1:] - ptr[:-1])
    flat_rows = element_ids * elements.shape[1] + local_ids  # rows of [N n, d] in node order
    targets = elements.reshape(-1)

    def padded():
        return ops.stress_forces(u, index, force_index, group.plan.num_slots, incidences, *args)

    def csr():
        compact = ops.stress_element_forces(u, index, *args).reshape(-1, dim)
        return torch.segment_reduce(compact[flat_rows], "sum", lengths=counts)

    def atomics():
        compact = ops.stress_element_forces(u, index, *args).reshape(-1, dim)
        return torch.zeros(num_nodes, dim, dtype=u.dtype, device=u.device).index_add_(0, targets, compact)

    return {"padded": padded, "csr": csr, "atomics": atomics}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--device", default=common.default_device())
    p.add_argument("--out", default="benchmarks/results")
    p.add_argument("--quick", action="store_true", help="a small beam: seconds on a CPU")
    p.add_argument("--models", default="hooke,stvk")
    p.add_argument("--repeat", type=int, default=20)
    p.add_argument("--budget-s", type=float, default=None, help="accepted for gpu_bench.sh (the run is short)")
    args = p.parse_args(argv)
    if not library.ensure_registered():
        raise SystemExit("gather_variants: the compiled extension is needed (tensormass_torch._C)")
    dims = (8, 3, 2) if args.quick else (80, 32, 20)
    meta = common.metadata(args.device, dtype="float32")
    results = common.Results(args.out, "gather_variants",
                             "Kernel 2 layouts: padded PartialForce against CSR and atomics",
                             meta, COLUMNS, notes=[
                                 "One force evaluation each (stress form): padded = tensormass::stress_forces "
                                 "(PartialForce [N_n, V, d], slot sums, no atomics); csr = stress_element_forces "
                                 "[N, n, d] + node lists + segment_reduce; atomics = the same + index_add_. "
                                 "See the script's docstring."])
    mesh = tm.beam_mesh(*dims, size=(1.0, 0.4, 0.25), device=args.device)
    g = torch.Generator().manual_seed(0)
    for model in args.models.split(","):
        mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model, tangent="exact")
        (group,) = tm.TensorMass(mesh, mat, form="stress").groups
        u = (0.01 * torch.randn(mesh.vertices.shape, generator=g)).to(args.device).contiguous()
        funcs = variants(group, u)
        reference = funcs["padded"]()
        base = None
        for name, fn in funcs.items():
            seconds = common.time_call(fn, args.device, warmup=3, repeat=args.repeat)
            first, second = fn(), fn()
            rec = common.record(scene="paper_beam" if not args.quick else "small_beam", model=model, kind="tet",
                                elements=group.elements.shape[0], backend=name, device=args.device,
                                dtype="float32")
            rec["ms"] = 1e3 * seconds
            base = rec["ms"] if name == "padded" else base
            rec["x_padded"] = rec["ms"] / base
            rec["deterministic"] = "yes" if torch.equal(first, second) else "no"
            scale = float(reference.abs().max()) or 1.0
            rec["max_rel_diff"] = float((first - reference).abs().max()) / scale
            results.add(rec)
    results.finish()
    print(results.markdown())


if __name__ == "__main__":
    main()
