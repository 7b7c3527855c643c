"""Large rotations (issue 4): the twist and spin scenes with hooke, corotational (polar, qr) and stvk.

    python benchmarks/studies/large_rotation.py [--resolution 2] [--steps 100] [--device cpu] [--dtype float64]
                                        [--variants hooke corotational ...] [--out benchmarks/results/large_rotation]
                                        [--no-render]

Measures per frame the volume (sum of signed tet volumes against the rest volume), the smallest
element volume ratio, the inverted elements, the kinetic and elastic energy (each model's own,
and the rotation-invariant corotational energy of the same positions), and for the spin the
angle turned; the twist's end energy is compared with the torsion energy of the same mesh
(a small-angle hooke solve, scaled) and with Saint-Venant's bar. Writes to ``--out``:
``large_rotation.json`` (one record per scene and model, with the frames, device, date, commit),
``large_rotation.md`` (the tables) and, with pyvista, ``twist_180.png``, ``spin.png`` (hooke vs
corotational, rest shape in grey) and ``twist.gif``.
The measuring code is the example's (``examples/large_rotation.py``).
"""
import argparse
import datetime
import importlib.util
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent


def _load_example():
    spec = importlib.util.spec_from_file_location("large_rotation_example", ROOT / "examples" / "large_rotation.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


example = _load_example()


def commit() -> str:
    if os.environ.get("TENSORMASS_COMMIT"):
        return os.environ["TENSORMASS_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def device_name(device: str) -> str:
    if device.startswith("cuda") and torch.cuda.is_available():
        return torch.cuda.get_device_name(torch.device(device))
    return platform.processor() or platform.machine()


def _fmt(value, spec):
    return "-" if value is None else format(value, spec)


def markdown(meta, summaries) -> str:
    backend = meta["backend"]["cpu" if meta["device"] == "cpu" else "cuda"]
    lines = [
        "# Large rotations: hooke against corotational and stvk",
        "",
        f"{meta['date']}, commit {meta['commit']}, {meta['device']} ({meta['device_name']}), {meta['dtype']}, "
        f"torch {meta['torch']}, backend {backend}; "
        f"beam 1 m x 0.1 m x 0.1 m, E = 5 MPa, nu = 0.3, rho = 1000 kg/m^3, resolution {meta['resolution']} "
        f"({summaries[0]['tets']} tets), {meta['steps']} implicit Euler steps over 1 s, CG tolerance 1e-6.",
        "",
        "Volume: sum of signed tet volumes against the rest volume (end of run; max |change| over the run). "
        "Min ratio: the smallest element volume / rest volume over the run (< 0: inverted). "
        "Invariant energy: the corotational (polar) energy of the same positions, a rotation-invariant "
        "measure of the strain that every model is judged by.",
        "",
        "## twist: clamped at x = 0, the far end turned 180 deg about the beam's axis",
        "",
        "Exact: a twisted bar of unchanged volume. Reference energy: this mesh's small-strain torsion energy "
        "(a static hooke solve at 0.001 rad scaled by angle^2); Saint-Venant's continuum bar "
        f"{next((s['reference_energy_saint_venant'] for s in summaries if s['scene'] == 'twist'), 0):.1f} J "
        "(the coarse P1 mesh is stiffer in torsion).",
        "",
        "| model | volume change | max abs change | min element ratio | inverted | energy (own) J | "
        "invariant energy J | own / reference | reference J | CG its | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        if s["scene"] != "twist":
            continue
        lines.append(f"| {s['variant']} | {s['volume_change_end_pct']:+.2f}% | {s['volume_change_max_pct']:.2f}% | "
                     f"{s['min_element_volume_ratio']:+.3f} | {s['inverted_max']} | {s['elastic_end']:.1f} | "
                     f"{s['elastic_invariant_end']:.1f} | {s['elastic_end_over_reference']:.2f} | "
                     f"{s['reference_energy_mesh']:.1f} | {s['cg_iterations']} | {s['wall_s']:.1f} |")
    lines += [
        "",
        "## spin: a free beam spinning about z through 180 deg (no gravity, no damping)",
        "",
        "Exact: a rigid rotation through 180 deg; volume and energy unchanged. Energy drift: (kinetic + elastic) "
        "at the end against the start, with each model's own elastic energy and with the invariant one.",
        "",
        "| model | volume change | min element ratio | inverted | turned deg | energy drift (own) | "
        "energy drift (invariant) | kinetic change | CG its | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        if s["scene"] != "spin":
            continue
        lines.append(f"| {s['variant']} | {s['volume_change_end_pct']:+.2f}% | {s['min_element_volume_ratio']:+.3f} | "
                     f"{s['inverted_max']} | {s['angle_deg']:.1f} | {s['energy_drift_pct']:+.2f}% | "
                     f"{_fmt(s['energy_drift_invariant_pct'], '+.4g')}% | {s['kinetic_change_pct']:+.1f}% | "
                     f"{s['cg_iterations']} | {s['wall_s']:.1f} |")
    lines += ["", "Variants: `corotational` = polar rotations, `corotational-qr` = SOFA's QR frame, "
              "`stvk-newton3` = stvk with 3 Newton iterations per step (the others: one linearisation per step).", ""]
    return "\n".join(lines)


def render(out: Path, meshes, snapshots, variants):
    """Pictures of hooke against corotational (rest shape in grey); skipped without pyvista."""
    from tensormass_torch.app import render as r

    pair = [v for v in ("hooke", "corotational") if v in variants]
    if len(pair) < 2:
        return []
    written = []
    mesh = meshes["twist"]
    twist = snapshots["twist"]
    written.append(r.render_png(out / "twist_180.png",
                                [[(mesh, None), (mesh, twist[v][-1])] for v in pair],
                                labels=[f"{v}: end turned 180 deg" for v in pair], window_size=(1200, 460),
                                zoom=1.3))
    frames = [[[(mesh, None), (mesh, twist[v][k])] for v in pair] for k in range(0, len(twist[pair[0]]), 2)]
    written.append(r.render_gif(out / "twist.gif", frames, fps=4, window_size=(720, 280), labels=pair,
                               zoom=1.3))
    mesh = meshes["spin"]
    spin = snapshots["spin"]
    half = (len(spin[pair[0]]) - 1) // 2
    panels, labels = [], []
    for k, when in ((half, "0.5 s (rigid: 90 deg)"), (-1, "1 s (rigid: 180 deg)")):
        for v in pair:
            panels.append([(mesh, None), (mesh, spin[v][k])])
            labels.append(f"{v}\nt = {when}")
    written.append(r.render_png(out / "spin.png", panels, labels=labels, camera="xy", window_size=(1600, 440),
                                zoom=0.8))
    return written


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--resolution", type=int, default=2, help="cells across the beam's section")
    parser.add_argument("--steps", type=int, default=100, help="implicit Euler steps over the 1 s run")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--variants", nargs="+", default=list(example.VARIANTS), choices=list(example.VARIANTS))
    parser.add_argument("--scenes", nargs="+", default=["twist", "spin"], choices=sorted(example.SCENES))
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "large_rotation"))
    parser.add_argument("--no-render", action="store_true", help="write no pictures")
    args = parser.parse_args(argv)
    import tensormass_torch as tm

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    meta = {
        "date": datetime.date.today().isoformat(), "commit": commit(), "device": args.device,
        "device_name": device_name(args.device), "dtype": args.dtype, "torch": torch.__version__,
        "backend": tm.backend_info(), "resolution": args.resolution, "steps": args.steps,
        "threads": torch.get_num_threads(),
    }
    summaries, frames, snapshots, meshes = [], {}, {}, {}
    for scene_name in args.scenes:
        for variant in args.variants:
            try:
                summary, records, snaps = example.run_case(scene_name, variant, args.resolution, args.steps,
                                                           dtype=getattr(torch, args.dtype), device=args.device)
            except tm.SolverError as exc:  # a model that cannot finish the scene is a result too
                print(f"{scene_name} {variant}: solver failed: {exc}", flush=True)
                summaries.append({"scene": scene_name, "variant": variant, "failed": str(exc)})
                continue
            summaries.append(summary)
            frames.setdefault(scene_name, {})[variant] = records
            snapshots.setdefault(scene_name, {})[variant] = snaps
            meshes[scene_name] = example.SCENES[scene_name](resolution=args.resolution).simulator.bodies[0].mesh
            print(example.format_summary(summary), flush=True)
    ok = [s for s in summaries if "failed" not in s]
    (out / "large_rotation.json").write_text(json.dumps({**meta, "records": summaries, "frames": frames}, indent=1))
    text = markdown(meta, ok)
    failed = [s for s in summaries if "failed" in s]
    if failed:
        text += "\nFailed: " + "; ".join(f"{s['scene']} {s['variant']}: {s['failed']}" for s in failed) + "\n"
    (out / "large_rotation.md").write_text(text)
    if not args.no_render:
        try:
            for path in render(out, meshes, snapshots, args.variants):
                print(f"wrote {path} ({path.stat().st_size // 1024} kB)")
        except ImportError as exc:
            print(f"no pictures: {exc}", file=sys.stderr)
    print(f"wrote {out / 'large_rotation.md'} and {out / 'large_rotation.json'}")
    return summaries


if __name__ == "__main__":
    main()
