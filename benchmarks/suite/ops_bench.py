"""Time of the element ops against the memory floor: extension vs pure torch, in one run.

    python benchmarks/suite/ops_bench.py                     # CUDA if available: the paper's beam
    python benchmarks/suite/ops_bench.py --device cpu --mesh 20 10 8 --repeat 10

Scene: the paper's beam ``tm.beam_mesh(80, 32, 20)`` (307,200 tetrahedra), float32, models
hooke and stvk, stress form and tensor form. Ops timed (the paper's kernels 1 and 2, docs/node-graph.md):

    k1       kernel 1: element partial forces written to PartialForce [N_n, V, d]
             (torch: the reference's element forces [N, n, d])
    k2       kernel 2: the per-node sum of the used slots (torch: the reference's scatter + sum)
    forces   k1 + k2 in one op call (torch: ops.forces with TENSORMASS_BACKEND=torch)
    dforces  the same pair with DForce(): (dF/du) du

Times: CUDA events around each call (CPU: perf_counter), after warm-up, median of --repeat;
on CUDA both with the L2 cache flushed before each call ("time", what the floor models) and
back to back ("warm"); see ``timer``.
Bytes (the floor counts what an op must move: each input read once, each output written once;
see ``op_bytes``), divided by the copy bandwidth measured here (a large device-to-device copy:
bandwidth = 2 x bytes / time, read + write) give the floor; `x floor` = time / floor.
The fused ops' floor excludes the PartialForce round trip of the paper's algorithm (written by
k1, read by k2): the column `x floor (incl. PF)` includes it.

Writes ops_bench.md and ops_bench.json (device, date, git commit, torch version, rows) to --out
(default $OUT, else benchmarks/results) and prints the table last.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common, measure, assembled
from common import Budget, metadata

import tensormass_torch as tm
from tensormass_torch import ops
from tensormass_torch.ops import library
from tensormass_torch.ops import stress as stress_family
from tensormass_torch.ops import tensor_form as tensor_form_family
from tensormass_torch.ops.reference import gather as ref_gather
from tensormass_torch.ops.reference import stress_form, tensor_form

T = None  # torch.ops.tensormass once loaded


# ---------------------------------------------------------------------------------------------
# timing
# ---------------------------------------------------------------------------------------------


def timer(device, warmup, repeat):
    """run(fn, cold) -> median seconds of one call.

    CUDA: events around each call. A sleep kernel first keeps the GPU busy while the CPU queues
    all the calls, so the events time the kernels back to back, not the Python launch overhead.
    warm: calls back to back (the inputs of the beam's ops, ~30-50 MB, largely stay in the 50 MB
    L2 of an H100, as they would between the products of one CG solve); cold: a 256 MB buffer
    is rewritten before each call (not timed), so every byte comes from DRAM: the case the
    copy-bandwidth floor models. CPU: perf_counter around each call (cold = warm).
    """
    cuda = torch.device(device).type == "cuda"
    flush = torch.empty(64 << 20, dtype=torch.float32, device=device) if cuda else None

    def run(fn, cold=False):
        for _ in range(warmup):
            fn()
        if cuda:
            torch.cuda.synchronize()
            try:
                torch.cuda._sleep(100_000_000)  # ~50 ms: time for the CPU to queue every call
            except (AttributeError, RuntimeError):
                pass
            pairs = []
            for _ in range(repeat):
                if cold:
                    flush.zero_()
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                fn()
                end.record()
                pairs.append((start, end))
            torch.cuda.synchronize()
            times = [s.elapsed_time(e) * 1e-3 for s, e in pairs]
        else:
            times = []
            for _ in range(repeat):
                t0 = time.perf_counter()
                fn()
                times.append(time.perf_counter() - t0)
        return statistics.median(times)

    return run


def copy_bandwidth(device, run, nbytes=1 << 30):
    """Bytes/s of a large device-to-device copy (read + write counted)."""
    if torch.device(device).type == "cpu":
        nbytes = min(nbytes, 1 << 28)
    src = torch.empty(nbytes // 4, dtype=torch.float32, device=device).fill_(1.0)
    dst = torch.empty_like(src)
    seconds = run(lambda: dst.copy_(src), cold=True)
    return 2.0 * nbytes / seconds


# ---------------------------------------------------------------------------------------------
# bytes each op must move
# ---------------------------------------------------------------------------------------------


def op_bytes(group, op, s, ix):
    """Bytes an op must move: every input read once + every output written once.

    s: float bytes, ix: index bytes; N items (elements, or edges for the hooke tensor form) with
    n nodes, V nodes, d dimensions:
      u (and du for dforces)               V d s          each
      index, force_index (ForceIndex)      N n ix         each
      incidences                           V ix
      stress form   shape vectors N n d s, measure/lam/mu 3 N s, projector N d d s (membranes)
      tensor hooke  edge tensors N d d s (the edges act on differences: no vertex tensors)
      tensor stvk   B N n^2 d^2 s, C N n^3 d s, D N n^4 s
      PartialForce (used slots)            N n d s        (k1 output, k2 input)
      nodal output                         V d s
    Returns (bytes of the op, bytes including the PartialForce round trip for fused ops).
    """
    plan = group.plan
    n_items, n = plan.index.shape
    V, d = plan.num_nodes, group.dim
    field = V * d * s
    partial = n_items * n * d * s
    if group.form == "stress":
        params = n_items * n * d * s + 3 * n_items * s + (n_items * d * d * s if group.projector is not None else 0)
    elif group.model == "hooke":
        params = n_items * d * d * s
    else:
        params = n_items * (n * n * d * d + n ** 3 * d + n ** 4) * s
    node_params = 0
    indices = 2 * n_items * n * ix
    values = field * (2 if op == "dforces" and not (group.form == "tensor" and group.model == "hooke") else 1)
    if op == "k1":
        b = field + indices + params + partial
        return b, b
    if op == "k2":
        b = partial + V * ix + field
        return b, b
    b = values + indices + V * ix + params + node_params + field
    return b, b + 2 * partial


# ---------------------------------------------------------------------------------------------
# the ops, extension and torch
# ---------------------------------------------------------------------------------------------


def extension_ops(group, u, du):
    """{op: callable} through torch.ops.tensormass (int32 indices, as the dispatch layer passes)."""
    idx, fi, inc = library.plan_indices(group.plan)
    ns = group.plan.num_slots
    if group.form == "stress":
        sa = stress_family.stress_args(group)
        k1 = lambda: T.stress_partial_forces(u, idx, fi, ns, *sa)  # noqa: E731
        fused = lambda: T.stress_forces(u, idx, fi, ns, inc, *sa)  # noqa: E731
        dfused = lambda: T.stress_dforces(u, du, idx, fi, ns, inc, *sa)  # noqa: E731
    elif group.model == "hooke":
        ek = group.edge_k.contiguous()
        k1 = lambda: T.tensor_hooke_partial_forces(u, idx, fi, ns, ek)  # noqa: E731
        fused = lambda: T.tensor_hooke_forces(u, idx, fi, ns, inc, ek)  # noqa: E731
        dfused = lambda: T.tensor_hooke_forces(du, idx, fi, ns, inc, ek)  # noqa: E731
    else:
        tb = tensor_form_family.stvk_tensors(group)
        k1 = lambda: T.tensor_stvk_partial_forces(u, idx, fi, ns, *tb)  # noqa: E731
        fused = lambda: T.tensor_stvk_forces(u, idx, fi, ns, inc, *tb)  # noqa: E731
        dfused = lambda: T.tensor_stvk_dforces(u, du, idx, fi, ns, inc, *tb)  # noqa: E731
    padded = k1()
    k2 = lambda: T.gather_partial(padded, inc, None)  # noqa: E731
    return {"k1": k1, "k2": k2, "forces": fused, "dforces": dfused}, (idx.element_size())


def torch_ops(group, u, du):
    """{op: callable} of the pure-torch reference (what TENSORMASS_BACKEND=torch runs)."""
    plan = group.plan
    if group.form == "stress":
        lam, mu = group.lame()
        k1 = lambda: stress_form.FORCES[group.model](u[group.elements], group.shape_vectors,  # noqa: E731
                                                     group.measure, lam, mu, group.projector)
    elif group.model == "hooke":
        k1 = lambda: tensor_form.hooke_edge_partial_forces(u, group.edges, group.edge_k)  # noqa: E731
    else:
        k1 = lambda: tensor_form.stvk_forces(u[group.elements], group.tensor_b, group.tensor_c,  # noqa: E731
                                             group.tensor_d)
    partial = k1()
    k2 = lambda: ref_gather.node_gather(partial, plan.index, plan.force_index, plan.num_slots,  # noqa: E731
                                        plan.num_nodes)

    def forced(fn):
        def call():
            os.environ["TENSORMASS_BACKEND"] = "torch"
            try:
                return fn()
            finally:
                os.environ["TENSORMASS_BACKEND"] = "auto"
        return call

    return {"k1": k1, "k2": k2, "forces": forced(lambda: ops.forces(group, u)),
            "dforces": forced(lambda: ops.dforces(group, u, du))}, plan.index.element_size()


# ---------------------------------------------------------------------------------------------
# main
# ---------------------------------------------------------------------------------------------


def markdown(meta, rows):
    lines = [
        f"### ops_bench: {meta['elements']:,} {meta['kind']} elements, {meta['nodes']:,} nodes, {meta['dtype']}, "
        f"{meta['device_name']}",
        "",
        f"copy bandwidth {meta['copy_bandwidth_GBps']:.0f} GB/s; torch {meta['torch']}; commit {meta['commit']}; "
        f"{meta['date']}",
        "",
        "time: median, L2 flushed before each call (cold); warm: back to back, L2 warm. x floor = time / "
        "(MB / copy bandwidth); incl. PF: the floor of the fused ops counting the PartialForce round trip.",
        "",
        "| model | form | op | backend | time (us) | warm (us) | MB | floor (us) | x floor | x floor (incl. PF) "
        "| torch / ext |",
        "|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['model']} | {r['form']} | {r['op']} | {r['backend']} | error: {r['error']} |"
                         " | | | | | |")
            continue
        speed = f"{r['torch_over_ext']:.1f}" if r.get("torch_over_ext") else ""
        lines.append(
            f"| {r['model']} | {r['form']} | {r['op']} | {r['backend']} | {r['time_us']:.1f} | {r['warm_us']:.1f} "
            f"| {r['bytes'] / 1e6:.1f} "
            f"| {r['floor_us']:.1f} | {r['x_floor']:.2f} | {r['x_floor_incl_partial']:.2f} | {speed} |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    global T
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--mesh", type=int, nargs=3, default=(80, 32, 20), metavar=("NX", "NY", "NZ"))
    parser.add_argument("--dtype", default="float32", choices=("float32", "float64"))
    parser.add_argument("--models", default="hooke,stvk")
    parser.add_argument("--forms", default="stress,tensor")
    parser.add_argument("--backends", default="extension,torch")
    parser.add_argument("--warmup", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=None)
    parser.add_argument("--out", default=os.environ.get("OUT") or "benchmarks/results")
    parser.add_argument("--budget-s", type=float, default=None,
                        help="wall-clock limit: later (model, form) pairs skipped")
    args = parser.parse_args(argv)
    device = torch.device(args.device)
    cuda = device.type == "cuda"
    warmup = args.warmup if args.warmup is not None else (10 if cuda else 2)
    repeat = args.repeat if args.repeat is not None else (100 if cuda else 10)
    dtype = getattr(torch, args.dtype)
    run = timer(device, warmup, repeat)

    backends = args.backends.split(",")
    if "extension" in backends:
        if not library.ensure_registered() or not tm._backend.use_extension(device):
            raise SystemExit(f"the extension cannot run on {device}: {tm.backend_info()['reason']}")
        T = torch.ops.tensormass

    torch.manual_seed(0)
    mesh = tm.beam_mesh(*args.mesh, size=(1.0, 0.4, 0.25), dtype=dtype, device=device)
    bandwidth = copy_bandwidth(device, run)
    meta = metadata(device)  # device, device name, date, commit, versions, threads, backends
    meta.update({
        "dtype": args.dtype,
        "mesh": list(args.mesh),
        "kind": "tet",
        "elements": int(mesh.elements.shape[0]),
        "nodes": int(mesh.vertices.shape[0]),
        "copy_bandwidth_GBps": bandwidth / 1e9,
        "warmup": warmup,
        "repeat": repeat,
        "timing": "CUDA events, median" if cuda else "perf_counter, median",
    })
    rows = []
    s = torch.empty((), dtype=dtype).element_size()
    budget = Budget(args.budget_s)
    for model in args.models.split(","):
        for form in args.forms.split(","):
            if budget.remaining() <= 0:
                rows.append({"model": model, "form": form, "op": "all", "backend": "all",
                             "error": "skipped: budget spent"})
                continue
            mat = tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model, tangent="exact")
            group = tm.TensorMass(mesh, mat, form=form).groups[0]
            gen = torch.Generator(device="cpu").manual_seed(1)
            u = (1e-3 * torch.randn(mesh.vertices.shape, generator=gen, dtype=dtype)).to(device)
            du = torch.randn(mesh.vertices.shape, generator=gen, dtype=dtype).to(device)
            timed = {}
            for backend in backends:
                fns, ix = (extension_ops if backend == "extension" else torch_ops)(group, u, du)
                for op in ("k1", "k2", "forces", "dforces"):
                    row = {"model": model, "form": form, "op": op, "backend": backend}
                    try:
                        warm = run(fns[op])
                        seconds = run(fns[op], cold=True) if cuda else warm
                    except Exception as exc:  # e.g. out of memory on the torch path: say so, go on
                        row["error"] = f"{type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
                        rows.append(row)
                        continue
                    nbytes, with_partial = op_bytes(group, op, s, ix)
                    floor = nbytes / bandwidth
                    row.update(time_us=seconds * 1e6, warm_us=warm * 1e6, bytes=nbytes, bytes_incl_partial=with_partial,
                               floor_us=floor * 1e6, x_floor=seconds / floor,
                               x_floor_incl_partial=seconds / (with_partial / bandwidth), index_bytes=ix)
                    timed[(backend, op)] = seconds
                    rows.append(row)
            for row in rows[-2 * 4:]:
                ext, ref = timed.get(("extension", row["op"])), timed.get(("torch", row["op"]))
                if row["backend"] == "extension" and ext and ref:
                    row["torch_over_ext"] = ref / ext
            del group
            if cuda:
                torch.cuda.empty_cache()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = markdown(meta, rows)
    (out / "ops_bench.md").write_text(table)
    (out / "ops_bench.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(table)


if __name__ == "__main__":
    main()
