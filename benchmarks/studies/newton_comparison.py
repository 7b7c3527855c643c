"""The strongest peer side by side: NVIDIA Newton's VBD solver and tensormass_torch on
the same clamped beams, in one process, on one device: steps/s against the error of the tip's
trajectory over ``--seconds`` of simulated time, each engine against a converged reference of its
own model.

    python benchmarks/studies/newton_comparison.py --device cuda --out DIR
    python benchmarks/studies/newton_comparison.py --quick --device cpu --out DIR     # seconds

Scenes (``--scenes``): SOFA's beam (101,250 tets) and the paper's beam (307,200 tets), clamped at
x = 0, under gravity (-z for both engines), no floor; the same mesh, density, Young's modulus
and Poisson ratio in both engines. Models: ours hooke, corotational and stvk (``--models``); Newton's neo-Hookean (VBD's
tetrahedra), whose Lame parameters are the same E and nu's. At small strain all of them are
linear elasticity; their references differ by the models' nonlinearity only.

Budgets: ours a fixed number of CG iterations a step (``--cg-budgets``, SOFA's way: tol 0), and a
converged step (``converged``: relative residual 1e-6); Newton's VBD iterations a step
(``--vbd-budgets``). Reference of each engine: ours the converged step at dt / 4, Newton's
``--vbd-reference`` iterations at dt / 4. Error: the RMS over the run of the tip's displacement
(mean over the tip face's nodes) against the reference's at the same times, divided by the
reference's largest tip displacement. "Solver error": the same against the engine's converged
run at the same dt (what the budget costs, apart from the time step's error). Time: steps/s
over the run, after a warm-up step (CUDA: ours chained captured steps; Newton's step captured in
a CUDA graph as its examples do).

``--stable-dts``: for each engine's cheapest budget, the largest dt of the list whose run stays
finite and within 10x the reference's tip displacement.

Newton is not a dependency: without ``newton`` and ``warp`` importable its rows are skipped with
one line saying so. Writes newton_comparison.md / .json (and .png with matplotlib).
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the shared common
import common
import numpy as np
import torch
from common import Results, metadata, record

import tensormass_torch as tm
from tensormass_torch.sim.builtin import sofa_beam

COLUMNS = [("scene", "scene", None), ("engine", "engine", None), ("model", "model", None),
           ("budget", "budget", None), ("dt", "dt", ".4g"), ("steps_per_s", "steps/s", ".1f"),
           ("tip_error", "tip error", ".2e"), ("solver_error", "solver error", ".2e"),
           ("max_tip", "max tip disp. (m)", ".3e"), ("elements", "elements", None)]


def scene_geometry(scene: str, elements: int):
    """(vertices [V, 3] float64, tets [E, 4], fixed [V] bool, tip [V] bool, material dict, dt)."""
    if scene == "sofa_beam":
        sim = sofa_beam(model="hooke", device="cpu", dtype=torch.float64, scale=1 if elements >= 100_000 else 5)
        body = sim.simulator.bodies[0]
        mat = body.material
        vertices, tets = body.mesh.vertices.double(), body.mesh.elements.long()
        fixed = body.fixed.clone()
        dt = float(sim.simulator.options.dt)
    else:
        mesh = tm.beam_mesh(*common.tet_dims(elements), size=common.PAPER_SIZE, dtype=torch.float64)
        vertices, tets = mesh.vertices, mesh.elements.long()
        fixed = vertices[:, 0] <= 1e-9
        mat = tm.Material(young=1e5, poisson=0.3, density=1000.0)
        dt = 0.01
    length = float(vertices[:, 0].max())
    tip = vertices[:, 0] >= length - 1e-9
    return vertices, tets, fixed, tip, dict(young=float(mat.young), poisson=float(mat.poisson),
                                            density=float(mat.density)), dt


# ------------------------------------------------------------------------------------ ours


def ours(geometry, model: str, budget, dt: float, seconds: float, device, dtype):
    """Tip z displacement at every step ``[n]`` (numpy) and steps/s."""
    vertices, tets, fixed, tip, material, _ = geometry
    mesh = tm.TetMesh(vertices.to(dtype), tets)
    options = (dict(cg_tol=1e-6, cg_max_iter=None, require_convergence=True) if budget == "converged"
               else dict(cg_tol=0.0, cg_max_iter=int(budget), require_convergence=False, check_every=1000))
    sim = tm.Simulator([tm.Body(mesh, tm.Material(model=model, **material), fixed=fixed)], dt=dt,
                       gravity=(0.0, 0.0, -9.81), device=device, dtype=dtype, **options)
    tip_rows = tip.nonzero().flatten().to(sim.device)
    rest_z = sim.x[tip_rows, 2].mean()
    steps = max(1, int(round(seconds / dt)))
    start_x, start_v = sim.x.clone(), sim.v.clone()
    sim.step(1)  # set-up and captures off the clock
    sim.x, sim.v = start_x.clone(), start_v.clone()
    trace = torch.empty(steps, dtype=torch.float64, device=sim.device)
    common.sync(sim.device)
    start = time.perf_counter()
    chunk = 1 if device.type != "cuda" else 16
    done = 0
    while done < steps:
        n = min(chunk, steps - done)
        sim.step(n)
        if chunk == 1:
            trace[done] = sim.x[tip_rows, 2].mean() - rest_z
        done += n
    common.sync(sim.device)
    elapsed = time.perf_counter() - start
    # (chained steps are timed without samples: the trajectory comes from a per-step run, untimed)
    if chunk > 1:
        sim.x, sim.v = start_x.clone(), start_v.clone()
        for i in range(steps):
            sim.step(1)
            trace[i] = sim.x[tip_rows, 2].mean() - rest_z
    return trace.cpu().numpy(), steps / elapsed


# ------------------------------------------------------------------------------------ Newton


_NEWTON_MODELS = {}  # (geometry, device) -> Newton's model of the last scene


def newton_available():
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except ImportError as exc:
        return f"newton or warp is not installed ({exc}): its rows are skipped"
    return None


def newton_model(geometry, wp_device: str, coloring: Path | None = None):
    """Newton's model of the beam (built once a scene and device: the builder's Python loops are
    slow); ``coloring``: as :func:`newton_run`."""
    import newton
    import warp as wp

    vertices, tets, fixed, _, material, _ = geometry
    young, poisson = material["young"], material["poisson"]
    mu = young / (2.0 * (1.0 + poisson))
    lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    key = (id(geometry), wp_device)
    if key not in _NEWTON_MODELS:
        _NEWTON_MODELS.clear()
        builder = newton.ModelBuilder(gravity=(0.0, 0.0, -9.81))
        builder.add_soft_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0,
                              vel=wp.vec3(0.0, 0.0, 0.0), vertices=[wp.vec3(*v) for v in vertices.tolist()],
                              indices=tets.reshape(-1).tolist(), density=material["density"], k_mu=mu,
                              k_lambda=lam, k_damp=0.0, add_surface_mesh_edges=False)
        for i in fixed.nonzero().flatten().tolist():
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
        _NEWTON_MODELS[key] = builder.finalize(device=wp_device)
    return _NEWTON_MODELS[key]


def newton_run(geometry, iterations: int, dt: float, seconds: float, device, coloring: Path | None = None):
    """Newton's VBD on the same mesh (neo-Hookean, the same E, nu, density): tip z displacement at
    every step ``[n]`` and steps/s. ``coloring``: a ``.npz`` of the particles' colour groups
    (``group_0``, ...) made by Newton's own ``ModelBuilder.color`` on another machine, read where
    it exists and written where it does not (Newton colours on the CPU, whose JIT library,
    ``warp-clang.so``, a GPU machine need not have)."""
    import newton
    import warp as wp

    vertices, tets, fixed, tip, material, _ = geometry
    wp_device = "cpu" if device.type == "cpu" else f"cuda:{device.index or 0}"
    model = newton_model(geometry, wp_device, coloring)
    solver = newton.solvers.SolverVBD(model, iterations=int(iterations), particle_enable_self_contact=False)
    states = [model.state(), model.state()]
    control = model.control()
    tip_rows = wp.array(tip.nonzero().flatten().numpy().astype(np.int32), dtype=wp.int32, device=wp_device)
    steps = max(1, int(round(seconds / dt)))
    rest_z = float(vertices[tip, 2].mean())

    def one_step():
        states[0].clear_forces()
        solver.step(states[0], states[1], control, None, dt)
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

    reset()
    wp.synchronize_device(wp_device)
    start = time.perf_counter()
    for _ in range(steps // 2):
        if graph is not None:
            wp.capture_launch(graph)
        else:
            two_steps()
    if steps % 2:
        one_step()
    wp.synchronize_device(wp_device)
    elapsed = time.perf_counter() - start
    reset()
    trace = np.empty(steps)
    rows = tip_rows.numpy()
    for i in range(steps):  # untimed: the trajectory, a sample a step
        one_step()
        trace[i] = states[0].particle_q.numpy()[rows, 2].mean() - rest_z
    return trace, steps / elapsed


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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default=common.default_device())
    parser.add_argument("--out", default="benchmarks/results/newton")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--scenes", default=None, help="sofa_beam, paper_beam (comma list)")
    parser.add_argument("--elements", type=int, default=None, help="the paper beam's tets (default 307,200)")
    parser.add_argument("--models", default="hooke,corotational,stvk")
    parser.add_argument("--cg-budgets", default="10,25,50,converged")
    parser.add_argument("--vbd-budgets", default="5,10,20,40")
    parser.add_argument("--vbd-reference", type=int, default=200, help="Newton's reference VBD iterations")
    parser.add_argument("--seconds", type=float, default=None, help="simulated seconds a run")
    parser.add_argument("--stable-dts", default="", help="dts to try for the largest stable one (comma list)")
    parser.add_argument("--make-colorings", action="store_true",
                        help="only build Newton's models of the scenes and write their colourings to --colorings")
    parser.add_argument("--colorings", default=None,
                        help="folder of Newton's particle colourings, <scene>_<nodes>.npz: read where they exist, "
                             "written where not (make them where warp runs on the CPU)")
    args = parser.parse_args(argv)
    common.fill_defaults(args, dict(scenes="sofa_beam,paper_beam", elements=307_200, seconds=1.0),
                         dict(scenes="paper_beam", elements=480, seconds=0.1))
    device = torch.device(args.device)
    dtype = torch.float32
    skip = newton_available()
    if args.make_colorings:
        if skip or args.colorings is None:
            raise SystemExit(skip or "--make-colorings needs --colorings DIR")
        for scene in [s for s in args.scenes.split(",") if s]:
            geometry = scene_geometry(scene, args.elements)
            newton_model(geometry, "cpu", coloring_file(args, scene, geometry))
            print("wrote", coloring_file(args, scene, geometry))
        return
    notes = [f"float32; error: RMS of the tip's z displacement against each engine's own reference over "
             f"{args.seconds:g} s, divided by the reference's largest; references at dt / 4."]
    if skip:
        notes.append(skip)
        print(skip, file=sys.stderr)
    else:
        import newton
        import warp

        notes.append(f"newton {newton.__version__}, warp {warp.__version__}")
    results = Results(args.out, "newton_comparison", "Newton (VBD) and tensormass_torch on the same beams",
                      metadata(device), COLUMNS, notes=notes)
    for scene in [s for s in args.scenes.split(",") if s]:
        geometry = scene_geometry(scene, args.elements)
        dt = geometry[5]
        elements = int(geometry[1].shape[0])
        for model in [m for m in args.models.split(",") if m]:
            reference, _ = ours(geometry, model, "converged", dt / 4, args.seconds, device, dtype)
            same_dt, _ = ours(geometry, model, "converged", dt, args.seconds, device, dtype)
            for budget in [b for b in args.cg_budgets.split(",") if b]:
                try:
                    trace, rate = ours(geometry, model, budget, dt, args.seconds, device, dtype)
                    error, max_tip = trajectory_error(trace, dt, reference, dt / 4)
                    results.add(record(scene=scene, engine="tensormass_torch", model=model, budget=f"CG {budget}",
                                       dt=dt, steps_per_s=rate, tip_error=error,
                                       solver_error=trajectory_error(trace, dt, same_dt, dt)[0], max_tip=max_tip,
                                       elements=elements))
                except Exception as exc:  # noqa: BLE001 (a failed run is a row)
                    results.add(record(scene=scene, engine="tensormass_torch", model=model, budget=f"CG {budget}",
                                       dt=dt, elements=elements, error=common.error_text(exc)))
        if not skip:
            newton_rows(results, scene, geometry, args, device)
        if args.stable_dts:
            stable_dt_rows(results, scene, geometry, args, device, dtype, skip)
    results.finish()


def coloring_file(args, scene, geometry):
    return None if args.colorings is None else Path(args.colorings) / f"{scene}_{geometry[0].shape[0]}.npz"


def newton_rows(results, scene, geometry, args, device):
    """Newton's rows of ``scene``: each VBD budget against its references."""
    dt = geometry[5]
    elements = int(geometry[1].shape[0])
    coloring = coloring_file(args, scene, geometry)
    reference, _ = newton_run(geometry, args.vbd_reference, dt / 4, args.seconds, device, coloring)
    same_dt, _ = newton_run(geometry, args.vbd_reference, dt, args.seconds, device, coloring)
    for budget in [int(b) for b in args.vbd_budgets.split(",") if b]:
        trace, rate = newton_run(geometry, budget, dt, args.seconds, device, coloring)
        error, max_tip = trajectory_error(trace, dt, reference, dt / 4)
        results.add(record(scene=scene, engine="newton", model="neo-Hookean (VBD)", budget=f"VBD {budget}",
                           dt=dt, steps_per_s=rate, tip_error=error,
                           solver_error=trajectory_error(trace, dt, same_dt, dt)[0], max_tip=max_tip,
                           elements=elements))


def stable_dt_rows(results, scene, geometry, args, device, dtype, skip):
    """The largest of ``--stable-dts`` at which each engine's cheapest budget (ours with the first
    model) stays finite and within 10x the converged tip displacement: one row each."""
    dts = sorted(float(d) for d in args.stable_dts.split(",") if d)
    model = [m for m in args.models.split(",") if m][0]
    budget = [b for b in args.cg_budgets.split(",") if b][0]
    vbd = [int(b) for b in args.vbd_budgets.split(",") if b][0]
    reference, _ = ours(geometry, model, "converged", geometry[5], args.seconds, device, dtype)
    bound = 10.0 * float(np.abs(reference).max())
    runs = [("tensormass_torch", model, f"CG {budget}", lambda dt: ours(geometry, model, budget, dt, args.seconds,
                                                                         device, dtype))]
    if not skip:
        runs.append(("newton", "neo-Hookean (VBD)", f"VBD {vbd}",
                     lambda dt: newton_run(geometry, vbd, dt, args.seconds, device,
                                           coloring_file(args, scene, geometry))))
    for engine, name, label, run in runs:
        largest = None
        for dt in dts:
            try:
                trace, _ = run(dt)
            except Exception:  # noqa: BLE001 (a failed step: not stable)
                break
            if not (np.all(np.isfinite(trace)) and np.abs(trace).max() <= bound):
                break
            largest = dt
        results.add(record(scene=scene, engine=engine, model=name, budget=f"{label}: largest stable dt",
                           dt=largest, elements=int(geometry[1].shape[0])))


if __name__ == "__main__":
    main()
