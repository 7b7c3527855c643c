"""A batch of bodies over several processes (sim/distributed.py): `torchrun --nproc-per-node 2
-m tensormass_torch run SCENE` on the CPU (gloo) writes, per body, what one process writes (float64,
1e-12) and one series of all; a step that fails on one rank fails every rank with one error naming
it, and nothing hangs; bodies are dealt by element count; scenes whose bodies must stay together
are refused by name."""
import math
import socket
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.app.cli import main
from tensormass_torch.sim.distributed import partition_bodies

pytestmark = pytest.mark.skipif(not torch.distributed.is_available() or not torch.distributed.is_gloo_available(),
                                reason="needs torch.distributed with gloo")

BODY = """
[[bodies]]
name = "{name}"
mesh = {{ generator = "beam", cells = [{n}, 2, 2], size = [{length}, 0.2, 0.2], origin = [0.0, {y}, 0.0] }}
material = {{ model = "{model}", young = {young}, poisson = 0.3, density = 1000.0 }}
fixed = {{ box = [[0.0, {y}, 0.0], [0.0, {y2}, 0.2]] }}
"""


def scene_file(tmp_path, youngs=(2e5, 5e5, 1e6, 3e5), models=("hooke", "stvk", "corotational", "corotational"),
               solver="cg_tol = 1e-10"):
    text = f'name = "beams"\ndt = 0.01\nsteps = 6\noutput_every = 3\ndtype = "float64"\n[solver]\n{solver}\n'
    for k, (young, model) in enumerate(zip(youngs, models)):
        y = 0.4 * k
        text += BODY.format(name=f"beam{k}", n=4 + 2 * k, length=0.5 + 0.1 * k, y=y, y2=y + 0.2, model=model,
                            young=young)
    path = tmp_path / "beams.toml"
    path.write_text(text)
    return path


def torchrun(args, processes=2, timeout=180):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    command = [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc-per-node", str(processes),
               "--master-addr", "127.0.0.1", "--master-port", str(port), "-m", "tensormass_torch"] + args
    return subprocess.run(command, capture_output=True, text=True, timeout=timeout,
                          env={**__import__("os").environ, "OMP_NUM_THREADS": "1"})


def series(folder: Path):
    root = ElementTree.parse(folder / "beams.pvd").getroot()
    return sorted((float(d.get("timestep")), int(d.get("part")), d.get("file")) for d in root.iter("DataSet"))


def test_bodies_over_two_processes_are_the_bodies_of_one(tmp_path):
    meshio = pytest.importorskip("meshio")
    path = scene_file(tmp_path)
    assert main(["run", str(path), "--out", str(tmp_path / "one"), "--quiet"]) == 0
    done = torchrun(["run", str(path), "--out", str(tmp_path / "two"), "--quiet"])
    assert done.returncode == 0, done.stderr[-3000:]
    one, two = series(tmp_path / "one"), series(tmp_path / "two")
    assert [(t, p, f) for t, p, f in two] == [(t, p, f) for t, p, f in one] and len(one) == 4 * 3
    for _, _, file in one:
        a, b = meshio.read(tmp_path / "one" / file), meshio.read(tmp_path / "two" / file)
        assert (a.points - b.points).__abs__().max() <= 1e-12
        for key in ("displacement", "velocity"):
            assert abs(a.point_data[key] - b.point_data[key]).max() <= 1e-12
    moved = meshio.read(tmp_path / "two" / one[-1][2])
    assert abs(moved.point_data["displacement"]).max() > 1e-4  # the bodies moved


def test_a_failed_step_on_one_rank_stops_the_run(tmp_path):
    """One stiff body cannot converge in the budget: its rank's step fails, the run stops at once
    with an error naming that rank (torchrun then ends the other processes)."""
    path = scene_file(tmp_path, youngs=(2e5, 2e5, 2e5, 5e9), solver="cg_tol = 1e-12\ncg_max_iter = 15")
    done = torchrun(["run", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    assert done.returncode != 0
    lines = [line for line in done.stderr.splitlines() if line.startswith("tensormass: error:")]
    assert lines, done.stderr[-3000:]
    assert all("a step at t = 0 failed (rank" in line and "SolverError" in line and "not converged" in line
               for line in lines)


def _collective_worker(rank: int, world: int, init: str, out: str):
    import torch.distributed as dist

    from tensormass_torch.sim.distributed import DistributedError, collectively

    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    results = []
    results.append(repr(collectively(lambda: rank * 10, "a step that works")))
    try:
        collectively(lambda: 1 / 0 if rank == 1 else rank, "a step")
        results.append("no error")
    except DistributedError as exc:
        results.append(str(exc))
    Path(out, f"rank{rank}.txt").write_text("\n".join(results))
    dist.destroy_process_group()


def test_what_one_rank_raises_every_rank_raises(tmp_path):
    """collectively(): where it works every rank gets its own result; where rank 1 raises, both
    ranks raise one DistributedError naming rank 1 and its error (neither waits)."""
    import torch.multiprocessing as mp

    init = f"file://{tmp_path / 'store'}"
    mp.start_processes(_collective_worker, args=(2, init, str(tmp_path)), nprocs=2, join=True, start_method="spawn")
    for rank in (0, 1):
        first, second = (tmp_path / f"rank{rank}.txt").read_text().splitlines()
        assert first == repr(rank * 10)
        assert second == "a step failed (rank 1: ZeroDivisionError: division by zero)"


def test_bodies_are_dealt_by_element_count():
    assert partition_bodies([10, 1, 7, 3, 3], 2) == [[0, 4], [1, 2, 3]]  # loads 13 and 11
    assert partition_bodies([5, 5, 5], 3) == [[0], [1], [2]]
    assert partition_bodies([4], 3) == [[0], [], []]
    shares = partition_bodies([int(1000 * (1 + math.sin(k))) for k in range(40)], 4)
    loads = [sum(int(1000 * (1 + math.sin(k))) for k in share) for share in shares]
    assert sorted(k for share in shares for k in share) == list(range(40))
    assert max(loads) - min(loads) <= 2000  # within the heaviest body
    with pytest.raises(ValueError, match="parts must be a positive integer"):
        partition_bodies([1], 0)


def test_scenes_whose_bodies_stay_together_are_refused(tmp_path):
    path = scene_file(tmp_path)
    path.write_text(path.read_text() + "\n[contact]\nstiffness = 1e5\n")
    with pytest.raises(tm.SceneError, match="contact between bodies or scalpels runs with all of its bodies"):
        tm.load_scene(path, select=lambda bodies: [0])
    scene = tm.load_scene(path, select=lambda bodies: range(len(bodies)))  # all of them: fine
    assert scene.body_ids == [0, 1, 2, 3]


# ---------------------------------------------------------------------------------------------
# one mesh over several processes (sim/partitioned.py)
# ---------------------------------------------------------------------------------------------

MODELS = ("hooke", "stvk", "corotational")


def partitioned_beam():
    mesh = tm.beam_mesh(12, 3, 3, size=(1.0, 0.25, 0.25), dtype=torch.float64)
    fixed = mesh.vertices[:, 0] == 0
    return mesh, fixed


def partitioned_body(model: str = "hooke"):
    """The partitioned beam as a body of ``model``."""
    mesh, fixed = partitioned_beam()
    return tm.Body(mesh, tm.Material(young=1e5, poisson=0.3, density=1000.0, model=model), fixed=fixed)


def spawned_results(worker, world: int, tmp_path, stem: str) -> list:
    """Run ``worker(rank, world, init, out)`` on ``world`` spawned processes; each rank's saved
    ``<stem>_<rank>.pt``."""
    import torch.multiprocessing as mp

    mp.start_processes(worker, args=(world, f"file://{tmp_path / 'store'}", str(tmp_path)), nprocs=world, join=True,
                       start_method="spawn")
    return [torch.load(tmp_path / f"{stem}_{r}.pt") for r in range(world)]


def _partitioned_worker(rank: int, world: int, init: str, out: str):
    import torch.distributed as dist

    from tensormass_torch.sim.partitioned import PartitionedSimulator

    torch.set_num_threads(1)
    dist.init_process_group("gloo", init_method=init, rank=rank, world_size=world)
    results = {}
    for model in MODELS:
        sim = PartitionedSimulator(partitioned_body(model), dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.001,
                                   planes=[tm.Plane((0.0, 0.0, 1.0), -0.005, 1e4)], cg_tol=1e-14)
        sim.step(5)
        results[model] = (sim.positions(), sim.velocities(), sim.owned.numel())
    # the host reading the residual after every iteration changes no iterate
    sim = PartitionedSimulator(partitioned_body(), dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.001,
                               planes=[tm.Plane((0.0, 0.0, 1.0), -0.005, 1e4)], cg_tol=1e-14, check_every=1)
    sim.step(5)
    results["hooke, checked every iteration"] = (sim.positions(), sim.velocities(), sim.last_iterations)
    torch.save(results, Path(out) / f"partitioned_{rank}.pt")
    dist.destroy_process_group()


@pytest.mark.parametrize("world", [3])
def test_one_mesh_over_processes_is_the_one_process_step(tmp_path, world):
    """A beam partitioned over 3 gloo processes (pymetis: a part with two neighbours), 5 steps with a floor it reaches,
    Rayleigh damping and fixed nodes: positions and velocities equal one process's Simulator's
    (float64, converged CG) to 1e-12, for hooke, stvk and corotational; every node owned once."""
    pytest.importorskip("pymetis")
    results = spawned_results(_partitioned_worker, world, tmp_path, "partitioned")
    mesh, _ = partitioned_beam()
    for model in MODELS:
        one = tm.Simulator([partitioned_body(model)], dt=0.01, rayleigh_mass=0.1, rayleigh_stiffness=0.001, cg_tol=1e-14,
                           planes=[tm.Plane((0.0, 0.0, 1.0), -0.005, 1e4)], preconditioner="none", cuda_graphs=False)
        one.step(5)
        assert float(one.x[:, 2].min()) < -0.005  # the floor is reached
        assert sum(r[model][2] for r in results) == mesh.num_vertices
        assert all(r[model][2] > 0 for r in results)
        for r in results:
            torch.testing.assert_close(r[model][0], one.x, rtol=0, atol=1e-12)
            torch.testing.assert_close(r[model][1], one.v, rtol=0, atol=1e-10)
            if model == "hooke":
                checked = r["hooke, checked every iteration"]
                assert torch.equal(checked[0], r[model][0]) and torch.equal(checked[1], r[model][1])
                assert checked[2] > 0


def _partitioned_cuda_worker(rank: int, world: int, init: str, out: str):
    import torch.distributed as dist

    from tensormass_torch.sim.partitioned import PartitionedSimulator

    torch.cuda.set_device(rank)
    dist.init_process_group("nccl", init_method=init, rank=rank, world_size=world)
    results = {}
    for model in MODELS:
        for graphs in (False, True):
            sim = PartitionedSimulator(partitioned_body(model), dt=0.01, rayleigh_mass=0.1, planes=[tm.Plane((0.0, 0.0, 1.0), -0.005, 1e4)],
                                       cg_tol=1e-14, check_every=4, cuda_graphs=graphs, device=f"cuda:{rank}")
            sim.step(5)
            captured = [graph is not False for graph in sim._graphs.values()]
            results[model, graphs] = (sim.positions(), sim.last_iterations, captured)
            sim.close()
    torch.save(results, Path(out) / f"partitioned_cuda_{rank}.pt")
    dist.destroy_process_group()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU (NCCL)")
def test_one_mesh_over_gpus_is_the_one_process_step(tmp_path):
    """On the GPU under NCCL (two GPUs where there are, else one rank): the partitioned step
    (fused node-graph products, scalars on the device) equals one process's Simulator in float64
    to 1e-12, eager and with its CG iterations replayed as captured CUDA graphs."""
    world = min(2, torch.cuda.device_count())
    if world > 1:
        pytest.importorskip("pymetis")
    results = spawned_results(_partitioned_cuda_worker, world, tmp_path, "partitioned_cuda")
    for model in MODELS:
        one = tm.Simulator([partitioned_body(model)], dt=0.01, rayleigh_mass=0.1, cg_tol=1e-14, preconditioner="none",
                           planes=[tm.Plane((0.0, 0.0, 1.0), -0.005, 1e4)], device="cuda")
        one.step(5)
        for r in results:
            for graphs in (False, True):
                torch.testing.assert_close(r[model, graphs][0], one.x.cpu(), rtol=0, atol=1e-12)
            assert r[model, True][1] == r[model, False][1] > 0
            assert r[model, True][2] and all(r[model, True][2])  # captured, not left eager
            assert r[model, False][2] == []


def test_a_partitioned_check_interval_must_be_positive():
    from tensormass_torch.sim.partitioned import PartitionedSimulator

    with pytest.raises(tm.SceneError, match="check_every must be a positive number"):
        PartitionedSimulator(partitioned_body(), check_every=0)  # refused before any collective


def test_node_partitions_are_connected_and_balanced():
    pytest.importorskip("pymetis")
    from tensormass_torch.mesh.topology import unique_edges
    from tensormass_torch.sim.partitioned import partition_nodes

    mesh = tm.beam_mesh(24, 4, 4, size=(1.0, 0.2, 0.2))
    parts = partition_nodes(mesh.elements, mesh.num_vertices, 4)
    sizes = torch.bincount(parts, minlength=4)
    assert int(sizes.min()) > 0 and int(sizes.max()) <= 1.2 * mesh.num_vertices / 4
    edges, _, _ = unique_edges(mesh.elements.long(), mesh.num_vertices)
    for p in range(4):  # each part connected through its own edges
        inside = edges[(parts[edges[:, 0]] == p) & (parts[edges[:, 1]] == p)]
        nodes = torch.nonzero(parts == p).flatten().tolist()
        reached, frontier = {nodes[0]}, [nodes[0]]
        neighbours = {}
        for a, b in inside.tolist():
            neighbours.setdefault(a, []).append(b)
            neighbours.setdefault(b, []).append(a)
        while frontier:
            frontier = [m for n in frontier for m in neighbours.get(n, []) if m not in reached]
            reached.update(frontier)
        assert reached == set(nodes)
    assert torch.equal(partition_nodes(mesh.elements, mesh.num_vertices, 1), torch.zeros(mesh.num_vertices,
                                                                                         dtype=torch.int64))


def test_partitioned_sums_travel_on_the_device_under_nccl(monkeypatch):
    """NCCL reduces device tensors only: the partitioned simulator's scalar sums are made on its
    device there, on the CPU under gloo."""
    import torch.distributed as dist

    from tensormass_torch.sim.partitioned import PartitionedSimulator

    seen = []
    monkeypatch.setattr(dist, "all_reduce", lambda tensor, *a, **k: seen.append(tensor.device))
    sim = PartitionedSimulator.__new__(PartitionedSimulator)
    sim.device = torch.device("meta")  # (a device other than the CPU that needs no GPU)
    for backend, expected in (("nccl", "meta"), ("gloo", "cpu")):
        monkeypatch.setattr(dist, "get_backend", lambda *a, backend=backend: backend)
        sim._sum(torch.tensor(3.0))
        assert seen[-1].type == expected


MESH_SPLIT = """name = "beams"
dt = 0.01
steps = 6
output_every = 3
dtype = "float64"
[solver]
cg_tol = 1e-12
rayleigh_mass = 0.1
[distributed]
split = "mesh"
[[planes]]
normal = [0, 0, 1]
offset = -0.02
stiffness = 1e4
[[bodies]]
name = "beam"
mesh = { generator = "beam", cells = [10, 3, 3], size = [1.0, 0.25, 0.25] }
material = { model = "corotational", young = 2e5, poisson = 0.3, density = 1000.0 }
fixed = { box = [[0.0, 0.0, 0.0], [0.0, 0.25, 0.25]] }
"""


def test_a_scene_split_by_mesh_over_two_processes_is_the_one_process_run(tmp_path):
    """``[distributed] split = "mesh"``: under torchrun the one body's mesh is partitioned
    (PartitionedSimulator) and rank 0 writes the gathered frames; in one process the same file is
    the usual Simulator. The frames agree to the CG's tolerance (float64)."""
    meshio = pytest.importorskip("meshio")
    pytest.importorskip("pymetis")
    from tensormass_torch.sim.scene_file import load_scene

    path = tmp_path / "beams.toml"
    path.write_text(MESH_SPLIT)
    assert type(load_scene(path).simulator).__name__ == "Simulator"  # one process: the usual simulator
    assert main(["run", str(path), "--out", str(tmp_path / "one"), "--quiet"]) == 0
    done = torchrun(["run", str(path), "--out", str(tmp_path / "two"), "--quiet"])
    assert done.returncode == 0, done.stderr[-3000:]
    one, two = series(tmp_path / "one"), series(tmp_path / "two")
    assert [(round(t, 9), p, f) for t, p, f in two] == [(round(t, 9), p, f) for t, p, f in one] and len(one) == 3
    for _, _, file in one:
        a, b = meshio.read(tmp_path / "one" / file), meshio.read(tmp_path / "two" / file)
        assert abs(a.points - b.points).max() <= 1e-10
        assert abs(a.point_data["velocity"] - b.point_data["velocity"]).max() <= 1e-8
    assert abs(meshio.read(tmp_path / "two" / one[-1][2]).point_data["displacement"]).max() > 1e-4


def test_a_mesh_split_names_what_the_partitioned_step_does_not_do(tmp_path):
    from tensormass_torch.errors import SceneError
    from tensormass_torch.sim.scene_file import load_scene

    two_bodies = MESH_SPLIT + MESH_SPLIT[MESH_SPLIT.index("[[bodies]]"):].replace('"beam"', '"other"', 1)
    for text, named in ((two_bodies, "2 bodies"),
                        (MESH_SPLIT.replace("rayleigh_mass = 0.1", "integrator = \"newmark\""), "integrator"),
                        (MESH_SPLIT.replace("stiffness = 1e4", "stiffness = 1e4\nfriction = 0.5"), "friction"),
                        (MESH_SPLIT.replace('split = "mesh"', 'split = "nodes"'), "unknown split")):
        path = tmp_path / "bad.toml"
        path.write_text(text)
        with pytest.raises(SceneError, match=named):
            load_scene(path)
    path.write_text(MESH_SPLIT)
    with pytest.raises(SceneError, match="unknown split"):
        load_scene(path, split="nodes")


def test_a_scene_files_device_and_split_are_read_before_the_group_starts(tmp_path):
    """Under torchrun the process group (NCCL and a GPU a rank for CUDA) starts before the scene
    is built, from the file's device and split, read without building it."""
    from tensormass_torch.sim.scene_file import scene_device, scene_split

    path = tmp_path / "s.toml"
    for text, device, split in (('device = "cuda"\n[distributed]\nsplit = "mesh"\n', "cuda", "mesh"),
                                ("dt = 0.01\n", None, "bodies"), ('device = "gpu"\n', None, "bodies"),
                                ("not toml [", None, "bodies")):
        path.write_text(text)
        assert (scene_device(path), scene_split(path)) == (device, split)
