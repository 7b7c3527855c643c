"""Several GPUs: the implicit step of one beam partitioned over the ranks
(``PartitionedSimulator``), and a batch of small bodies dealt over the ranks (each rank steps
its share as one packed ``Simulator``), at each size given, on as many ranks as torchrun starts.

    torchrun --nproc-per-node N benchmarks/studies/distributed_scaling.py --device cuda --out DIR
    python benchmarks/studies/distributed_scaling.py --quick --device cpu --out DIR   # one process

Run it once per N into the same DIR: each run adds its rows to distributed_scaling.json (a row
measured again replaces the old one) and writes distributed_scaling.md with every N so far, so strong scaling
(one size over N) and weak scaling (size proportional to N) read off one table.

Beam rows: the paper beam's proportions (1 x 0.4 x 0.25 m, clamped at x = 0, gravity), hooke,
E = 1e5, dt = 0.01, float32, each step solved to a relative residual of ``--tol`` by the
partitioned CG (all-reduced dots, halo exchanges). Per row: ms a step (the slowest rank's,
after one warm-up step), CG iterations, ms an iteration, set-up seconds (partition, parts,
models) and each rank's peak GPU memory. With one rank, the row "single" is the one-process
``tm.Simulator`` (fused node-graph kernels, captured steps) to the same tolerance: what the
partitioned path has to beat.

Batch rows: ``--bodies`` small beams of ``--body-cells`` cells (6 tets a cell), stvk, 10 CG
iterations a step (the batch benchmark's settings), bodies dealt by element count
(``partition_bodies``); body-steps per second over all ranks.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import torch
import torch.distributed as dist
from common import metadata

import tensormass_torch as tm
from tensormass_torch.sim import distributed
from tensormass_torch.sim.partitioned import PartitionedSimulator

COLUMNS = [("kind", "kind"), ("ranks", "ranks"), ("elements", "elements"), ("path", "path"),
           ("ms_per_step", "ms/step"), ("cg_iterations", "CG it"), ("ms_per_iteration", "ms/CG it"),
           ("body_steps_per_s", "body-steps/s"), ("setup_s", "set-up s"), ("memory_gb", "peak GB a rank"),
           ("note", "note")]


def sync(device):
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(step, device, steps: int) -> float:
    """Seconds a step of ``step(n)``, the slowest rank's (barriers around the timed steps)."""
    sync(device)
    dist.barrier()
    start = time.perf_counter()
    step(steps)
    sync(device)
    elapsed = torch.tensor([time.perf_counter() - start], dtype=torch.float64, device=distributed.group_device(device))
    dist.all_reduce(elapsed, op=dist.ReduceOp.MAX)
    return float(elapsed[0]) / steps


def peak_gb(device) -> list:
    """Each rank's peak GPU memory (GB), gathered (empty on the CPU)."""
    value = torch.cuda.max_memory_allocated(device) / 1e9 if device.type == "cuda" else None
    values = [None] * dist.get_world_size()
    dist.all_gather_object(values, value)
    return [round(v, 2) for v in values if v is not None]


def beam(elements: int, device):
    mesh = tm.beam_mesh(*common.tet_dims(elements), size=common.PAPER_SIZE, dtype=torch.float32)
    material = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="hooke")
    return tm.Body(mesh, material, fixed=mesh.vertices[:, 0] <= 1e-6), mesh.num_elements


def slabs(mesh, parts: int) -> torch.Tensor:
    """Each node's part ``[V]``: equal node counts in order along the beam's axis (connected slabs,
    the cut a graph partitioner finds for a beam, without its minutes on a mesh of tens of millions)."""
    order = torch.sort(mesh.vertices[:, 0].cpu(), stable=True).indices
    partition = torch.empty(mesh.num_vertices, dtype=torch.int64)
    partition[order] = torch.arange(mesh.num_vertices) * parts // mesh.num_vertices
    return partition


def beam_rows(elements: int, device, args) -> list:
    rows = []
    world = dist.get_world_size()
    body, count = beam(elements, device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    start = time.perf_counter()
    graphs = ", graphs" if args.graphs == "yes" and device.type == "cuda" else ""  # (CPU: none)
    partition = slabs(body.mesh, world) if args.partition == "slabs" else None  # None: METIS
    sim = PartitionedSimulator(body, dt=0.01, cg_tol=args.tol, device=device, dtype=torch.float32,
                               partition=partition, check_every=args.check_every, cuda_graphs=args.graphs == "yes")
    setup = time.perf_counter() - start
    sim.step(1)
    per_step = timed(sim.step, device, args.steps)
    iterations = sim.last_iterations
    rows.append(dict(kind="beam", ranks=world, elements=count, path=f"partitioned ({args.partition}{graphs})",
                     ms_per_step=per_step * 1e3,
                     cg_iterations=iterations, ms_per_iteration=per_step * 1e3 / max(iterations, 1),
                     setup_s=setup, memory_gb=peak_gb(device)))
    sim.close()
    del sim
    if world == 1 and args.single == "yes":
        if device.type == "cuda":
            torch.cuda.empty_cache()
            torch.cuda.reset_peak_memory_stats(device)
        start = time.perf_counter()
        single = tm.Simulator([body], dt=0.01, cg_tol=args.tol, cg_max_iter=20000, require_convergence=False,
                              check_every=8, device=device, dtype=torch.float32)
        setup = time.perf_counter() - start
        single.step(1)
        per_step = timed(single.step, device, args.steps)
        iterations = int(single.last_report.cg[0].iterations.max())
        rows.append(dict(kind="beam", ranks=1, elements=count, path="single", ms_per_step=per_step * 1e3,
                         cg_iterations=iterations, ms_per_iteration=per_step * 1e3 / max(iterations, 1),
                         setup_s=setup, memory_gb=peak_gb(device)))
    return rows


def batch_row(bodies: int, device, args) -> dict:
    world, rank = dist.get_world_size(), dist.get_rank()
    mesh = tm.beam_mesh(*args.body_cells, size=(0.1 * args.body_cells[0] / args.body_cells[2],
                                                0.1 * args.body_cells[1] / args.body_cells[2], 0.1),
                        dtype=torch.float32)
    fixed = mesh.vertices[:, 0] <= 1e-6
    material = tm.Material(young=1e5, poisson=0.3, density=1000.0, model="stvk")
    share = distributed.partition_bodies([mesh.num_elements] * bodies, world)[rank]
    gc.collect()  # the previous row's simulator (its reference cycles) gone before this row's peak
    if device.type == "cuda":
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats(device)
    start = time.perf_counter()
    sim = tm.Simulator([tm.Body(mesh, material, fixed=fixed) for _ in share], dt=0.01, cg_tol=0.0,
                       cg_max_iter=10, require_convergence=False, check_every=1000, device=device,
                       dtype=torch.float32)
    setup = time.perf_counter() - start
    sim.step(2)
    per_step = timed(sim.step, device, args.batch_steps)
    return dict(kind="batch", ranks=world, elements=bodies * mesh.num_elements, path=f"{bodies} bodies",
                ms_per_step=per_step * 1e3, cg_iterations=10, body_steps_per_s=bodies / per_step, setup_s=setup,
                memory_gb=peak_gb(device))


def write(out: Path, rows: list, meta: dict, world: int):
    path = out / "distributed_scaling.json"
    old = json.loads(path.read_text()) if path.exists() else {"runs": {}, "records": []}
    old["runs"][str(world)] = meta
    def key(r):
        return r["kind"], r["ranks"], r["elements"], r["path"]

    replaced = {key(r) for r in rows}  # a row measured again replaces the old one
    records = [r for r in old["records"] if key(r) not in replaced] + rows
    records.sort(key=lambda r: (r["kind"], r["elements"], r["ranks"], r["path"]))
    path.write_text(json.dumps({"runs": old["runs"], "records": records}, indent=1))
    lines = ["# Several GPUs: a partitioned beam and a dealt batch, by ranks", ""]
    lines += [f"- {n} rank(s): {m.get('device_name')}, {m.get('date')}, commit {m.get('commit')}, "
              f"torch {m.get('torch')}" for n, m in sorted(old["runs"].items())]
    lines += ["", "| " + " | ".join(title for _, title in COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for r in records:
        cells = []
        for key, _ in COLUMNS:
            value = r.get(key)
            cells.append("" if value is None else f"{value:.3g}" if isinstance(value, float) else str(value))
        lines.append("| " + " | ".join(cells) + " |")
    (out / "distributed_scaling.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results/distributed")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--beams", default=None, help="beam tets (comma list)")
    parser.add_argument("--bodies", default=None, help="batch sizes (comma list)")
    parser.add_argument("--body-cells", default="2x2x2", help="cells of a small body (6 tets a cell)")
    parser.add_argument("--tol", type=float, default=1e-5, help="the beam's CG relative residual")
    parser.add_argument("--steps", type=int, default=5, help="timed beam steps")
    parser.add_argument("--partition", choices=("metis", "slabs"), default="metis",
                        help="the beam's parts: METIS's (the library's default) or equal slabs along its axis")
    parser.add_argument("--check-every", type=int, default=16, help="partitioned CG iterations between host reads")
    parser.add_argument("--graphs", choices=("yes", "no"), default="yes",
                        help="replay the partitioned CG's iterations as captured CUDA graphs")
    parser.add_argument("--single", choices=("yes", "no"), default="yes",
                        help="with one rank, also time the one-process simulator")
    parser.add_argument("--batch-steps", type=int, default=20, help="timed batch steps")
    args = parser.parse_args(argv)
    common.fill_defaults(args, dict(beams="1228800,2457600,4915200", bodies="10000,100000"),
                         dict(beams="4800", bodies="40"))
    args.body_cells = tuple(int(v) for v in args.body_cells.split("x"))
    if not distributed.launched():  # one process: a group of one
        os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
        os.environ.setdefault("MASTER_PORT", "29533")
        os.environ.update(RANK="0", WORLD_SIZE="1", LOCAL_RANK="0")
    device = distributed.init(args.device)
    rows = []

    def done(new):
        rows.extend(new)
        if dist.get_rank() == 0:
            for row in new:
                print(json.dumps(row), flush=True)

    for elements in [int(v) for v in args.beams.split(",") if v and int(v) > 0]:
        done(beam_rows(elements, device, args))
    for bodies in [int(v) for v in args.bodies.split(",") if v and int(v) > 0]:
        done([batch_row(bodies, device, args)])
    if dist.get_rank() == 0:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write(out, rows, metadata(device), dist.get_world_size())
    dist.destroy_process_group()


if __name__ == "__main__":
    main()
