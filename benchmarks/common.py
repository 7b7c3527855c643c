"""What every benchmark script shares: timing, metadata, the record schema, writers, the copy
bandwidth and the byte count of one CG iteration (the floor: benchmarks/README.md, Method).

Timing is CUDA-synchronised wall clock: ``sync`` before starting and before stopping the clock,
so a measurement covers everything the GPU was asked to do, launches and host work included
(what a user of ``sim.step`` waits for). Warm-up calls come first; the result is the median of
the repeats (``time_call``) or the mean over a run of steps (``time_steps``).

Records (one per measurement, ``record``): the fields of ``RECORD_FIELDS`` (None where they do
not apply) plus any script-specific ones. Writers put ``<name>.md`` (a table), ``<name>.json``
(``{"meta": {...}, "records": [...]}``) and ``<name>.png`` (when matplotlib imports) under the
output folder; the md and json are rewritten after every measurement so that a run cut short
still leaves what it measured.
"""
from __future__ import annotations

import contextlib
import datetime
import json
import math
import os
import statistics
import subprocess
import time
from pathlib import Path
from typing import Callable, Dict, Iterable, List, Optional, Sequence

import torch

import tensormass_torch as tm

# The fields every record has (None where they do not apply). Units are in the names.
RECORD_FIELDS = (
    "scene",                 # what was simulated: "paper_beam", "sofa_beam", "batch", ...
    "model",                 # "hooke" | "stvk" | "corotational"
    "kind",                  # "tet" | "tri"
    "elements",              # elements of the whole scene (all objects)
    "nodes",                 # nodes of the whole scene
    "objects",               # objects in the batch (1 for a single body)
    "backend",               # "extension" | "torch" | "csr" | "bsr" | "cupy" | "loop-extension" ...
    "device",                # "cuda" | "cpu"
    "device_name",           # "NVIDIA H200", "cpu (16 threads)"
    "dtype",                 # "float32" | "float64"
    "cg_iterations",         # CG iterations of one step (the fixed budget the step ran)
    "steps",                 # steps timed (after warm-up)
    "steps_per_s",           # whole implicit Euler steps per second
    "ms_per_step",
    "objects_steps_per_s",   # objects x steps per second (batches)
    "ms_per_cg_iteration",   # time of one CG iteration (see each script for how it is taken)
    "bytes_per_cg_iteration",  # the floor's byte count (cg_iteration_bytes)
    "floor_ms_per_cg_iteration",  # bytes / measured copy bandwidth of the device
    "floor_ratio",           # ms_per_cg_iteration / floor_ms_per_cg_iteration
    "assembly_ms",           # assembled-matrix alternatives: time to assemble A once
    "error",                 # why the measurement failed (then the numbers are None)
    "skipped",               # why it was not run (time limit, size limit, no CUDA, ...)
)


# ---------------------------------------------------------------------------------------------
# devices, timing, budgets
# ---------------------------------------------------------------------------------------------


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def is_cuda(device) -> bool:
    return torch.device(device).type == "cuda"


def sync(device) -> None:
    """Wait for the device's queued work (no-op on the CPU)."""
    if is_cuda(device):
        torch.cuda.synchronize(torch.device(device))


def time_call(fn: Callable[[], object], device, warmup: int = 2, repeat: int = 5) -> float:
    """Median seconds of ``fn()`` over ``repeat`` synchronised calls, after ``warmup`` calls."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(max(repeat, 1)):
        sync(device)
        start = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def time_steps(step: Callable[[int], object], device, steps: int, max_seconds: float) -> tuple:
    """Seconds per call of ``step(1)``, over up to ``steps`` calls or until ``max_seconds`` passed
    (at least one call). Steps are timed one by one (each synchronised) only to stop in time;
    the result is total time / steps, so a step's launches overlap nothing they would not
    overlap in a user's loop except across the synchronisation. Returns (seconds_per_step, n)."""
    sync(device)
    start = time.perf_counter()
    done = 0
    # Steps are issued in chunks so the clock is read rarely; the first chunk is one step (its
    # time sizes the next chunks against max_seconds).
    chunk = 1
    while done < steps:
        step(chunk)
        sync(device)
        done += chunk
        elapsed = time.perf_counter() - start
        if elapsed >= max_seconds:
            break
        per_step = elapsed / done
        room = int((max_seconds - elapsed) / max(per_step, 1e-9))
        chunk = max(1, min(steps - done, room, 2 * done))
    return (time.perf_counter() - start) / done, done


class Budget:
    """Wall-clock seconds a script may still spend; measurements ask it before they start."""

    def __init__(self, seconds: Optional[float]):
        self.deadline = None if seconds is None else time.monotonic() + float(seconds)

    def remaining(self) -> float:
        return math.inf if self.deadline is None else self.deadline - time.monotonic()

    def allows(self, estimate_s: float) -> bool:
        return estimate_s <= self.remaining()

    def share(self, parts: int) -> "Budget":
        """A budget of remaining / parts seconds (one of ``parts`` parts still to run)."""
        sub = Budget(None)
        if self.deadline is not None:
            sub.deadline = time.monotonic() + max(self.remaining(), 0.0) / max(parts, 1)
        return sub


@contextlib.contextmanager
def forced_backend(mode: Optional[str]):
    """Run the block with ``TENSORMASS_BACKEND=mode`` ("torch" forces the pure-torch path; it is
    read at every op call, so the whole block, construction included, runs that path). None:
    leave the environment as it is."""
    if mode is None:
        yield
        return
    old = os.environ.get("TENSORMASS_BACKEND")
    os.environ["TENSORMASS_BACKEND"] = mode
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("TENSORMASS_BACKEND", None)
        else:
            os.environ["TENSORMASS_BACKEND"] = old


def release(device) -> None:
    """Give cached device memory back between measurements of different sizes."""
    import gc

    gc.collect()
    if is_cuda(device):
        torch.cuda.empty_cache()


# ---------------------------------------------------------------------------------------------
# metadata and records
# ---------------------------------------------------------------------------------------------


def git_commit() -> Optional[str]:
    """$TENSORMASS_COMMIT (the GPU machine's copy of the tree has no .git), else the short commit
    of the tree (+"-dirty" with uncommitted changes to tracked files), else None."""
    env = os.environ.get("TENSORMASS_COMMIT")
    if env:
        return env
    here = Path(__file__).resolve().parent
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                cwd=here, timeout=10).stdout.strip()
        if not commit:
            return None
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True,
                               text=True, cwd=here, timeout=10).stdout.strip()
        return commit + ("-dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def device_name(device) -> str:
    if is_cuda(device):
        return torch.cuda.get_device_name(torch.device(device))
    return f"cpu ({torch.get_num_threads()} threads)"


def metadata(device, **extra) -> Dict[str, object]:
    """Device, date, commit, versions and thread count of this run (the md header, json meta)."""
    try:
        backends = tm.backend_info()
    except Exception as exc:  # a bad TENSORMASS_BACKEND: recorded, not fatal for the metadata
        backends = {"error": str(exc)}
    meta = {
        "device": str(device),
        "device_name": device_name(device),
        "cpu_threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
        "backend_info": backends,
    }
    meta.update(extra)
    return meta


def write_blocks(path, args, blocks) -> None:
    """A probe's blocks of steps as JSON at ``path`` (None: nothing), with the run's metadata and
    its command line's ``args`` (an ``argparse.Namespace`` with ``device``)."""
    if path is not None:
        Path(path).write_text(json.dumps(dict(meta=metadata(args.device), args=vars(args), blocks=blocks), indent=1,
                                         default=str))


def record(**fields) -> Dict[str, object]:
    """One measurement: every field of ``RECORD_FIELDS`` (None unless given) plus the extras."""
    rec = {name: None for name in RECORD_FIELDS}
    rec.update(fields)
    return rec


def error_text(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {lines[0][:200] if lines else ''}"


def add_floor(rec: Dict[str, object], bytes_per_iteration: Optional[int], bandwidth_bytes_per_s: Optional[float]):
    """Fill bytes/floor/floor_ratio of a record from its ms_per_cg_iteration."""
    if bytes_per_iteration is None or not bandwidth_bytes_per_s:
        return rec
    floor_ms = 1e3 * bytes_per_iteration / bandwidth_bytes_per_s
    rec["bytes_per_cg_iteration"] = int(bytes_per_iteration)
    rec["floor_ms_per_cg_iteration"] = floor_ms
    if rec.get("ms_per_cg_iteration"):
        rec["floor_ratio"] = rec["ms_per_cg_iteration"] / floor_ms
    return rec


# ---------------------------------------------------------------------------------------------
# writers
# ---------------------------------------------------------------------------------------------


def _cell(value, fmt: Optional[str]) -> str:
    if value is None:
        return ""
    if fmt and isinstance(value, (int, float)) and not isinstance(value, bool):
        return format(value, fmt)
    return str(value).replace("|", "/")


def markdown_table(records: Sequence[dict], columns: Sequence[tuple]) -> str:
    """Rows of ``records`` as a markdown table; ``columns``: (field, header, format or None).
    A record with ``error`` or ``skipped`` shows that text in the last column."""
    header = [h for _, h, _ in columns] + ["note"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    for r in records:
        note = r.get("error") or r.get("skipped") or r.get("note") or ""
        cells = [_cell(r.get(f), fmt) for f, _, fmt in columns] + [_cell(note, None)]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def header_lines(title: str, meta: dict) -> List[str]:
    bw = meta.get("copy_bandwidth_GBps") or {}
    bw_text = ", ".join(f"{k} {v:.0f} GB/s" for k, v in bw.items()) if isinstance(bw, dict) else ""
    return [
        f"# {title}",
        "",
        f"{meta.get('device_name')}; {meta.get('date')}; commit {meta.get('commit')}; torch {meta.get('torch')}"
        f" (CUDA {meta.get('cuda')}); CPU threads {meta.get('cpu_threads')} of {meta.get('cpu_count')}"
        + (f"; copy bandwidth {bw_text}" if bw_text else ""),
        "",
    ]


class Results:
    """The md/json/png of one benchmark under ``out``: add records as they come, write at the end.

    Args:
        out: the folder (created). name: file stem (``figure2`` -> figure2.md/.json/.png).
        title: first line of the md. meta: ``metadata(...)``. columns: the md table's columns.
        notes: lines printed under the header (what is measured, how).
    """

    def __init__(self, out, name: str, title: str, meta: dict, columns: Sequence[tuple], notes: Iterable[str] = ()):
        self.out = Path(out)
        self.out.mkdir(parents=True, exist_ok=True)
        self.name, self.title, self.meta, self.columns = name, title, meta, list(columns)
        self.notes = list(notes)
        self.records: List[dict] = []
        self.plot_note = None
        #: markdown lines written after the table (a summary drawn from the records)
        self.appendix: List[str] = []

    def add(self, rec: dict, echo: bool = True) -> dict:
        rec.setdefault("device_name", self.meta.get("device_name"))
        self.records.append(rec)
        if echo:
            print(json.dumps({k: v for k, v in rec.items() if v is not None}, default=str), flush=True)
        self.write()
        return rec

    def markdown(self) -> str:
        lines = header_lines(self.title, self.meta) + self.notes + ([""] if self.notes else [])
        lines.append(markdown_table(self.records, self.columns))
        if self.appendix:
            lines += [""] + self.appendix
        if self.plot_note:
            lines += ["", self.plot_note]
        return "\n".join(lines) + "\n"

    def write(self) -> None:
        (self.out / f"{self.name}.md").write_text(self.markdown())
        (self.out / f"{self.name}.json").write_text(
            json.dumps({"meta": self.meta, "records": self.records}, indent=1, default=str))

    def plot(self, draw: Callable) -> Optional[Path]:
        """``draw(plt) -> figure`` saved as ``<name>.png``; without matplotlib a note in the md."""
        try:
            import matplotlib

            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            self.plot_note = f"({self.name}.png not drawn: matplotlib is not installed)"
            self.write()
            return None
        path = self.out / f"{self.name}.png"
        try:
            fig = draw(plt)
            fig.savefig(path, dpi=120, bbox_inches="tight")
            plt.close(fig)
        except Exception as exc:  # a plot must never lose the numbers
            self.plot_note = f"({self.name}.png failed: {error_text(exc)})"
            self.write()
            return None
        self.write()
        return path

    def finish(self) -> None:
        self.write()
        print(self.markdown(), flush=True)


def plot_title(meta: dict, what: str) -> str:
    return f"{what}\n{meta.get('device_name')}, {str(meta.get('date'))[:10]}, commit {meta.get('commit')}"


# ---------------------------------------------------------------------------------------------
# the floor: copy bandwidth and bytes per CG iteration
# ---------------------------------------------------------------------------------------------


def copy_bandwidth(device, nbytes: int = 1 << 30) -> float:
    """Bytes/s of a large same-device copy (``dst.copy_(src)``), read + write counted: the
    bandwidth the floor divides by. CUDA: 1 GiB (far beyond L2), timed with CUDA events (the
    copy alone, no launch or synchronisation overhead), median of 9; CPU: 256 MiB at most,
    all threads, wall clock, median of 5."""
    if not is_cuda(device):
        nbytes = min(nbytes, 1 << 28)
    src = torch.ones(nbytes // 4, dtype=torch.float32, device=device)
    dst = torch.empty_like(src)
    if not is_cuda(device):
        seconds = time_call(lambda: dst.copy_(src), device, warmup=2, repeat=5)
        return 2.0 * nbytes / seconds
    for _ in range(2):
        dst.copy_(src)
    times = []
    for _ in range(9):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        dst.copy_(src)
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end) * 1e-3)
    return 2.0 * nbytes / statistics.median(times)


# Per form, the group buffers the CG's matvec (kernel 1 with DForce) must read once per
# iteration. The gather plan's index/ForceIndex/incidences are counted separately, at the index
# width the extension reads (int32 where the values fit).
_MATVEC_BUFFERS = {
    ("stress", "hooke"): ("shape_vectors", "measure", "young", "poisson", "projector"),
    ("stress", "stvk"): ("shape_vectors", "measure", "young", "poisson", "projector"),
    ("stress", "corotational"): ("shape_vectors", "measure", "young", "poisson", "projector", "rest_elements",
                                 "rest_normals"),
    ("tensor", "hooke"): ("edge_k",),
    ("tensor", "stvk"): ("tensor_b", "tensor_c", "tensor_d"),
}


def _nbytes(t: Optional[torch.Tensor]) -> int:
    return 0 if t is None else t.numel() * t.element_size()


def _edge_count(index: torch.Tensor, num_nodes: int) -> int:
    """Distinct node pairs over the items of ``index [N, n]`` (the node graph's edges)."""
    n = index.shape[1]
    pairs = [torch.stack((index[:, a], index[:, b]), 1) for a in range(n) for b in range(a + 1, n)]
    if not pairs:
        return 0
    both = torch.cat(pairs).long()
    low, high = both.min(1).values, both.max(1).values
    return int(torch.unique(low * num_nodes + high).numel())


def cg_iteration_bytes(model, objects: int = 1, constrained: bool = True, planes: int = 0) -> Dict[str, int]:
    """Bytes one CG iteration of implicit Euler must move at the least (each read once, each
    write once), for a ``tm.TensorMass`` (e.g. ``sim.model``) of V nodes in d = 3 dimensions,
    float size s, index size ix (4: int32, what the extension reads when the ids fit).

    Per group (N items with n nodes: elements, or edges for the hooke tensor form):
      indices        index and ForceIndex [N, n] (2 N n ix), incidences [V] (V ix)
      material       the group's buffers its DForce reads (``_MATVEC_BUFFERS``): e.g. the stress
                     form's shape vectors [N, n, d], measure, young, poisson [N] (the extension
                     turns young/poisson into lam/mu, same size), projectors of membranes;
                     corotational adds the rest element nodes (QR frame); the hooke tensor
                     form its edge [Ed, d, d] tensors; the stvk tensor
                     form B, C, D
      partial_force  PartialForce written by kernel 1 and read by kernel 2: 2 N n d s (the
                     used slots only: the padding of the [N_n, V, d] buffer is not counted)
      p              the search direction read by kernel 1: V d s
      u              displacements read by DForce where K depends on u (stvk, corotational): V d s
    A model whose differential the CG may take once per linearisation as the edge blocks of the
    node graph (the hooke tensor form's own graph; stvk and corotational through
    ``KernelVariants.node_tangent``) is counted as that graph where it moves fewer bytes than the element
    form: its E edges as items of n = 2 nodes, E d x d blocks as material, no u (the stvk tensor
    form: B, C, D and u per iteration against one block an edge).
    Once per iteration:
      epilogue       mass [V] and free mask [V] read, A p [V, d] written, p . Ap per node [V]
                     written: (2 + d + 1) V s (free mask only when nodes are constrained)
      updates        x += a p; r -= a Ap (reads x, p, r, Ap, writes x, r: 6 V d s) and
                     p = r + b p (reads r, p, writes p: 3 V d s), the per-node p.Ap read by
                     its reduction (V s): 9 V d s + V s
      segments       object id per node read by the per-object reductions: V ix when objects > 1
      planes         positions read by the contact term, per plane: V d s
    Returns the parts and their ``total`` (bytes).
    """
    V = int(model.num_nodes)
    d = int(model.dim)
    s = model.rest.element_size()
    parts = {"indices": 0, "material": 0, "partial_force": 0, "p": 0, "u": 0}
    for group in model.groups:
        index = group.plan.index
        n_items, n = index.shape
        ix = 4 if (V <= 2**31 - 1 and index.numel() <= 2**31 - 1) else 8
        names = _MATVEC_BUFFERS.get((group.form, group.model), ())
        element_form = {"indices": 2 * n_items * n * ix + V * ix,
                        "material": sum(_nbytes(getattr(group, name, None)) for name in names),
                        "partial_force": 2 * n_items * n * d * s,
                        "u": V * d * s if group.model in ("stvk", "corotational") else 0}
        edges = _edge_count(index, V)
        node_graph = {"indices": 2 * edges * 2 * ix + V * ix, "material": edges * d * d * s,
                      "partial_force": 2 * edges * 2 * d * s, "u": 0}
        counted = min(element_form, node_graph, key=lambda form: sum(form.values()))
        for name, value in counted.items():
            parts[name] += value
        parts["p"] += V * d * s
    parts["epilogue"] = (1 + (1 if constrained else 0) + d + 1) * V * s
    parts["updates"] = 9 * V * d * s + V * s
    parts["segments"] = V * 4 if objects > 1 else 0
    parts["planes"] = planes * V * d * s
    parts["total"] = sum(parts.values())
    return parts


def sim_cg_bytes(sim) -> Dict[str, int]:
    """``cg_iteration_bytes`` of a ``tm.Simulator``'s packed model."""
    constrained = bool(sim.fixed.any() or sim.prescribed.any())
    return cg_iteration_bytes(sim.model, objects=sim.num_bodies, constrained=constrained,
                              planes=len(sim.planes) if sim.planes is not None else 0)


# ---------------------------------------------------------------------------------------------
# scenes of the figures
# ---------------------------------------------------------------------------------------------

PAPER_BEAM = (80, 32, 20)        # 307,200 tetrahedra (hexes x 6)
PAPER_SIZE = (1.0, 0.4, 0.25)
TRI_BEAM = (480, 320)            # 307,200 triangles (quads x 2): the paper's count in 2-D


def tet_dims(elements: int) -> tuple:
    """Hex counts (nx, ny, nz) of a beam with the paper beam's proportions and about
    ``elements`` tetrahedra (6 per hex)."""
    k = (elements / (6.0 * PAPER_BEAM[0] * PAPER_BEAM[1] * PAPER_BEAM[2])) ** (1.0 / 3.0)
    return tuple(max(1, round(k * n)) for n in PAPER_BEAM)


def tri_dims(elements: int) -> tuple:
    """Quad counts (nx, ny) of a rectangle of about ``elements`` triangles (2 per quad)."""
    k = (elements / (2.0 * TRI_BEAM[0] * TRI_BEAM[1])) ** 0.5
    return tuple(max(1, round(k * n)) for n in TRI_BEAM)


def cantilever_sim(kind: str, model: str, elements: int, device, dtype=torch.float32, cg_iterations: int = 25,
                   young: float = 1e5):
    """The paper's beam scene at about ``elements`` elements: clamped at x = 0, under gravity,
    implicit Euler with a fixed CG budget (tol 0: every variant does the same work).

    tet: ``beam_mesh`` with the paper beam's proportions (1 x 0.4 x 0.25 m), gravity -z.
    tri: ``beam_tri_mesh`` (1 x 0.667 m) as a membrane in the plane z = 0, gravity -y (in plane).
    Material: E = ``young`` (default the paper's 1e5 Pa), nu = 0.3, rho = 1000, the exact tangent;
    corotational with SOFA's QR frame (the frame the extension implements). Returns (simulator,
    gravity).
    """
    if kind == "tet":
        mesh = tm.beam_mesh(*tet_dims(elements), size=PAPER_SIZE, dtype=dtype, device=device)
        gravity = (0.0, 0.0, -9.81)
    elif kind == "tri":
        nx, ny = tri_dims(elements)
        mesh = tm.beam_tri_mesh(nx, ny, size=(1.0, ny / nx), dtype=dtype, device=device)
        gravity = (0.0, -9.81, 0.0)
    else:
        raise ValueError(f"unknown element kind {kind!r}; expected 'tet' or 'tri'")
    # The paper's method: stvk on its exact tangent (the default "auto" would take the definite one)
    rotation = {"rotation": "qr"} if model == "corotational" else {}
    mat = tm.Material(young=young, poisson=0.3, density=1000.0, model=model, tangent="exact", **rotation)
    body = tm.Body(mesh, mat, fixed=mesh.vertices[:, 0] <= 1e-6)
    sim = tm.Simulator([body], dt=0.01, gravity=gravity, cg_tol=0.0, cg_max_iter=cg_iterations,
                       require_convergence=False, check_every=1000, device=device, dtype=dtype)
    return sim, gravity


def last_cg_iterations(sim) -> Optional[int]:
    report = sim.last_report
    if report is None:
        return None
    return int(torch.as_tensor(report.cg_iterations).max())


def parse_ints(text: str) -> List[int]:
    return [int(float(x)) for x in text.split(",") if x.strip()]


def fill_defaults(args, normal: Dict[str, object], quick: Dict[str, object]) -> None:
    """Options left at None take their --quick value (when ``args.quick``) or their normal one;
    an option given on the command line wins in both cases."""
    for name, value in normal.items():
        if getattr(args, name) is None:
            setattr(args, name, quick.get(name, value) if args.quick else value)
