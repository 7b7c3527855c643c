"""Identify contact: recover the penalty stiffness and thickness of the contact between two bodies
from the observed trajectory of one dropped onto the other.

    python examples/identify_contact.py [--steps 30] [--iterations 20] [--stiffness 5e3]
                                        [--thickness 4e-3] [--device cpu|cuda]

A soft block falls 1 cm onto a larger one held at its base, touches it and rebounds or settles
(``tm.Contact``: a vertex-triangle penalty k with a contact thickness delta, frictionless). Its
trajectory at the true k and delta is the observation. Starting from a wrong guess, L-BFGS fits
log k and log delta to it through ``tm.rollout(contact_stiffness=..., contact_thickness=...)``:
each gradient is one adjoint solve per step (more where a step's contact set took more), with
the contact pairs each step found held. Prints the recovered values against the truth, the
misfit before and after, and the wall time.
"""
import argparse
import time

import torch

import tensormass_torch as tm


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--iterations", type=int, default=20, help="L-BFGS iterations (at most)")
    parser.add_argument("--stiffness", type=float, default=5e3, help="the true contact stiffness k (N/m)")
    parser.add_argument("--thickness", type=float, default=4e-3, help="the true contact thickness delta (m)")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    dtype, device = torch.float64, args.device
    material = tm.Material(young=5e4, poisson=0.3, density=1000.0, model="corotational")
    lower = tm.beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=dtype)
    upper = tm.beam_mesh(2, 2, 2, size=(0.1, 0.1, 0.1), origin=(0.05, 0.05, 0.11 + args.thickness), dtype=dtype)
    bodies = [tm.Body(lower, material, fixed=lower.vertices[:, 2] == 0), tm.Body(upper, material)]
    sim = tm.Simulator(bodies, dt=0.005, cg_tol=1e-10, rayleigh_mass=0.5, device=device,
                       contact=tm.Contact(stiffness=args.stiffness, thickness=args.thickness))
    rows = slice(sim.ptr[1], sim.ptr[2])  # the falling block's nodes

    def heights(stiffness, thickness):
        run = tm.rollout(sim, args.steps, contact_stiffness=stiffness, contact_thickness=thickness)
        return run.x[:, rows]

    truth = torch.tensor([args.stiffness, args.thickness], dtype=dtype, device=device)
    with torch.no_grad():
        observed = heights(truth[0], truth[1])
    guess = torch.tensor([0.4 * args.stiffness, 0.25 * args.thickness], dtype=dtype, device=device)
    logs = guess.log().clone().requires_grad_(True)
    scale = float(observed.square().mean())

    def misfit():
        values = logs.exp()
        return (heights(values[0], values[1]) - observed).square().mean() / scale

    with torch.no_grad():
        before = float(misfit())
    optimizer = torch.optim.LBFGS([logs], max_iter=args.iterations, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-14, tolerance_change=1e-16)
    evaluations = 0

    def closure():
        nonlocal evaluations
        evaluations += 1
        optimizer.zero_grad()
        loss = misfit()
        loss.backward()
        return loss

    start = time.perf_counter()
    optimizer.step(closure)
    seconds = time.perf_counter() - start
    with torch.no_grad():
        after = float(misfit())
    found = logs.detach().exp()
    print(f"misfit {before:.3e} -> {after:.3e} in {evaluations} rollouts + gradients, {seconds:.1f} s on {device}")
    for name, i, unit in (("stiffness", 0, "N/m"), ("thickness", 1, "m")):
        error = abs(float(found[i]) / float(truth[i]) - 1)
        print(f"  {name}: {float(found[i]):.4g} {unit} (truth {float(truth[i]):.4g}, start {float(guess[i]):.4g}; "
              f"error {error:.1e})")
    return {"recovered": found.tolist(), "truth": truth.tolist(), "misfit": after, "first_misfit": before,
            "seconds": seconds}


if __name__ == "__main__":
    main()
