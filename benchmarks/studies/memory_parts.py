"""The memory estimate's parts (``tensormass_torch.sim.memory.HELD``): bytes an element and bytes
a node that a simulator holds while it steps, each an index part and a float part.

    python benchmarks/studies/memory_parts.py --out DIR
    python benchmarks/studies/memory_parts.py --quick --out DIR       # seconds

For each element kind and model, two mesh families (a beam: few nodes an element; a batch of
small bodies: many) in float32 and float64: every tensor storage a simulator adds over its
construction and two steps, counted on the CPU (the Python heap's tensors). The two families give
the element and node parts (bytes = a N + b V), the two dtypes the index and float parts (the
float bytes double in float64, the index bytes do not). The peaks' extra bytes come from the GPU
(``setup_memory.py``, ``distributed_scaling.py``), not from here.
"""
from __future__ import annotations

import argparse
import gc
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import torch
from common import metadata

import tensormass_torch as tm

MODELS = ("hooke", "stvk", "corotational")


def families(kind: str, dtype, quick: bool) -> dict:
    """``{family: (mesh, copies)}``: a beam and a batch of small bodies of ``kind``."""
    if kind == "tet":
        beam = tm.beam_mesh(*((12, 3, 3) if quick else (60, 12, 12)), size=(5.0, 1.0, 1.0), dtype=dtype)
        return {"beam": (beam, 1), "small bodies": (tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), dtype=dtype),
                                                    40 if quick else 1000)}
    sheet = tm.beam_tri_mesh(*((30, 15) if quick else (300, 150)), size=(2.0, 1.0), dim=3, dtype=dtype)
    return {"beam": (sheet, 1), "small bodies": (tm.beam_tri_mesh(4, 4, size=(0.1, 0.1), dim=3, dtype=dtype),
                                                 60 if quick else 1500)}


def storages() -> dict:
    """Bytes of each distinct tensor storage the Python heap holds, by address."""
    gc.collect()
    found = {}
    for obj in gc.get_objects():
        # (issubclass on the type: isinstance would touch deprecated module objects and warn)
        kind = type(obj)
        if issubclass(kind, torch.Tensor) and obj.device.type == "cpu" and not kind.__name__.startswith("Fake"):
            storage = obj.untyped_storage()
            found[storage.data_ptr()] = storage.nbytes()
    return found


def held_bytes(mesh, copies: int, model: str, dtype) -> int:
    """What a simulator of ``copies`` bodies of ``mesh`` adds, after two steps."""
    before = storages()
    material = tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model)
    bodies = [tm.Body(mesh, material, fixed=mesh.vertices[:, 0] <= 1e-9) for _ in range(copies)]
    sim = tm.Simulator(bodies, dt=0.01, cg_tol=0.0, cg_max_iter=5, require_convergence=False, dtype=dtype)
    sim.step(2)
    after = storages()
    del sim
    return sum(size for address, size in after.items() if address not in before)


def parts(kind: str, model: str, quick: bool) -> dict:
    """The element and node parts (index, float32) of ``kind`` and ``model``, and the counts."""
    fits, counts = {}, {}
    for dtype in (torch.float32, torch.float64):
        points = []
        for family, (mesh, copies) in families(kind, dtype, quick).items():
            elements, nodes = mesh.num_elements * copies, mesh.num_vertices * copies
            total = held_bytes(mesh, copies, model, dtype)
            points.append((nodes / elements, total / elements))
            counts[(family, str(dtype)[6:])] = dict(elements=elements, nodes=nodes, bytes=total)
        (v0, b0), (v1, b1) = points
        node = (b1 - b0) / (v1 - v0)
        fits[dtype] = (b0 - v0 * node, node)
    (e32, n32), (e64, n64) = fits[torch.float32], fits[torch.float64]
    return dict(kind=kind, model=model, element=(2 * e32 - e64, e64 - e32), node=(2 * n32 - n64, n64 - n32),
                counts={f"{f}, {d}": c for (f, d), c in counts.items()})


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="benchmarks/results/scale")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--kinds", default="tet,tri")
    parser.add_argument("--models", default=",".join(MODELS))
    args = parser.parse_args(argv)
    rows = [parts(kind, model, args.quick) for kind in args.kinds.split(",") for model in args.models.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = metadata(torch.device("cpu"))
    (out / "memory_parts.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = ["# The memory estimate's held parts (bytes an element and a node, CPU count)", "",
             f"{meta.get('date')}; commit {meta.get('commit')}; torch {meta.get('torch')}"
             + ("; --quick (small meshes)" if args.quick else ""), "",
             "| kind | model | element: index B | element: float32 B | node: index B | node: float32 B |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['kind']} | {r['model']} | {r['element'][0]:.0f} | {r['element'][1]:.0f} | "
                     f"{r['node'][0]:.0f} | {r['node'][1]:.0f} |")
    (out / "memory_parts.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return rows


if __name__ == "__main__":
    main()
