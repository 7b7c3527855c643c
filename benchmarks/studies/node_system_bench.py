"""The hooke tensor form's CG matvec: the node-centric kernel against the padded two-kernel path.

    python benchmarks/studies/node_system_bench.py --device cuda              # SOFA beam + paper beams
    python benchmarks/studies/node_system_bench.py --device cpu --quick       # a smoke test (small beams)

Variants of one matvec A p = free (c_M M p - c_K K p) with its per-node dots (float32):

    padded   kernel 1 (tensor_hooke_partial_forces: one thread per edge, PartialForce [N_n, V, 3])
             + kernel 2 (gather_system: slot sums and the system epilogue), the paper's Algorithm 1
    node     hooke_node_system: one thread per node over the node graph (neighbor [N_n, V],
             node_k [N_n, V, 3, 3]), the same terms summed in the same order: bitwise the same result

both through ``native.system_matvec(..., variants=KernelVariants(hooke_matvec=...))``, as the solver
calls it (with its ``StepOptions.variants``), with the scene's mass, free mask and contact node
stiffness. Timing: on CUDA, events around ``--inner`` back-to-back calls (after ``--warmup``
calls), the median over ``--repeat`` samples, divided by ``--inner``; on the CPU the same with
the wall clock. Prints a markdown table (``--out DIR`` also writes node_system_bench.md).
"""
from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # common, measure

import common  # noqa: E402

import tensormass_torch as tm  # noqa: E402
from tensormass_torch.ops import library, native, node_graph  # noqa: E402
from tensormass_torch.ops.variants import KernelVariants  # noqa: E402

LAYOUTS = ("padded", "node")


def build_scenes(device, quick):
    """[(name, simulator)] of the hooke scenes (tensor form): the SOFA beam, the paper's beam in
    tetrahedra and in membrane triangles."""
    elements = 3000 if quick else 307200
    sofa = tm.sim.builtin.sofa_beam("hooke", device=device, dtype=torch.float32, scale=5 if quick else 1).simulator
    paper_tet, _ = common.cantilever_sim("tet", "hooke", elements, device)
    paper_tri, _ = common.cantilever_sim("tri", "hooke", elements, device)
    return [("sofa_beam", sofa), ("paper_beam_tet", paper_tet), ("paper_beam_tri", paper_tri)]


def matvec_case(sim):
    """(group, u, p, mass [V], free [V], c_mass, c_stiff, node_stiffness [V, 3, 3] or None) of the
    simulator's implicit-Euler matvec at its current state."""
    groups = sim.model.groups
    if len(groups) != 1 or groups[0].form != "tensor" or groups[0].model != "hooke":
        raise SystemExit("node_system_bench: each scene must be one hooke tensor-form group")
    opts = sim.options
    h = opts.dt
    c_mass, c_stiff = 1.0 + h * opts.rayleigh_mass, h * (h + opts.rayleigh_stiffness)
    u = (sim.x - sim.model.rest).contiguous()
    gen = torch.Generator().manual_seed(0)
    p = torch.randn(u.shape, generator=gen, dtype=u.dtype).to(u.device)
    mass = sim.system.mass.reshape(-1).contiguous()
    free = None if sim.system.free is None else sim.system.free.reshape(-1).to(u.dtype).contiguous()
    stiffness = None if sim.planes is None else sim.planes.node_stiffness(sim.x).contiguous()
    return groups[0], u, p, mass, free, c_mass, c_stiff, stiffness


def median_seconds(fn, device, warmup, repeat, inner):
    """Median seconds per call of ``fn`` over ``repeat`` samples of ``inner`` back-to-back calls."""
    for _ in range(warmup):
        fn()
    samples = []
    if common.is_cuda(device):
        torch.cuda.synchronize(device)
        for _ in range(repeat):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            for _ in range(inner):
                fn()
            end.record()
            end.synchronize()
            samples.append(start.elapsed_time(end) * 1e-3 / inner)
    else:
        for _ in range(repeat):
            t0 = time.perf_counter()
            for _ in range(inner):
                fn()
            samples.append((time.perf_counter() - t0) / inner)
    return statistics.median(samples)


def measure(name, sim, device, args):
    """The table rows of one scene: one per layout."""
    group, u, p, mass, free, c_mass, c_stiff, stiffness = matvec_case(sim)
    plan = group.plan
    neighbor, node_k = node_graph.hooke_node_graph(group)  # built once, cached on the group

    def call(layout):
        variants = KernelVariants(hooke_matvec=layout)
        return lambda: native.system_matvec(group, u, p, mass, free, c_mass, c_stiff, None, stiffness,
                                            variants=variants)

    with torch.no_grad():
        results = {layout: call(layout)() for layout in LAYOUTS}
        same = all(torch.equal(a, b) for a, b in zip(results["node"], results["padded"]))
        seconds = {layout: median_seconds(call(layout), device, args.warmup, args.repeat, args.inner)
                   for layout in LAYOUTS}
    itemsize = u.element_size()
    extra_mb = {  # per call (padded: the PartialForce buffer) or held (node: the node graph)
        "padded": plan.partial_force_bytes(u.shape[1], itemsize) / 1e6,
        "node": (neighbor.numel() * neighbor.element_size() + node_k.numel() * node_k.element_size()) / 1e6,
    }
    rows = []
    for layout in LAYOUTS:
        rows.append({
            "scene": name, "nodes": plan.num_nodes, "edges": group.edges.shape[0], "N_n": plan.num_slots,
            "layout": layout, "us": seconds[layout] * 1e6, "x_padded": seconds["padded"] / seconds[layout],
            "bitwise": "yes" if same else "NO", "buffer_mb": extra_mb[layout],
        })
    return rows


COLUMNS = [("scene", "scene", "{}"), ("nodes", "nodes", "{:,}"), ("edges", "edges", "{:,}"), ("N_n", "N_n", "{}"),
           ("layout", "layout", "{}"), ("us", "us per matvec", "{:.2f}"), ("x_padded", "speed-up vs padded", "{:.2f}"),
           ("bitwise", "node == padded bitwise", "{}"),
           ("buffer_mb", "MB (padded: PartialForce per call; node: graph held)", "{:.1f}")]


def markdown(rows):
    lines = ["| " + " | ".join(title for _, title, _ in COLUMNS) + " |",
             "|" + "|".join("---" for _ in COLUMNS) + "|"]
    for row in rows:
        lines.append("| " + " | ".join(fmt.format(row[key]) for key, _, fmt in COLUMNS) + " |")
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--quick", action="store_true", help="small beams, few repeats (seconds on a CPU)")
    parser.add_argument("--warmup", type=int, default=None)
    parser.add_argument("--repeat", type=int, default=None)
    parser.add_argument("--inner", type=int, default=None, help="back-to-back calls per timed sample")
    parser.add_argument("--out", default=None, help="folder for node_system_bench.md (default: print only)")
    args = parser.parse_args(argv)
    quick = dict(warmup=2, repeat=5, inner=2)
    normal = dict(warmup=20, repeat=50, inner=20)
    for key, value in (quick if args.quick else normal).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    if not library.ensure_registered() or not hasattr(torch.ops.tensormass, "hooke_node_system"):
        raise SystemExit("node_system_bench: the compiled extension with hooke_node_system is needed")
    if common.is_cuda(args.device) and not tm._C.has_cuda():
        raise SystemExit("node_system_bench: the extension was built without CUDA")
    rows = []
    for name, sim in build_scenes(args.device, args.quick):
        rows.extend(measure(name, sim, args.device, args))
    header = (f"hooke tensor-form CG matvec, float32, {common.device_name(args.device)}, "
              f"median of {args.repeat} x {args.inner} calls after {args.warmup} warm-up calls, "
              f"commit {common.git_commit()}")
    text = header + "\n\n" + markdown(rows)
    print(text)
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "node_system_bench.md").write_text(text + "\n")
    return rows


if __name__ == "__main__":
    main()
