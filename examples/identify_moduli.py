"""System identification: recover the Young's moduli of a beam's regions from its trajectory.

    python examples/identify_moduli.py [--regions 4] [--steps 30] [--model corotational]
                                       [--cells 8 2 2] [--iterations 40] [--device cpu|cuda]
    python examples/identify_moduli.py --per-element ...   # one modulus per element

A clamped beam made of ``--regions`` slabs of different stiffness sags under gravity while a load
lifts and pushes its free end; its node positions over ``--steps`` steps are the observation.
Starting from a uniform guess, L-BFGS fits the log-moduli to the observation through
``tm.rollout``: the gradient of the trajectory misfit with respect to every modulus comes from
one adjoint solve per step (``solver.adjoint``). Prints each region's recovered modulus against
the truth (per element: the relative error's quantiles over the elements), the final misfit and
the wall time.
"""
import argparse
import math
import time

import torch

import tensormass_torch as tm


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs=3, default=[8, 2, 2], help="hexahedra along x, y, z")
    parser.add_argument("--regions", type=int, default=4, help="slabs along the beam, one modulus each")
    parser.add_argument("--per-element", action="store_true", help="one unknown modulus per element")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--model", default="corotational", choices=["corotational", "hooke", "stvk"])
    parser.add_argument("--iterations", type=int, default=40, help="L-BFGS iterations (at most)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    args = parser.parse_args(argv)
    dtype = getattr(torch, args.dtype)
    nx, ny, nz = args.cells
    length = 1.0
    mesh = tm.beam_mesh(nx, ny, nz, size=(length, length * ny / nx, length * nz / nx), dtype=dtype,
                        device=args.device)
    centroids = mesh.vertices[mesh.elements].mean(1)
    # the truth: a modulus per slab along x (per element: a smooth field varying along x and z)
    slab = torch.clamp((centroids[:, 0] / length * args.regions).long(), max=args.regions - 1)
    truth_regions = torch.tensor([2e5 * (1.0 + 1.5 * ((7 * k) % args.regions) / max(args.regions - 1, 1))
                                  for k in range(args.regions)], dtype=dtype, device=args.device)
    if args.per_element:
        truth = 2e5 * (1.6 + 0.6 * torch.sin(2 * math.pi * centroids[:, 0] / length)
                       * torch.cos(math.pi * centroids[:, 2] / (length * nz / nx)))
    else:
        truth = truth_regions[slab]
    body = tm.Body(mesh, tm.Material(young=truth, poisson=0.3, density=1000.0, model=args.model),
                   fixed=mesh.vertices[:, 0] == 0)
    sim = tm.Simulator([body], dt=0.01, rayleigh_mass=0.5, cg_tol=1e-10 if dtype == torch.float64 else 1e-6)
    # a load on the free end's nodes (up and sideways, as heavy as the beam) strains the slabs near
    # the tip, which the beam's own weight hardly does
    tip = mesh.vertices[:, 0] >= length - 1e-6
    load = torch.zeros_like(sim.x)
    load[tip] = torch.tensor([0.0, 0.5, 1.0], dtype=dtype, device=args.device) * (
        9.81 * float(sim.model.lumped_mass().sum()) / int(tip.sum()))
    with torch.no_grad():
        observed = tm.rollout(sim, args.steps, forces=load).x  # [T + 1, V, 3]
    scale = float((observed[-1] - observed[0]).norm(dim=1).max())  # the tip's sag

    unknowns = mesh.num_elements if args.per_element else args.regions
    log_young = torch.full((unknowns,), math.log(3e5), dtype=dtype, device=args.device, requires_grad=True)

    def young_of(log_young):
        return log_young.exp() if args.per_element else log_young.exp()[slab]

    def misfit():
        run = tm.rollout(sim, args.steps, young=young_of(log_young), forces=load)
        return ((run.x - observed) / scale).square().sum(-1).mean()

    optimizer = torch.optim.LBFGS([log_young], lr=1.0, max_iter=args.iterations, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-12, tolerance_change=1e-14)
    evaluations = []

    def closure():
        optimizer.zero_grad()
        loss = misfit()
        loss.backward()
        evaluations.append(float(loss.detach()))
        return loss

    start = time.perf_counter()
    optimizer.step(closure)
    wall = time.perf_counter() - start
    recovered = young_of(log_young.detach())
    relative = (recovered - truth).abs() / truth
    print(f"{args.model}, {mesh.num_elements} elements, {args.steps} steps, {unknowns} unknown moduli: "
          f"{len(evaluations)} rollouts and their gradients in {wall:.1f} s; misfit {evaluations[0]:.3e} -> "
          f"{evaluations[-1]:.3e}")
    result = {"evaluations": len(evaluations), "wall_s": wall, "misfit": evaluations[-1],
              "first_misfit": evaluations[0]}
    if args.per_element:
        q = torch.quantile(relative.double().cpu(), torch.tensor([0.5, 0.9, 1.0], dtype=torch.float64))
        print(f"relative error over the elements: median {q[0]:.2e}, 90 % {q[1]:.2e}, max {q[2]:.2e}")
        result["relative_error_quantiles"] = q.tolist()
    else:
        found = log_young.detach().exp()
        print(f"{'region':>6} {'truth E':>12} {'recovered E':>12} {'error':>9}")
        for k in range(args.regions):
            err = abs(float(found[k]) / float(truth_regions[k]) - 1)
            print(f"{k:6d} {float(truth_regions[k]):12.5g} {float(found[k]):12.5g} {err:9.2e}")
        result["recovered"] = found.tolist()
        result["truth"] = truth_regions.tolist()
    return result


if __name__ == "__main__":
    main()
