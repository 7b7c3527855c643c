"""Large rotations: linear elasticity (hooke) fails, the corotational model does not.

    python examples/large_rotation.py [--scene twist spin] [--models hooke corotational stvk]
                                      [--resolution 1] [--steps 40] [--dtype float64] [--device cpu]

Two built-in scenes (``tensormass run twist`` / ``tensormass run spin``), each turned through
180 degrees in 1 s:
- twist: a beam clamped at one end while its other end is turned about the beam's axis. The
  exact answer is a twisted bar of unchanged volume whose energy is the torsion energy. hooke
  measures strain in the fixed frame: it does not twist the bar but crushes and inverts the
  elements next to the turned end, at many times the energy.
- spin: a free beam spinning about an axis across it. The exact answer is a rigid rotation.
  hooke sees no strain in a linearised rotation, so its nodes fly off along straight lines: the
  beam shears and grows (volume x (1 + pi^2) at 180 degrees) and turns only atan(pi) = 72 deg.

Prints, per scene and model, the volume change, the smallest element volume ratio and the
number of inverted elements, the energies (each model's own, and a rotation-invariant measure:
the corotational energy of the same positions) and, for the spin, the angle turned.
"""
import argparse
import math
import time

import torch

import tensormass_torch as tm
from tensormass_torch.sim.builtin import spin, twist

#: Variants compared: name -> (Material model, rotation, Newton iterations per step).
VARIANTS = {
    "hooke": ("hooke", "polar", 1),
    "corotational": ("corotational", "polar", 1),
    "corotational-qr": ("corotational", "qr", 1),
    "stvk": ("stvk", "polar", 1),
    "stvk-newton3": ("stvk", "polar", 3),
}
SCENES = {"twist": twist, "spin": spin}
SHEAR_SQUARE_TORSION = 0.1406  # Saint-Venant torsion constant J / a^4 of a square section


def element_volumes(mesh, x: torch.Tensor) -> torch.Tensor:
    """Signed volumes ``[N]`` of the mesh's tets at positions ``x [V, 3]``."""
    return tm.TetMesh(x, mesh.elements, check=False).signed_measures()


def beam_axis_angle(x: torch.Tensor, rest: torch.Tensor) -> float:
    """Angle (rad, in the xy plane) of the vector from the beam's x-min end face to its x-max end
    face at positions ``x [V, 3]`` (faces found on the rest shape ``rest [V, 3]``)."""
    lo = rest[:, 0] <= rest[:, 0].min() + 1e-9
    hi = rest[:, 0] >= rest[:, 0].max() - 1e-9
    d = x[hi].mean(0) - x[lo].mean(0)
    return math.atan2(float(d[1]), float(d[0]))


def torsion_references(mesh, material: tm.Material, angle: float):
    """Torsion energies (J) of the twist scene's beam turned through ``angle`` at its x-max end:
    (this mesh under small-strain torsion, Saint-Venant's bar).

    The mesh value is exact for the discrete bar under linear theory: a static ``hooke`` solve at
    a tiny angle, scaled by angle^2 (the energy is quadratic). Large-twist effects (fibres
    lengthening) add a few percent on top.
    """
    x_rest = mesh.vertices.to(torch.float64)
    mesh64 = tm.TetMesh(x_rest, mesh.elements, check=False)
    hooke = tm.TensorMass(mesh64, tm.Material(material.young, material.poisson, material.density, model="hooke"))
    length = float(x_rest[:, 0].max() - x_rest[:, 0].min())
    side = float(x_rest[:, 1].max() - x_rest[:, 1].min())
    clamped = x_rest[:, 0] <= x_rest[:, 0].min() + 1e-9
    turned = x_rest[:, 0] >= x_rest[:, 0].max() - 1e-9
    small = 1e-3
    lift = torch.zeros_like(x_rest)  # the end turned by a linearised small rotation about x
    lift[turned, 1] = -small * x_rest[turned, 2]
    lift[turned, 2] = small * x_rest[turned, 1]
    # Free nodes balance the force of the lifted end: K (lift + w) = 0 off the constrained nodes.
    w = tm.solve_static(hooke, fixed=clamped | turned, gravity=(0.0, 0.0, 0.0), external=hooke(x_rest + lift),
                        tol=1e-10)
    mesh_energy = float(hooke.energy(x_rest + lift + w)) * (angle / small) ** 2
    shear = float(material.young) / (2.0 * (1.0 + float(material.poisson)))
    saint_venant = shear * SHEAR_SQUARE_TORSION * side ** 4 * angle ** 2 / (2.0 * length)
    return mesh_energy, saint_venant


def run_case(scene_name: str, variant: str, resolution: int = 1, steps: int = 40, duration: float = 1.0,
             dtype=torch.float64, device="cpu", frames: int = 20, angle: float = math.pi):
    """Run one scene with one model variant and measure it.

    Returns ``(summary, records, snapshots)``: ``summary`` a dict of the figures, ``records`` one
    dict per measured frame, ``snapshots`` positions ``[V, 3]`` (CPU float64) of each measured
    frame, the rest shape first.
    """
    model, rotation, newton = VARIANTS[variant]
    scene = SCENES[scene_name](resolution=resolution, model=model, rotation=rotation, device=device, dtype=dtype,
                               angle=angle, steps=steps, dt=duration / steps)
    sim = scene.simulator
    sim.options.newton_iters = newton
    mesh = sim.bodies[0].mesh
    rest = sim.model.rest
    rest_volumes = element_volumes(mesh, rest)
    # A common, rotation-invariant yardstick for every model: the corotational (polar) energy.
    material = sim.bodies[0].material
    invariant = tm.TensorMass(mesh, tm.Material(material.young, material.poisson, material.density,
                                                model="corotational"))
    every = max(1, steps // frames)
    records, snapshots = [], []
    wall, cg_iterations, unwrapped, previous = 0.0, 0, 0.0, None

    def measure():
        nonlocal unwrapped, previous
        x = sim.positions(0)
        volumes = element_volumes(mesh, x)
        record = {
            "step": sim.steps_done, "time": round(sim.time, 9),
            "volume_ratio": float(volumes.sum() / rest_volumes.sum()),
            "min_element_volume_ratio": float((volumes / rest_volumes).min()),
            "inverted": int((volumes <= 0).sum()),
            "kinetic": float(sim.kinetic_energy()[0]),
            "elastic": float(sim.model.energy(x)),
            "elastic_invariant": float(invariant.energy(x)),
        }
        if scene_name == "spin":
            a = beam_axis_angle(x, rest)
            if previous is not None:  # unwrap: the beam turns less than 180 deg between frames
                unwrapped += math.remainder(a - previous, 2 * math.pi)
            previous = a
            record["angle_deg"] = math.degrees(unwrapped)
        records.append(record)
        snapshots.append(x.detach().to("cpu", torch.float64).clone())

    measure()
    while sim.steps_done < steps:
        chunk = min(every, steps - sim.steps_done)
        start = time.perf_counter()
        for _ in range(chunk):
            report = sim.step()
            cg_iterations += int(report.cg_iterations.max())
        if sim.device.type == "cuda":
            torch.cuda.synchronize(sim.device)
        wall += time.perf_counter() - start
        measure()

    first, last = records[0], records[-1]
    summary = {
        "scene": scene_name, "variant": variant, "model": model, "rotation": rotation, "newton_iters": newton,
        "tets": mesh.num_elements, "nodes": mesh.num_vertices, "steps": steps, "dt": duration / steps,
        "dtype": str(dtype).replace("torch.", ""), "device": str(sim.device),
        "volume_change_end_pct": 100.0 * (last["volume_ratio"] - 1.0),
        "volume_change_max_pct": 100.0 * max(abs(r["volume_ratio"] - 1.0) for r in records),
        "min_element_volume_ratio": min(r["min_element_volume_ratio"] for r in records),
        "inverted_max": max(r["inverted"] for r in records),
        "elastic_end": last["elastic"], "elastic_invariant_end": last["elastic_invariant"],
        "kinetic_end": last["kinetic"],
        "cg_iterations": cg_iterations, "wall_s": wall, "steps_per_s": steps / wall if wall > 0 else None,
    }
    if scene_name == "twist":
        mesh_ref, saint_venant = torsion_references(mesh, material, angle)
        summary.update(reference_energy_mesh=mesh_ref, reference_energy_saint_venant=saint_venant,
                       elastic_end_over_reference=last["elastic"] / mesh_ref,
                       elastic_invariant_end_over_reference=last["elastic_invariant"] / mesh_ref)
    else:
        start_energy = first["kinetic"] + first["elastic"]
        summary.update(energy_start=start_energy,
                       energy_drift_pct=100.0 * (last["kinetic"] + last["elastic"] - start_energy) / start_energy,
                       energy_drift_invariant_pct=100.0 * (last["kinetic"] + last["elastic_invariant"] - start_energy)
                       / start_energy,
                       kinetic_change_pct=100.0 * (last["kinetic"] - first["kinetic"]) / first["kinetic"],
                       angle_deg=last["angle_deg"], angle_exact_deg=math.degrees(angle))
    return summary, records, snapshots


def format_summary(s) -> str:
    line = (f"{s['scene']:5s} {s['variant']:16s} volume {s['volume_change_end_pct']:+8.2f}% "
            f"(max |{s['volume_change_max_pct']:.2f}|%), min element ratio {s['min_element_volume_ratio']:+.3f}, "
            f"inverted {s['inverted_max']:3d}, ")
    if s["scene"] == "twist":
        line += (f"energy {s['elastic_end']:9.2f} J (x{s['elastic_end_over_reference']:.2f} of the mesh's torsion "
                 f"energy {s['reference_energy_mesh']:.2f} J), invariant {s['elastic_invariant_end']:9.2f} J")
    else:
        line += (f"turned {s['angle_deg']:6.1f} deg, energy drift {s['energy_drift_pct']:+.2f}% "
                 f"(invariant {s['energy_drift_invariant_pct']:+.2f}%), kinetic {s['kinetic_change_pct']:+.1f}%")
    return line + f"; {s['wall_s']:.1f} s"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", nargs="+", default=["twist", "spin"], choices=sorted(SCENES))
    parser.add_argument("--models", nargs="+", default=["hooke", "corotational"], choices=list(VARIANTS))
    parser.add_argument("--resolution", type=int, default=1, help="cells across the beam's section")
    parser.add_argument("--steps", type=int, default=40, help="steps over the 1 s run")
    parser.add_argument("--dtype", default="float64", choices=["float32", "float64"])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    results = {}
    for scene_name in args.scene:
        for variant in args.models:
            summary, _, _ = run_case(scene_name, variant, args.resolution, args.steps,
                                     dtype=getattr(torch, args.dtype), device=args.device)
            results[(scene_name, variant)] = summary
            print(format_summary(summary), flush=True)
    return results


if __name__ == "__main__":
    main()
