"""Control: find the forces on a soft beam's free end that bring it to a target and stop it there.

    python examples/reach_target.py [--steps 40] [--iterations 40] [--model corotational]
                                    [--target 0.7 0.3 0.2] [--device cpu|cuda]

A beam clamped at one end hangs under gravity. The control is one force per step on its free
end (spread over the end's nodes: ``[steps, 3]`` unknowns); the loss asks the end's centre to be
at ``--target`` at the last step, at rest, with a small penalty on the forces. L-BFGS minimises it
through ``tm.rollout(forces=...)``, whose gradient comes from one adjoint solve per step. Prints
the end's distance to the target and its speed before and after, and the wall time.
"""
import argparse
import time

import torch

import tensormass_torch as tm


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs=3, default=[8, 2, 2])
    parser.add_argument("--steps", type=int, default=40)
    parser.add_argument("--iterations", type=int, default=40, help="L-BFGS iterations (at most)")
    parser.add_argument("--model", default="corotational", choices=["corotational", "hooke", "stvk"])
    parser.add_argument("--target", type=float, nargs=3, default=[0.7, 0.3, 0.3])
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    nx, ny, nz = args.cells
    mesh = tm.beam_mesh(nx, ny, nz, size=(1.0, ny / nx, nz / nx), dtype=torch.float64, device=args.device)
    body = tm.Body(mesh, tm.Material(young=2e5, poisson=0.3, density=1000.0, model=args.model),
                   fixed=mesh.vertices[:, 0] == 0)
    sim = tm.Simulator([body], dt=0.02, rayleigh_mass=0.2, cg_tol=1e-10)
    end = mesh.vertices[:, 0] >= 1.0 - 1e-9
    target = torch.tensor(args.target, dtype=torch.float64, device=args.device)
    weight = float(sim.model.lumped_mass().sum()) * 9.81  # the beam's weight: the forces' scale
    control = torch.zeros(args.steps, 3, dtype=torch.float64, device=args.device, requires_grad=True)
    spread = end.to(torch.float64)[:, None] / int(end.sum())  # [V, 1]

    def outcome(control):
        forces = weight * control[:, None, :] * spread  # [T, V, 3]
        run = tm.rollout(sim, args.steps, forces=forces, frames=[args.steps])
        centre, speed = run.x[-1][end].mean(0), run.v[-1][end].mean(0)
        return centre, speed

    def loss_of(control):
        centre, speed = outcome(control)
        return ((centre - target).square().sum() + 0.05 * speed.square().sum()
                + 1e-5 * control.square().sum())

    with torch.no_grad():
        centre0, speed0 = outcome(control)
    optimizer = torch.optim.LBFGS([control], max_iter=args.iterations, line_search_fn="strong_wolfe")
    rollouts = []

    def closure():
        optimizer.zero_grad()
        loss = loss_of(control)
        loss.backward()
        rollouts.append(float(loss.detach()))
        return loss

    start = time.perf_counter()
    optimizer.step(closure)
    wall = time.perf_counter() - start
    with torch.no_grad():
        centre, speed = outcome(control)
    before = float((centre0 - target).norm()), float(speed0.norm())
    after = float((centre - target).norm()), float(speed.norm())
    print(f"{args.model}, {mesh.num_elements} elements, {args.steps} steps, {3 * args.steps} unknowns: "
          f"{len(rollouts)} rollouts and their gradients in {wall:.1f} s")
    print(f"end to target: {before[0]:.4f} m -> {after[0]:.2e} m; end speed: {before[1]:.3f} -> {after[1]:.2e} m/s; "
          f"largest force {float(control.detach().norm(dim=1).max()):.2f} x the beam's weight")
    return {"distance": (before[0], after[0]), "speed": (before[1], after[1]), "rollouts": len(rollouts),
            "wall_s": wall}


if __name__ == "__main__":
    main()
