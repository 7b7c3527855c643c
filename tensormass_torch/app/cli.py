"""The ``tensormass`` command line (also ``python -m tensormass_torch``).

    tensormass run SCENE         run a built-in scene or a .toml scene file; .vtu frames + .pvd series
    tensormass view SCENE        run a scene live in the browser: watch, poke and cut it (viser)
    tensormass bench [SCENE]     steps/s of one scene on one device (the full suite: benchmarks/)
    tensormass convert IN OUT    convert a mesh file between meshio formats
    tensormass info              backends, devices and build, as JSON

Exit status: 0 on success, 2 for a usage error (bad flags, unknown scene name, bad
``TENSORMASS_BACKEND``), 1 when the work itself fails (a bad scene file, a missing or broken
mesh, a failed solve). Errors are one line on stderr: ``tensormass: error: ...``.
"""
from __future__ import annotations

import argparse
import inspect
import json
import sys
import time
from pathlib import Path

PROG = "tensormass"


class UsageError(Exception):
    """A command line that asks for something that does not exist (exit status 2)."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line, ``tensormass: error: ...`` (exit status 2),
    as every other error of the command line; ``--help`` still prints the usage."""

    def error(self, message):
        command = self.prog.split(" ", 1)[1] + ": " if " " in self.prog else ""
        self.exit(2, f"{PROG}: error: {command}{message} (see {self.prog} --help)\n")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value}")
    return value


# ---------------------------------------------------------------------------------------------
# Scenes: a built-in name or a TOML file
# ---------------------------------------------------------------------------------------------


def _is_scene_file(scene: str) -> bool:
    return scene.endswith(".toml") or Path(scene).is_file()


def _check_device(device: str):
    import torch

    from ..errors import SceneError

    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError):
        raise UsageError(f"--device: not a torch device: {device!r}") from None
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise SceneError(f"--device {device}: torch sees no CUDA device")


def _load(args):
    """The scene named by ``args.scene`` with the flags' overrides -> ``scenes.Scene``."""
    import torch

    from ..sim.builtin import SCENES

    if args.device is not None:
        _check_device(args.device)
    if _is_scene_file(args.scene):
        from ..sim.scene_file import load_scene

        if args.resolution is not None:
            raise UsageError("--resolution applies to built-in scenes; a scene file sets its mesh itself")
        return load_scene(args.scene, device=args.device, dtype=args.dtype, model=args.model)
    if args.scene not in SCENES:
        raise UsageError(f"unknown scene {args.scene!r}: built-in scenes are {', '.join(sorted(SCENES))}, "
                         "or give a .toml scene file")
    kwargs = {"device": args.device or "cpu",
              "dtype": {"float32": torch.float32, "float64": torch.float64}[args.dtype or "float32"]}
    if args.model:
        kwargs["model"] = args.model
    if args.resolution is not None:
        if "resolution" not in inspect.signature(SCENES[args.scene]).parameters:
            raise UsageError(f"--resolution: the scene {args.scene!r} has no resolution")
        kwargs["resolution"] = args.resolution
    return SCENES[args.scene](**kwargs)


def _add_scene_arguments(parser, models):
    parser.add_argument("--device", default=None,
                        help="torch device, e.g. cpu, cuda, cuda:1 (default: the scene file's, else cpu)")
    parser.add_argument("--dtype", default=None, choices=["float32", "float64"],
                        help="precision (default: the scene file's, else float32)")
    parser.add_argument("--model", default=None, choices=list(models), help="material model of every body")
    parser.add_argument("--resolution", type=_positive_int, default=None,
                        help="mesh resolution of a built-in scene (cantilever, twist, spin, paper_beam)")


# ---------------------------------------------------------------------------------------------
# Commands
# ---------------------------------------------------------------------------------------------


def _cmd_info(args):
    import platform

    import torch

    from .. import __version__
    from .._backend import backend_info, load_extension

    info = backend_info()
    devices = [{"index": i, "name": torch.cuda.get_device_name(i),
                "capability": ".".join(map(str, torch.cuda.get_device_capability(i))),
                "memory_gib": round(torch.cuda.get_device_properties(i).total_memory / 2**30, 1)}
               for i in range(torch.cuda.device_count())] if torch.cuda.is_available() else []
    module = load_extension() if info["mode"] != "torch" else None
    info.update({
        "version": __version__,
        "python": platform.python_version(),
        "cuda_devices": devices,
        "build": {
            "extension": getattr(module, "__file__", None),
            "extension_cuda": bool(module.has_cuda()) if module is not None else False,
            "torch_cuda": torch.version.cuda,
            "openmp": torch.backends.openmp.is_available(),
            "cpu_threads": torch.get_num_threads(),
        },
    })
    print(json.dumps(info, indent=2))
    return 0


def _cmd_run(args):
    from ..sim import distributed
    from ..sim.output import FrameWriter
    from .progress import Progress
    from .render import FrameRenderer

    if (args.png or args.gif) and not args.out:
        raise UsageError("--png and --gif need --out (the folder the pictures go to)")
    if distributed.launched():
        return _run_distributed(args)
    # Everything that can fail on bad input happens before the first file is written.
    scene = _load(args)
    sim = scene.simulator
    steps = scene.steps if args.steps is None else args.steps
    every = scene.output_every if args.every is None else args.every
    render_options = getattr(scene, "render", {}) or {}
    png = args.png or render_options.get("png", False)
    gif = args.gif or render_options.get("gif", False)
    writer = renderer = None
    if args.out:
        if png or gif:
            renderer = FrameRenderer(args.out, scene.name, png=png, gif=gif,
                                     window_size=render_options.get("window_size", (800, 600)))
        writer = FrameWriter(args.out, scene.name)
    say = (lambda *a: None) if args.quiet else (lambda *a: print(*a, file=sys.stderr, flush=True))
    say(f"{scene.description}; {steps} steps on {sim.device} ({str(sim.dtype).replace('torch.', '')})")
    progress = None if args.quiet else Progress(steps, label=scene.name)

    def write_frame():
        if writer:
            writer.write(sim)
        if renderer:
            renderer.write(sim)

    write_frame()
    stepping = 0.0  # wall time in sim.step alone: the rate shown leaves frame output out
    for done in range(1, steps + 1):
        start = time.perf_counter()
        sim.step(1)
        stepping += time.perf_counter() - start
        if done % every == 0 or done == steps:
            write_frame()
        if progress:
            progress.update(done, sim, stepping)
    if progress:
        progress.finish(steps, sim, stepping)
    if renderer:
        renderer.close()
    if writer:
        say(f"wrote {writer.frame} frames to {Path(args.out) / (scene.name + '.pvd')}")
    if renderer and renderer.files:
        say(f"rendered {len(renderer.files)} picture(s) to {args.out}")
    return 0


def _cmd_view(args):
    from .viewer import Viewer

    if args.gif and not args.record:
        raise UsageError("--gif needs --record (the folder the GIF goes to)")
    scene = _load(args)
    viewer = Viewer(scene, host=args.host, port=args.port, coloring=args.coloring, record=args.record,
                    gif=args.gif, playing=not args.paused, steps=args.steps)
    if args.exit_on_close:
        viewer.exit_on_close()
    print(f"{PROG}: viewing {viewer.name} at {viewer.url} (Ctrl-C to stop)", file=sys.stderr, flush=True)
    viewer.wait_closed()
    return 0


def _run_distributed(args):
    """``tensormass run`` under ``torchrun``: this rank's share of the scene's bodies
    (``sim.distributed``), its frames written by it, the series by rank 0."""
    import torch.distributed as dist

    from ..sim import distributed
    from ..sim.output import FrameWriter

    if args.png or args.gif:
        raise UsageError("--png and --gif render one process's frames: run without torchrun for pictures")
    if args.device is None and _is_scene_file(args.scene):
        from ..sim.scene_file import scene_device

        # a file's CUDA device is a GPU a rank (cuda:LOCAL_RANK, NCCL), as --device cuda is
        args.device = scene_device(args.scene)
    device = distributed.init(args.device)
    if args.device is not None:
        args.device = str(device)
    try:
        if _is_scene_file(args.scene):
            from ..sim.scene_file import load_scene, scene_split

            if (args.split or scene_split(args.scene)) == "mesh":
                return _run_partitioned(args)

            def load(select):
                return load_scene(args.scene, device=args.device, dtype=args.dtype, model=args.model, select=select)
        elif args.split == "mesh":
            raise UsageError("--split mesh takes a scene file (its [distributed] table), not a built-in scene")
        else:
            def load(select):
                return distributed.select_bodies(_load(args), select)
        share = distributed.BatchShare(load)
        scene, rank = share.scene, share.rank
        steps = scene.steps if args.steps is None else args.steps
        every = scene.output_every if args.every is None else args.every
        writer = FrameWriter(args.out, scene.name, series=rank == 0) if args.out else None
        say = (lambda *a: None) if args.quiet or rank else (lambda *a: print(*a, file=sys.stderr, flush=True))
        say(f"{scene.description}; {steps} steps over {share.world} processes")

        series = []  # rank 0: every rank's frames so far

        def write_frame():
            entries = distributed.collectively(
                lambda: writer.write(scene.simulator, share.body_ids) if scene.simulator is not None else [],
                "writing a frame")
            gathered = [None] * share.world
            dist.all_gather_object(gathered, entries)
            if rank == 0:
                series.extend(e for part in gathered for e in part)
                writer.write_series(series)

        if writer:
            write_frame()
        for done in range(1, steps + 1):
            share.step(1)
            if writer and (done % every == 0 or done == steps):
                write_frame()
        if writer:
            say(f"wrote {writer.frame} frames to {Path(args.out) / (scene.name + '.pvd')}")
        return 0
    finally:
        dist.destroy_process_group()


def _run_partitioned(args):
    """``tensormass run`` under ``torchrun`` with the scene's one body's mesh partitioned over the
    processes (``PartitionedSimulator``): every rank steps its part; each frame is gathered on
    every rank and written by rank 0."""
    import torch.distributed as dist

    from ..sim import distributed
    from ..sim.output import FrameWriter
    from ..sim.scene_file import load_scene

    scene = distributed.collectively(lambda: load_scene(args.scene, device=args.device, dtype=args.dtype,
                                                        model=args.model, split="mesh"), "loading the scene")
    sim, rank = scene.simulator, dist.get_rank()
    steps = scene.steps if args.steps is None else args.steps
    every = scene.output_every if args.every is None else args.every
    writer = FrameWriter(args.out, scene.name) if args.out and rank == 0 else None
    say = (lambda *a: None) if args.quiet or rank else (lambda *a: print(*a, file=sys.stderr, flush=True))
    say(f"{scene.description}; {steps} steps")

    def write_frame():
        frame = sim.snapshot()  # (every rank: the gather is collective)
        # (rank 0 writes; a failed write stops every rank rather than leaving them waiting)
        distributed.collectively(lambda: writer.write(frame) if writer else None, "writing a frame")

    try:
        if args.out:
            write_frame()
        for done in range(1, steps + 1):
            sim.step(1)  # (a failed solve raises on every rank alike: the CG's scalars are all-reduced)
            if args.out and (done % every == 0 or done == steps):
                write_frame()
    finally:
        sim.close()  # (its captured graphs go before the process group does)
    if writer:
        say(f"wrote {writer.frame} frames to {Path(args.out) / (scene.name + '.pvd')}")
    return 0


def _synchronize(device):
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _cmd_bench(args):
    import torch

    scene = _load(args)
    sim = scene.simulator
    sim.step(args.warmup)
    _synchronize(sim.device)
    iterations = torch.zeros((), dtype=torch.float64, device=sim.device)
    start = time.perf_counter()
    for _ in range(args.steps):
        report = sim.step(1)
        # Summed on the device: reading it every step would synchronise every step.
        iterations += report.cg_iterations.max()
    _synchronize(sim.device)
    elapsed = time.perf_counter() - start
    elements = sum(b.mesh.num_elements for b in sim.bodies)
    result = {
        "scene": scene.name, "device": str(sim.device), "dtype": str(sim.dtype).replace("torch.", ""),
        "models": sorted({b.material.model for b in sim.bodies}), "bodies": sim.num_bodies,
        "elements": elements, "steps": args.steps, "seconds": elapsed,
        "steps_per_s": args.steps / elapsed, "ms_per_step": 1e3 * elapsed / args.steps,
        "cg_iterations_per_step": float(iterations) / args.steps,
    }
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(f"{result['scene']} ({', '.join(result['models'])}, {sim.num_bodies} bodies, {elements} elements) "
              f"on {result['device']} {result['dtype']}: {args.steps} steps in {elapsed:.3f} s = "
              f"{result['steps_per_s']:.1f} steps/s ({result['ms_per_step']:.2f} ms/step), "
              f"{result['cg_iterations_per_step']:.1f} CG iterations/step")
    return 0


_POINTLESS_FORMATS = (".mesh", ".meshb")  # medit stores no point data


def _cmd_convert(args):
    from ..mesh.io import load_mesh, save_mesh

    if not Path(args.input).is_file():
        raise FileNotFoundError(f"mesh file not found: '{args.input}'")
    mesh, point_data = load_mesh(args.input, orient=args.orient, with_point_data=True)
    if point_data and args.output.lower().endswith(_POINTLESS_FORMATS):
        if not args.quiet:
            print(f"{PROG}: note: {args.output} cannot store point data; dropped {', '.join(point_data)}",
                  file=sys.stderr)
        point_data = {}
    save_mesh(args.output, mesh, **point_data)
    if not args.quiet:
        print(f"{args.input} -> {args.output}: {mesh.num_vertices} vertices, {mesh.num_elements} "
              f"{'tetrahedra' if mesh.kind == 'tet' else 'triangles'}", file=sys.stderr)
    return 0


# ---------------------------------------------------------------------------------------------
# Parser and entry point
# ---------------------------------------------------------------------------------------------


def build_parser():
    """The ``tensormass`` argument parser (sub-commands run, view, bench, convert, info)."""
    from ..physics.materials import MODELS
    from ..sim.builtin import SCENES

    parser = _Parser(
        prog=PROG,
        description="Tensor-Mass soft-body simulation with an implicit solver (PyTorch).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    scene_help = f"a built-in scene ({', '.join(sorted(SCENES))}) or a .toml scene file"

    info = sub.add_parser("info", help="backends, devices and build, as JSON")
    info.set_defaults(func=_cmd_info)

    run = sub.add_parser("run", help="run a scene and write its frames",
                         description="Run a scene; with --out, write one .vtu per body and frame and a "
                                     ".pvd series (ParaView), and optionally PNG frames / a GIF.")
    run.add_argument("scene", metavar="SCENE", help=scene_help)
    run.add_argument("--out", default=None, help="output folder (nothing is written without it)")
    run.add_argument("--steps", type=_positive_int, default=None, help="number of steps (default: the scene's)")
    run.add_argument("--every", type=_positive_int, default=None,
                     help="write a frame every N steps (default: the scene's output_every)")
    run.add_argument("--png", action="store_true", help="also render a PNG per frame (needs pyvista)")
    run.add_argument("--gif", action="store_true", help="also render an animated GIF of the frames (needs pyvista)")
    run.add_argument("--quiet", action="store_true", help="no progress line; print nothing but errors")
    run.add_argument("--split", choices=["bodies", "mesh"], default=None,
                     help="under torchrun: deal the bodies over the processes, or partition the one body's "
                          "mesh over them (default: the scene file's [distributed] split, else bodies)")
    _add_scene_arguments(run, MODELS)
    run.set_defaults(func=_cmd_run)

    view = sub.add_parser("view", help="run a scene live in the browser (viser): watch, poke and cut it",
                          description="Serve a scene live at http://HOST:PORT: its bodies drawn as they move, "
                                      "play / pause / step / reset, dt, the CG budget, the model and Young's "
                                      "modulus as controls, tools moved with gizmos, cuts drawn with two clicks.")
    view.add_argument("scene", metavar="SCENE", help=scene_help)
    view.add_argument("--port", type=int, default=8080, help="port to serve on (default 8080; 0: any free one)")
    view.add_argument("--host", default="127.0.0.1",
                      help="address to serve on (default 127.0.0.1: this machine only; 0.0.0.0: every network)")
    view.add_argument("--coloring", default="displacement", choices=["displacement", "stress", "none"],
                      help="what the bodies' colours show (default displacement)")
    view.add_argument("--record", default=None, help="also write the frames shown to this folder (.vtu + .pvd)")
    view.add_argument("--gif", action="store_true", help="with --record, also an animated GIF (needs pyvista)")
    view.add_argument("--paused", action="store_true", help="start paused")
    view.add_argument("--steps", type=_positive_int, default=None, help="pause after this many steps")
    view.add_argument("--exit-on-close", action="store_true", help="stop once the last page viewing it closes")
    _add_scene_arguments(view, MODELS)
    view.set_defaults(func=_cmd_view)

    bench = sub.add_parser("bench", help="steps/s of one scene (the full benchmark suite is in benchmarks/)",
                           description="Time the implicit steps of one scene on one device and print steps/s. "
                                       "This is a quick check; the full benchmark suite (kernels against the "
                                       "copy floor, layouts, batches) is in the repository's benchmarks/ folder.")
    bench.add_argument("scene", metavar="SCENE", nargs="?", default="cantilever", help=scene_help)
    bench.add_argument("--steps", type=_positive_int, default=20, help="timed steps (default 20)")
    bench.add_argument("--warmup", type=int, default=3, help="untimed steps first (default 3)")
    bench.add_argument("--json", action="store_true", help="print the result as JSON")
    _add_scene_arguments(bench, MODELS)
    bench.set_defaults(func=_cmd_bench)

    convert = sub.add_parser("convert", help="convert a mesh file (meshio formats: .vtu .vtk .msh .mesh ...)")
    convert.add_argument("input", metavar="IN", help="mesh file to read")
    convert.add_argument("output", metavar="OUT", help="mesh file to write; its extension picks the format")
    convert.add_argument("--orient", action="store_true", help="flip inverted elements instead of failing")
    convert.add_argument("--quiet", action="store_true", help="print nothing but errors")
    convert.set_defaults(func=_cmd_convert)
    return parser


def _fail(message: str, status: int) -> int:
    print(f"{PROG}: error: {message}", file=sys.stderr)
    return status


def main(argv=None):
    """Entry point of the ``tensormass`` console script; returns the exit status."""
    args = build_parser().parse_args(argv)  # usage errors: argparse prints them and exits 2
    from .._backend import BackendError
    from ..errors import TensorMassError

    try:
        return args.func(args)
    except (UsageError, BackendError) as exc:  # asked for something that does not exist
        return _fail(str(exc), 2)
    except (TensorMassError, FileNotFoundError, ImportError) as exc:  # the work failed
        return _fail(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, 1)
    except KeyboardInterrupt:
        return _fail("interrupted", 130)
    except BrokenPipeError:  # e.g. `tensormass info | head`
        sys.stderr.close()
        return 0


if __name__ == "__main__":
    sys.exit(main())
