"""The strongest peer side by side: NVIDIA Newton's VBD solver and tensormass_torch on
the same scenes, in one process, on one device: steps/s against the error of a trajectory over
``--seconds`` of simulated time, each engine against a converged reference of its own model.

    python benchmarks/studies/newton_comparison.py --device cuda --out DIR
    python benchmarks/studies/newton_comparison.py --quick --device cpu --out DIR     # seconds
    python benchmarks/studies/newton_comparison.py --replot --out DIR   # md / png again from the json

Scenes (``--scenes``): SOFA's beam (101,250 tets) and the paper's beam (307,200 tets), clamped at
x = 0, under gravity (-z for both engines), no floor; and ``drop``: ``--bodies`` small boxes
(72 tets each) dropped from 0.3-0.5 m onto a penalty floor z = 0 (1e4 N/m a node in both
engines, frictionless; the bodies are apart and do not meet). The same meshes, density, Young's
modulus and Poisson ratio in both engines. Models: ours hooke, corotational and stvk
(``--models``); Newton's neo-Hookean (VBD's tetrahedra), whose Lame parameters are the same E and
nu's. At small strain all of them are linear elasticity; their references differ by the models'
nonlinearity only.

Budgets: ours a fixed number of CG iterations a step (``--cg-budgets``, SOFA's way: tol 0), and a
converged step (``converged``: relative residual 1e-6), each with the preconditioners of
``--preconditioners``; Newton's VBD iterations a step (``--vbd-budgets``). Reference of each
engine: ours the converged step at dt / 4, Newton's ``--vbd-reference`` iterations at dt / 4.
Trajectory: the mean z displacement of the beam's tip face, or of all the drop's nodes. Error:
its RMS over the run against the reference's at the same times, divided by the reference's
largest. "Solver error": the same against the engine's converged run at the same dt (what the
budget costs, apart from the time step's error). Time: steps/s over whole runs from the start,
repeated until ``--min-seconds`` were timed, after a warm-up (CUDA: ours chained captured steps;
Newton's step captured in a CUDA graph as its examples do).

Ratios (after the table): for each row of one engine, the fastest run of the other that is at
least as accurate (no interpolation between budgets), and ours over Newton's steps/s.

``--stable-dts``: for each engine's cheapest budget, the largest dt of the list whose run stays
finite and within 10x the reference's displacement.

Newton is not a dependency: without ``newton`` and ``warp`` importable its rows are skipped with
one line saying so. Writes newton_comparison.md / .json (and .png with matplotlib).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import numpy as np
import torch
from common import Results, metadata, record

import tensormass_torch as tm
from tensormass_torch.sim.builtin import sofa_beam

COLUMNS = [("scene", "scene", None), ("engine", "engine", None), ("model", "model", None),
           ("budget", "budget", None), ("preconditioner", "precond.", None), ("dt", "dt", ".4g"),
           ("steps_per_s", "steps/s", ".1f"), ("tip_error", "error", ".2e"), ("solver_error", "solver error", ".2e"),
           ("max_tip", "max disp. (m)", ".3e"), ("elements", "elements", None)]
TITLE = "Newton (VBD) and tensormass_torch on the same scenes"
DROP_FLOOR_STIFFNESS = 1e4  # N/m a node: both engines' floor penalty


@dataclass
class Scene:
    """One scene for both engines: ``bodies`` equal bodies, consecutive in ``vertices [V, 3]``
    (float64) and ``tets [E, 4]``; ``fixed [V]`` and ``tracked [V]`` (bool: the nodes whose mean z
    displacement is the trajectory); ``floor``: the floor z = 0's penalty stiffness, or None."""

    name: str
    vertices: torch.Tensor
    tets: torch.Tensor
    fixed: torch.Tensor
    tracked: torch.Tensor
    material: dict
    dt: float
    bodies: int = 1
    floor: Optional[float] = None

    @property
    def elements(self) -> int:
        return int(self.tets.shape[0])


def make_scene(name: str, elements: int, bodies: int) -> Scene:
    if name == "sofa_beam":
        sim = sofa_beam(model="hooke", device="cpu", dtype=torch.float64, scale=1 if elements >= 100_000 else 5)
        body = sim.simulator.bodies[0]
        mat = body.material
        vertices, tets = body.mesh.vertices.double(), body.mesh.elements.long()
        fixed = body.fixed.clone()
        material = dict(young=float(mat.young), poisson=float(mat.poisson), density=float(mat.density))
        dt = float(sim.simulator.options.dt)
    elif name == "paper_beam":
        mesh = tm.beam_mesh(*common.tet_dims(elements), size=common.PAPER_SIZE, dtype=torch.float64)
        vertices, tets = mesh.vertices, mesh.elements.long()
        fixed = vertices[:, 0] <= 1e-9
        material, dt = dict(young=1e5, poisson=0.3, density=1000.0), 0.01
    elif name == "drop":
        box = tm.beam_mesh(3, 2, 2, size=(0.3, 0.2, 0.2), origin=(-0.15, -0.1, 0.0), dtype=torch.float64)
        side = max(1, math.ceil(math.sqrt(bodies)))
        offsets = torch.tensor([[0.5 * (i % side), 0.5 * (i // side), 0.3 + 0.1 * (i % 3)] for i in range(bodies)],
                               dtype=torch.float64)
        vertices = (box.vertices[None] + offsets[:, None]).reshape(-1, 3)
        nodes = box.vertices.shape[0]
        tets = (box.elements.long()[None] + nodes * torch.arange(bodies)[:, None, None]).reshape(-1, 4)
        fixed = torch.zeros(vertices.shape[0], dtype=torch.bool)
        scene = Scene(name, vertices, tets, fixed, torch.ones_like(fixed),
                      dict(young=1e5, poisson=0.3, density=1000.0), 0.01, bodies, DROP_FLOOR_STIFFNESS)
        return scene
    else:
        raise SystemExit(f"unknown scene {name!r}: sofa_beam, paper_beam or drop")
    length = float(vertices[:, 0].max())
    return Scene(name, vertices, tets, fixed, vertices[:, 0] >= length - 1e-9, material, dt)


def timed_runs(run, reset, sync, steps: int, min_seconds: float) -> float:
    """Steps/s of ``run()`` (``steps`` steps from the start): whole runs, each after ``reset()``,
    until ``min_seconds`` were timed (a run of 1 s simulated can be a few ms of GPU time)."""
    runs, elapsed = 0, 0.0
    while runs == 0 or elapsed < min_seconds:
        reset()
        sync()
        start = time.perf_counter()
        run()
        sync()
        elapsed += time.perf_counter() - start
        runs += 1
    return runs * steps / elapsed


# ------------------------------------------------------------------------------------ ours


def ours(scene: Scene, model: str, budget, dt: float, seconds: float, device, dtype, preconditioner: str = "none",
         min_seconds: float = 0.0):
    """The tracked nodes' mean z displacement at every step ``[n]`` (numpy) and steps/s."""
    per_body_nodes = scene.vertices.shape[0] // scene.bodies
    per_body_tets = scene.elements // scene.bodies
    bodies = []
    for b in range(scene.bodies):
        nodes = slice(b * per_body_nodes, (b + 1) * per_body_nodes)
        tets = scene.tets[b * per_body_tets:(b + 1) * per_body_tets] - b * per_body_nodes
        bodies.append(tm.Body(tm.TetMesh(scene.vertices[nodes].to(dtype), tets, check=False),
                              tm.Material(model=model, **scene.material), fixed=scene.fixed[nodes]))
    options = (dict(cg_tol=1e-6, cg_max_iter=None, require_convergence=True) if budget == "converged"
               else dict(cg_tol=0.0, cg_max_iter=int(budget), require_convergence=False, check_every=1000))
    planes = [tm.Plane((0.0, 0.0, 1.0), 0.0, scene.floor)] if scene.floor else None
    sim = tm.Simulator(bodies, dt=dt, gravity=(0.0, 0.0, -9.81), planes=planes, device=device, dtype=dtype,
                       preconditioner=preconditioner, **options)
    rows = scene.tracked.nonzero().flatten().to(sim.device)
    rest_z = sim.x[rows, 2].mean()
    steps = max(1, int(round(seconds / dt)))
    start_x, start_v = sim.x.clone(), sim.v.clone()
    sim.step(1)  # set-up and captures off the clock
    trace = torch.empty(steps, dtype=torch.float64, device=sim.device)
    chunk = 1 if device.type != "cuda" else 16

    def reset():
        sim.x, sim.v = start_x.clone(), start_v.clone()

    def run():
        done = 0
        while done < steps:
            n = min(chunk, steps - done)
            sim.step(n)
            if chunk == 1:
                trace[done] = sim.x[rows, 2].mean() - rest_z
            done += n

    rate = timed_runs(run, reset, lambda: common.sync(sim.device), steps, min_seconds)
    if chunk > 1:  # chained steps are timed without samples: the trajectory comes from a per-step run, untimed
        reset()
        for i in range(steps):
            sim.step(1)
            trace[i] = sim.x[rows, 2].mean() - rest_z
    return trace.cpu().numpy(), rate


# ------------------------------------------------------------------------------------ Newton


_NEWTON_MODELS = {}  # (scene, device) -> Newton's model of the last scene


def newton_available():
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except ImportError as exc:
        return f"newton or warp is not installed ({exc}): its rows are skipped"
    return None


def newton_model(scene: Scene, wp_device: str, coloring: Optional[Path] = None):
    """Newton's model of the scene (built once a scene and device: the builder's Python loops are
    slow); ``coloring``: as :func:`newton_run`."""
    import newton
    import warp as wp

    young, poisson = scene.material["young"], scene.material["poisson"]
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    key = (id(scene), wp_device)
    if key not in _NEWTON_MODELS:
        _NEWTON_MODELS.clear()
        builder = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        if scene.floor:
            builder.add_ground_plane()
        # all bodies as one mesh of disjoint parts: the same particles and tetrahedra as separate meshes.
        # Particle radius 1 mm: Newton's floor contact starts at a particle's radius (10 cm by default).
        builder.add_soft_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0,
                              vel=wp.vec3(0.0, 0.0, 0.0), vertices=[wp.vec3(*v) for v in scene.vertices.tolist()],
                              indices=scene.tets.reshape(-1).tolist(), density=scene.material["density"], k_mu=mu,
                              k_lambda=lam, k_damp=0.0, add_surface_mesh_edges=False, particle_radius=1e-3)
        for i in scene.fixed.nonzero().flatten().tolist():
            builder.particle_mass[i] = 0.0
        if coloring is not None and coloring.exists():
            with np.load(coloring) as groups:
                builder.set_coloring([groups[f"group_{k}"] for k in range(len(groups.files))])
        else:
            builder.color()
            if coloring is not None:
                coloring.parent.mkdir(parents=True, exist_ok=True)
                np.savez(coloring, **{f"group_{k}": np.asarray(g) for k, g in
                                      enumerate(builder.particle_color_groups)})
        model = builder.finalize(device=wp_device)
        if scene.floor:
            model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = float(scene.floor), 0.0, 0.0
        _NEWTON_MODELS[key] = model
    return _NEWTON_MODELS[key]


def newton_run(scene: Scene, iterations: int, dt: float, seconds: float, device, coloring: Optional[Path] = None,
               min_seconds: float = 0.0):
    """Newton's VBD on the same mesh (neo-Hookean, the same E, nu, density): the tracked nodes'
    mean z displacement at every step ``[n]`` and steps/s. ``coloring``: a ``.npz`` of the
    particles' colour groups (``group_0``, ...) made by Newton's own ``ModelBuilder.color``, read
    where it exists and written where it does not (colouring a large mesh is slow)."""
    import newton
    import warp as wp

    wp_device = "cpu" if device.type == "cpu" else f"cuda:{device.index or 0}"
    model = newton_model(scene, wp_device, coloring)
    solver = newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=False)
    states = [model.state(), model.state()]
    control = model.control()
    pipeline = newton.CollisionPipeline(model) if scene.floor else None
    contacts = pipeline.contacts() if pipeline is not None else None
    rows = scene.tracked.nonzero().flatten().numpy()
    steps = max(1, int(round(seconds / dt)))
    rest_z = float(scene.vertices[scene.tracked, 2].mean())

    def one_step():
        states[0].clear_forces()
        if pipeline is not None:
            pipeline.collide(states[0], contacts)
        solver.step(states[0], states[1], control, contacts, dt)
        states[0], states[1] = states[1], states[0]

    # two steps make the state pair return to where it started: capture both
    def two_steps():
        one_step()
        one_step()

    two_steps()  # warm-up: kernels compiled and loaded
    initial_q = wp.clone(model.particle_q)
    graph = None
    if wp_device != "cpu":
        with wp.ScopedCapture(device=wp_device) as capture:
            two_steps()
        graph = capture.graph

    def reset():
        for s in states:
            wp.copy(s.particle_q, initial_q)
            s.particle_qd.zero_()

    def run():
        for _ in range(steps // 2):
            if graph is not None:
                wp.capture_launch(graph)
            else:
                two_steps()
        if steps % 2:
            one_step()

    rate = timed_runs(run, reset, lambda: wp.synchronize_device(wp_device), steps, min_seconds)
    reset()
    trace = np.empty(steps)
    for i in range(steps):  # untimed: the trajectory, a sample a step
        one_step()
        trace[i] = states[0].particle_q.numpy()[rows, 2].mean() - rest_z
    return trace, rate


# ------------------------------------------------------------------------------------ error


def trajectory_error(trace: np.ndarray, dt: float, reference: np.ndarray, ref_dt: float) -> tuple:
    """(RMS of trace - reference at trace's times / max |reference|, max |trace|); inf where the
    run is not finite."""
    if not np.all(np.isfinite(trace)):
        return math.inf, math.inf
    times = dt * np.arange(1, len(trace) + 1)
    ref_times = ref_dt * np.arange(1, len(reference) + 1)
    ref = np.interp(times, ref_times, reference)
    scale = max(float(np.abs(reference).max()), 1e-30)
    return float(np.sqrt(np.mean((trace - ref) ** 2)) / scale), float(np.abs(trace).max())


def _label(r: dict) -> str:
    precond = r.get("preconditioner")
    return f"{r['model']} {r['budget']}" + (f" + {precond}" if precond not in (None, "none") else "")


def ratios(records) -> list:
    """Markdown lines: for each timed row of each engine, the other engine's fastest run at least
    as accurate (none where it reaches no such error), and ours over Newton's steps/s."""
    timed = [r for r in records if r.get("steps_per_s") and r.get("tip_error") is not None
             and math.isfinite(r["tip_error"])]
    lines = ["Ours over Newton's steps/s at equal error: for each run, the other engine's fastest run with an "
             "error at most as large.", "",
             "| scene | run | error | steps/s | other engine's fastest run as accurate | its steps/s | ours / Newton |",
             "|---|---|---|---|---|---|---|"]
    for scene in dict.fromkeys(r["scene"] for r in timed):
        rows = [r for r in timed if r["scene"] == scene]
        for r in sorted(rows, key=lambda r: (r["engine"] != "newton", r["tip_error"])):
            other = [o for o in rows if o["engine"] != r["engine"] and o["tip_error"] <= r["tip_error"]]
            best = max(other, key=lambda o: o["steps_per_s"]) if other else None
            if best is None:
                match, rate, ratio = "none reaches it", "", ("ours only" if r["engine"] != "newton" else "Newton only")
            else:
                ours_rate, newton_rate = ((r, best) if r["engine"] != "newton" else (best, r))
                match, rate = f"{best['engine']} {_label(best)} ({best['tip_error']:.2e})", f"{best['steps_per_s']:.1f}"
                ratio = f"{ours_rate['steps_per_s'] / newton_rate['steps_per_s']:.2f}x"
            lines.append(f"| {scene} | {r['engine']} {_label(r)} | {r['tip_error']:.2e} | {r['steps_per_s']:.1f} | "
                         f"{match} | {rate} | {ratio} |")
    return lines


def draw(records, meta):
    """Error against steps/s, a panel a scene, a line an engine and model (and preconditioner)."""
    timed = [r for r in records if r.get("steps_per_s") and r.get("tip_error") is not None
             and math.isfinite(r["tip_error"]) and r["tip_error"] > 0]
    scenes = list(dict.fromkeys(r["scene"] for r in timed))

    def fig(plt):
        figure, axes = plt.subplots(1, max(1, len(scenes)), figsize=(5.5 * max(1, len(scenes)), 4.5), squeeze=False)
        for ax, scene in zip(axes[0], scenes):
            rows = [r for r in timed if r["scene"] == scene]
            for key in dict.fromkeys((r["engine"], r["model"], r.get("preconditioner")) for r in rows):
                line = sorted((r for r in rows if (r["engine"], r["model"], r.get("preconditioner")) == key),
                              key=lambda r: r["steps_per_s"])
                name = f"{'Newton' if key[0] == 'newton' else 'ours'} {key[1]}" + (
                    f" + {key[2]}" if key[2] not in (None, "none") else "")
                ax.plot([r["steps_per_s"] for r in line], [r["tip_error"] for r in line],
                        "s--" if key[0] == "newton" else "o-", label=name)
                for r in line:
                    ax.annotate(r["budget"].split(" ", 1)[1], (r["steps_per_s"], r["tip_error"]), fontsize=7,
                                textcoords="offset points", xytext=(3, 3))
            ax.set_xscale("log")
            ax.set_yscale("log")
            ax.set_xlabel("steps/s")
            ax.set_ylabel("error against the engine's converged reference")
            ax.set_title(f"{scene} ({rows[0]['elements']:,} tets)")
            ax.grid(True, which="both", alpha=0.3)
            ax.legend(fontsize=7)
        figure.suptitle(common.plot_title(meta, "Error against steps/s: Newton (VBD) and tensormass_torch"))
        figure.tight_layout()
        return figure

    return fig


def finish(results: Results) -> None:
    results.appendix = ratios(results.records)
    if any(r.get("steps_per_s") for r in results.records):
        results.plot(draw(results.records, results.meta))
    results.finish()


def replot(out) -> Results:
    """Rebuild newton_comparison.md / .png from the newton_comparison.json under ``out``."""
    data = json.loads((Path(out) / "newton_comparison.json").read_text())
    results = Results(out, "newton_comparison", TITLE, data["meta"], COLUMNS, notes=data["meta"].get("notes", []))
    results.records = data["records"]
    finish(results)
    return results


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results/newton")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--replot", action="store_true", help="only rebuild md/png from the json under --out")
    parser.add_argument("--scenes", default=None, help="sofa_beam, paper_beam, drop (comma list)")
    parser.add_argument("--elements", type=int, default=None, help="the paper beam's tets (default 307,200)")
    parser.add_argument("--bodies", type=int, default=None, help="the drop's bodies (default 1,000)")
    parser.add_argument("--models", default="hooke,corotational,stvk")
    parser.add_argument("--preconditioners", default="none", help="ours: none, jacobi, multigrid (comma list)")
    parser.add_argument("--cg-budgets", default="10,25,50,converged")
    parser.add_argument("--vbd-budgets", default="5,10,20,40")
    parser.add_argument("--vbd-reference", type=int, default=200, help="Newton's reference VBD iterations")
    parser.add_argument("--seconds", type=float, default=None, help="simulated seconds a run")
    parser.add_argument("--min-seconds", type=float, default=None, help="timed seconds a row at least (whole runs)")
    parser.add_argument("--stable-dts", default="", help="dts to try for the largest stable one (comma list)")
    parser.add_argument("--make-colorings", action="store_true",
                        help="only build Newton's models of the scenes and write their colourings to --colorings")
    parser.add_argument("--colorings", default=None,
                        help="folder of Newton's particle colourings, <scene>_<nodes>.npz: read where they exist, "
                             "written where not")
    args = parser.parse_args(argv)
    if args.replot:
        return replot(args.out)
    common.fill_defaults(args, dict(scenes="sofa_beam,paper_beam,drop", elements=307_200, bodies=1000, seconds=1.0,
                                    min_seconds=0.5),
                         dict(scenes="paper_beam", elements=480, bodies=4, seconds=0.1, min_seconds=0.0))
    device = torch.device(args.device)
    dtype = torch.float32
    skip = newton_available()
    scenes = [s for s in args.scenes.split(",") if s]
    if args.make_colorings:
        if skip or args.colorings is None:
            raise SystemExit(skip or "--make-colorings needs --colorings DIR")
        for name in scenes:
            scene = make_scene(name, args.elements, args.bodies)
            newton_model(scene, "cpu", coloring_file(args, scene))
            print("wrote", coloring_file(args, scene))
        return None
    notes = [f"float32; error: RMS of the tracked displacement (beams: the tip face's mean z; drop: all nodes' "
             f"mean z) against each engine's own reference over {args.seconds:g} s, divided by the reference's "
             f"largest; references at dt / 4."]
    if skip:
        notes.append(skip)
        print(skip, file=sys.stderr)
    else:
        import newton
        import warp

        notes.append(f"newton {newton.__version__}, warp {warp.__version__}")
    meta = metadata(device)
    meta["notes"] = notes
    results = Results(args.out, "newton_comparison", TITLE, meta, COLUMNS, notes=notes)
    preconditioners = [p for p in args.preconditioners.split(",") if p]
    for name in scenes:
        scene = make_scene(name, args.elements, args.bodies)
        dt = scene.dt
        for model in [m for m in args.models.split(",") if m]:
            reference, _ = ours(scene, model, "converged", dt / 4, args.seconds, device, dtype)
            same_dt, _ = ours(scene, model, "converged", dt, args.seconds, device, dtype)
            for preconditioner in preconditioners:
                for budget in [b for b in args.cg_budgets.split(",") if b]:
                    row = dict(scene=name, engine="tensormass_torch", model=model, budget=f"CG {budget}",
                               preconditioner=preconditioner, dt=dt, elements=scene.elements)
                    try:
                        trace, rate = ours(scene, model, budget, dt, args.seconds, device, dtype, preconditioner,
                                           args.min_seconds)
                        error, max_tip = trajectory_error(trace, dt, reference, dt / 4)
                        results.add(record(**row, steps_per_s=rate, tip_error=error, max_tip=max_tip,
                                           solver_error=trajectory_error(trace, dt, same_dt, dt)[0]))
                    except Exception as exc:  # noqa: BLE001 (a failed run is a row)
                        results.add(record(**row, error=common.error_text(exc)))
        if not skip:
            newton_rows(results, scene, args, device)
        if args.stable_dts:
            stable_dt_rows(results, scene, args, device, dtype, skip)
    finish(results)
    return results


def coloring_file(args, scene: Scene):
    return None if args.colorings is None else Path(args.colorings) / f"{scene.name}_{scene.vertices.shape[0]}.npz"


def newton_rows(results, scene: Scene, args, device):
    """Newton's rows of ``scene``: each VBD budget against its references."""
    dt = scene.dt
    coloring = coloring_file(args, scene)
    reference, _ = newton_run(scene, args.vbd_reference, dt / 4, args.seconds, device, coloring)
    same_dt, _ = newton_run(scene, args.vbd_reference, dt, args.seconds, device, coloring)
    for budget in [int(b) for b in args.vbd_budgets.split(",") if b]:
        trace, rate = newton_run(scene, budget, dt, args.seconds, device, coloring, args.min_seconds)
        error, max_tip = trajectory_error(trace, dt, reference, dt / 4)
        results.add(record(scene=scene.name, engine="newton", model="neo-Hookean (VBD)", budget=f"VBD {budget}",
                           dt=dt, steps_per_s=rate, tip_error=error,
                           solver_error=trajectory_error(trace, dt, same_dt, dt)[0], max_tip=max_tip,
                           elements=scene.elements))


def stable_dt_rows(results, scene: Scene, args, device, dtype, skip):
    """The largest of ``--stable-dts`` at which each engine's cheapest budget (ours with the first
    model and preconditioner) stays finite and within 10x the converged displacement: one row each."""
    dts = sorted(float(d) for d in args.stable_dts.split(",") if d)
    model = [m for m in args.models.split(",") if m][0]
    preconditioner = [p for p in args.preconditioners.split(",") if p][0]
    budget = [b for b in args.cg_budgets.split(",") if b][0]
    vbd = [int(b) for b in args.vbd_budgets.split(",") if b][0]
    reference, _ = ours(scene, model, "converged", scene.dt, args.seconds, device, dtype)
    bound = 10.0 * float(np.abs(reference).max())
    runs = [("tensormass_torch", model, f"CG {budget}", preconditioner,
             lambda dt: ours(scene, model, budget, dt, args.seconds, device, dtype, preconditioner))]
    if not skip:
        runs.append(("newton", "neo-Hookean (VBD)", f"VBD {vbd}", None,
                     lambda dt: newton_run(scene, vbd, dt, args.seconds, device, coloring_file(args, scene))))
    for engine, name, label, precond, run in runs:
        largest = None
        for dt in dts:
            try:
                trace, _ = run(dt)
            except Exception:  # noqa: BLE001 (a failed step: not stable)
                break
            if not (np.all(np.isfinite(trace)) and np.abs(trace).max() <= bound):
                break
            largest = dt
        results.add(record(scene=scene.name, engine=engine, model=name, budget=f"{label}: largest stable dt",
                           preconditioner=precond, dt=largest, elements=scene.elements))


if __name__ == "__main__":
    main()
