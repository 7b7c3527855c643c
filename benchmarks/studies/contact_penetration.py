"""Contact between bodies: two blocks dropped onto each other and onto a floor; the
deepest interpenetration against the contact stiffness and the step, and whether they come to rest.

    python benchmarks/studies/contact_penetration.py [--stiffness 1e4 1e5 1e6] [--dt 0.01 0.005 0.0025]
                                                     [--seconds 0.6] [--rounds R ...] [--device cpu]
                                                     [--dtype float64]
                                                     [--out benchmarks/results/contact] [--quick]

The scene is the test's (tests/physics/test_body_contact.py): two 0.2 x 0.2 x 0.1 m hooke blocks
(E = 1e5 Pa, nu = 0.3, 1000 kg/m^3, 4 x 4 x 2 cells), the upper 2 cm above the lower, a floor
plane of 1e5 N/m, Rayleigh mass damping 1/s. For each (stiffness, dt): the deepest
interpenetration of a surface into the other over the run (``StepReport.contact``, the thickness
0), as metres and as a fraction of the mean edge length, the kinetic energy at the end, the
wall time per step; ``--rounds``: a run for each ``Contact(rounds=...)``. Writes
``contact_penetration.md`` and ``.json`` to ``--out``.
"""
import argparse
import sys
import time
from pathlib import Path
from typing import Optional

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
import common  # noqa: E402

import tensormass_torch as tm  # noqa: E402


def drop(stiffness: float, dt: float, seconds: float, device, dtype, rounds: Optional[int] = None):
    rounds = tm.Contact().rounds if rounds is None else rounds
    material = tm.Material(young=1e5, poisson=0.3, density=1000)
    lower = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), dtype=dtype)
    upper = tm.beam_mesh(4, 4, 2, size=(0.2, 0.2, 0.1), origin=(0.0, 0.0, 0.12), dtype=dtype)
    sim = tm.Simulator([tm.Body(lower, material), tm.Body(upper, material)], dt=dt, device=device,
                       planes=[tm.Plane((0, 0, 1), 0.0, 1e5)], contact=tm.Contact(stiffness=stiffness, rounds=rounds),
                       rayleigh_mass=1.0)
    edges = lower.edges()
    edge = float(torch.linalg.vector_norm(lower.vertices[edges[:, 0]] - lower.vertices[edges[:, 1]], dim=-1).mean())
    steps = max(1, round(seconds / dt))
    deepest = 0.0
    start = time.perf_counter()
    for _ in range(steps):
        report = sim.step()
        deepest = max(deepest, float(report.contact.body_penetration.max()))
    elapsed = time.perf_counter() - start
    return dict(stiffness_n_per_m=stiffness, dt_s=dt, rounds=rounds, steps=steps, max_penetration_m=deepest,
                max_penetration_over_edge=deepest / edge, mean_edge_m=edge,
                kinetic_energy_end_j=float(sim.kinetic_energy().sum()), ms_per_step=1e3 * elapsed / steps)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--stiffness", type=float, nargs="+", default=[1e4, 1e5, 1e6])
    parser.add_argument("--dt", type=float, nargs="+", default=[0.01, 0.005, 0.0025])
    parser.add_argument("--seconds", type=float, default=0.6)
    parser.add_argument("--rounds", type=int, nargs="+", default=[tm.Contact().rounds],
                        help="a run for each Contact(rounds=...)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parent.parent / "results" / "contact"))
    parser.add_argument("--quick", action="store_true", help="one case, a few steps (the tests' run)")
    args = parser.parse_args(argv)
    if args.quick:
        args.stiffness, args.dt, args.seconds = [1e5], [0.01], 0.05
    dtype = getattr(torch, args.dtype)
    meta = common.metadata(args.device, seconds=args.seconds, dtype=args.dtype)
    columns = [("stiffness_n_per_m", "stiffness (N/m)", ".0e"), ("dt_s", "dt (s)", "g"),
               ("rounds", "rounds", None), ("steps", "steps", None),
               ("max_penetration_m", "deepest (m)", ".2e"), ("max_penetration_percent", "/ mean edge (%)", ".3f"),
               ("kinetic_energy_end_j", "kinetic energy at the end (J)", ".2e"), ("ms_per_step", "ms/step", ".1f")]
    results = common.Results(args.out, "contact_penetration", "Two blocks dropped onto each other: deepest "
                             "interpenetration against stiffness and dt", meta, columns,
                             [f"{args.dtype}, {args.seconds} s simulated."])
    for k, dt, rounds in [(k, dt, r) for k in args.stiffness for dt in args.dt for r in args.rounds]:
        row = drop(k, dt, args.seconds, args.device, dtype, rounds)
        row["max_penetration_percent"] = 100 * row["max_penetration_over_edge"]
        results.add(row, echo=False)
    results.finish()
    return results.records


if __name__ == "__main__":
    main()
