"""The ``tensormass`` command line (also ``python -m tensormass_torch``).

    tensormass info          backend report (tm.backend_info()) as JSON
    tensormass run SCENE     run a built-in scene, write .vtu frames and a .pvd series
"""
import argparse
import json
import sys


def _cmd_info(args):
    from ._backend import backend_info

    print(json.dumps(backend_info(), indent=2))
    return 0


def _cmd_run(args):
    import time

    import torch

    from .output import FrameWriter
    from .scenes import SCENES

    dtype = {"float32": torch.float32, "float64": torch.float64}[args.dtype]
    kwargs = {"device": args.device, "dtype": dtype}
    if args.model:
        kwargs["model"] = args.model
    scene = SCENES[args.scene](**kwargs)
    sim = scene.simulator
    steps = scene.steps if args.steps is None else args.steps
    every = max(1, scene.output_every if args.every is None else args.every)
    writer = FrameWriter(args.out, scene.name) if args.out else None
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, flush=True))
    say(f"{scene.description}; {steps} steps on {sim.device} ({args.dtype})")
    if writer:
        writer.write(sim)
    start = time.perf_counter()
    done = 0
    while done < steps:
        chunk = min(every, steps - done)
        report = sim.step(chunk)
        done += chunk
        if writer:
            writer.write(sim)
        rate = done / (time.perf_counter() - start)
        cg = report.cg[0]
        say(f"step {done:5d}/{steps}  t = {sim.time:7.3f} s  {rate:8.2f} steps/s  "
            f"CG {int(cg.iterations.max())} it, residual {float(cg.relative_residual.max()):.2e}")
    if writer:
        say(f"wrote {writer.frame} frames to {args.out}/{scene.name}.pvd")
    return 0


def build_parser():
    parser = argparse.ArgumentParser(
        prog="tensormass",
        description="Tensor-Mass soft-body simulation with an implicit solver (PyTorch).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    info = sub.add_parser("info", help="print the backend report (tm.backend_info()) as JSON")
    info.set_defaults(func=_cmd_info)

    from .materials import MODELS
    from .scenes import SCENES

    run = sub.add_parser("run", help="run a built-in scene and write its frames")
    run.add_argument("scene", choices=sorted(SCENES), help="scene name")
    run.add_argument("--out", default=None, help="output folder for .vtu frames and the .pvd series")
    run.add_argument("--steps", type=int, default=None, help="number of steps (default: the scene's)")
    run.add_argument("--every", type=int, default=None, help="write a frame every N steps")
    run.add_argument("--device", default="cpu", help="torch device, e.g. cpu or cuda")
    run.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    run.add_argument("--model", default=None, choices=list(MODELS), help="material model")
    run.add_argument("--quiet", action="store_true", help="print nothing but errors")
    run.set_defaults(func=_cmd_run)
    return parser


def main(argv=None):
    """Entry point of the ``tensormass`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)
    from .errors import TensorMassError

    try:
        return args.func(args)
    except TensorMassError as exc:  # bad input, a bad TENSORMASS_BACKEND value, a failed solve
        print("tensormass: error: %s" % exc, file=sys.stderr)
        return 2
    except BrokenPipeError:  # e.g. `tensormass info | head`
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
