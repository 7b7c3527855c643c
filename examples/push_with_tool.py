"""Control through contact: find the path of a rigid sphere that pushes a soft beam's free end to a
target and holds it there.

    python examples/push_with_tool.py [--steps 30] [--iterations 30] [--model corotational]
                                      [--keys 5] [--depth 0.12] [--device cpu|cuda]

A beam clamped at one end hangs at rest under gravity. A sphere (a penalty tool, ``tm.Sphere``)
starts just above its free end. The control is the sphere's path, its centre at the end of every
step (``tm.rollout(tool_positions=...)``), changed from a first guess at ``--keys`` keyframes
and linearly in between (``[keys, 3]`` unknowns): the loss asks the end's centre to be
``--depth`` lower than where it hangs at the last step, and at rest. The tool can only push,
and the gradient reaches its path only while it touches the beam, so the first guess lowers it
onto the end. L-BFGS minimises the loss; each gradient is one adjoint solve per step. Prints the
end's height off the target and its speed before and after, where the sphere ends, and the wall
time.
"""
import argparse
import time

import torch

import tensormass_torch as tm


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=int, nargs=3, default=[8, 2, 2])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--iterations", type=int, default=30, help="L-BFGS iterations (at most)")
    parser.add_argument("--model", default="corotational", choices=["corotational", "hooke", "stvk"])
    parser.add_argument("--keys", type=int, default=5, help="keyframes of the path's change (the unknowns)")
    parser.add_argument("--depth", type=float, default=0.12, help="how far below its rest sag to push the end")
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    nx, ny, nz = args.cells
    dtype, device = torch.float64, args.device
    mesh = tm.beam_mesh(nx, ny, nz, size=(1.0, ny / nx, nz / nx), dtype=dtype, device=device)
    fixed = mesh.vertices[:, 0] == 0
    body = tm.Body(mesh, tm.Material(young=2e6, poisson=0.3, density=1000.0, model=args.model), fixed=fixed)
    # a node penalty: the sphere must be wide enough not to pass between the end's top nodes
    radius = 0.6 * max(ny / nx, nz / nx)
    sim = tm.Simulator([body], dt=0.02, rayleigh_mass=1.0, cg_tol=1e-10,
                       tools=[tm.Sphere(radius, position=(0.0, 0.0, 10.0), stiffness=2e5)])
    # the beam starts at rest where it hangs (the sphere away), and the sphere just above its end
    sim.x = sim.x + tm.solve_static(sim.model, fixed=fixed, gravity=sim.gravity.tolist())
    end = mesh.vertices[:, 0] >= 1.0 - 1e-9
    target = float(sim.x[end][:, 2].mean()) - args.depth  # the end's centre's height asked for
    start = torch.tensor([1.0 - 0.05, 0.5 * ny / nx, float(sim.x[end][:, 2].max()) + radius + 0.01], dtype=dtype,
                         device=device)
    # first guess: the sphere lowered steadily by the depth asked over the first half, then held
    fraction = torch.clamp(torch.arange(1, args.steps + 1, dtype=dtype, device=device) / (args.steps / 2), max=1.0)
    first = start - (args.depth + 0.02) * fraction[:, None] * torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=device)
    # the unknowns: the path's change at --keys keyframes, linear in between (from none at step 0)
    keys = torch.linspace(0, args.steps, args.keys + 1, dtype=dtype, device=device)[1:]
    step_times = torch.arange(1, args.steps + 1, dtype=dtype, device=device)
    weights = torch.clamp(1 - (step_times[:, None] - keys[None, :]).abs() / (args.steps / args.keys), min=0.0)
    offset = torch.zeros(args.keys, 3, dtype=dtype, device=device, requires_grad=True)

    def path_of(offset):
        return first + weights @ offset  # [steps, 3]

    def outcome(offset):
        run = tm.rollout(sim, args.steps, tool_positions=path_of(offset)[:, None, :], frames=[args.steps])
        return run.x[-1][end][:, 2].mean(), run.v[-1][end].mean(0)

    def loss_of(offset):
        centre, speed = outcome(offset)
        return ((centre - target) ** 2 + 0.05 * speed.square().sum()) / args.depth ** 2

    with torch.no_grad():
        centre0, speed0 = outcome(offset)
    optimizer = torch.optim.LBFGS([offset], max_iter=args.iterations, line_search_fn="strong_wolfe")
    rollouts = []

    def closure():
        optimizer.zero_grad()
        loss = loss_of(offset)
        loss.backward()
        rollouts.append(float(loss.detach()))
        return loss

    started = time.perf_counter()
    optimizer.step(closure)
    wall = time.perf_counter() - started
    with torch.no_grad():
        centre, speed = outcome(offset)
        held, guessed = float(path_of(offset)[-1, 2]), float(first[-1, 2])
    miss0, miss = abs(float(centre0) - target), abs(float(centre) - target)
    print(f"{args.model}, {mesh.num_elements} tets, {args.steps} steps, a sphere of radius {radius:.3g} pushing "
          f"the end {args.depth} m down: {len(rollouts)} rollouts with gradients in {wall:.1f} s")
    print(f"end's height off the target: {miss0:.4f} m -> {miss:.4f} m; its speed {float(speed0.norm()):.4f} -> "
          f"{float(speed.norm()):.4f} m/s; the sphere's centre ends at a height of {held:.3f} m (first guess "
          f"{guessed:.3f}, start {float(start[2]):.3f})")
    return {"miss_before": miss0, "miss_after": miss, "speed_after": float(speed.norm()), "rollouts": len(rollouts),
            "wall_s": wall, "sphere_end": held}


if __name__ == "__main__":
    main()
