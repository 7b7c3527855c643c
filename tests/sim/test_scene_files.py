"""Scene files (TOML): every shipped scene runs, options reach the simulator, and each kind of
mistake gives one SceneError line naming the file and the key path."""
import textwrap
from pathlib import Path

import pytest
import torch

import tensormass_torch as tm
from tensormass_torch.sim.scene_file import load_scene

SCENES_DIR = Path(__file__).resolve().parents[2] / "scenes"
SHIPPED = sorted(SCENES_DIR.glob("*.toml"))

BEAM = """
dt = 0.01
steps = 3
[[bodies]]
mesh = { generator = "beam", cells = [4, 1, 1], size = [1.0, 0.25, 0.25] }
material = { model = "hooke", young = 1e5, poisson = 0.3 }
fixed = { box = [[0, 0, 0], [0, 0.25, 0.25]] }
"""


def write(tmp_path, text, name="scene.toml"):
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return path


def test_scene_files_are_shipped():
    assert len(SHIPPED) >= 2


@pytest.mark.parametrize("path", SHIPPED, ids=[p.stem for p in SHIPPED])
def test_shipped_scene_runs(path):
    scene = load_scene(path)
    sim = scene.simulator
    assert scene.steps > 0 and scene.output_every > 0 and scene.description
    report = sim.step(2)
    assert sim.steps_done == 2
    assert all(s == "converged" or not sim.options.require_convergence for s in report.cg[-1].status())
    for i in range(sim.num_bodies):
        assert torch.isfinite(sim.positions(i)).all()
    # Gravity pulls along -z in every shipped scene: something must have moved down.
    assert min(float(sim.displacements(i)[:, 2].min()) for i in range(sim.num_bodies)) < 0


def test_options_reach_the_simulator(tmp_path):
    path = write(tmp_path, """
        name = "custom"
        dt = 0.005
        steps = 7
        output_every = 2
        gravity = [0, -9, 0]
        dtype = "float64"
        [solver]
        cg_tol = 1e-5
        cg_max_iter = 50
        require_convergence = false
        newton_iters = 2
        rayleigh_mass = 0.1
        rayleigh_stiffness = 0.01
        [render]
        png = true
        window_size = [320, 240]
        [[planes]]
        normal = [0, 1, 0]
        offset = -1.0
        stiffness = 1e4
        [[bodies]]
        name = "b"
        mesh = { generator = "beam", cells = [2, 1, 1], size = [1, 0.5, 0.5], origin = [0, 1, 0] }
        material = { model = "stvk", young = 1e5, poisson = 0.25, density = 500 }
        velocity = [0, 0, 1]
    """)
    scene = load_scene(path)
    sim = scene.simulator
    assert (scene.name, scene.steps, scene.output_every) == ("custom", 7, 2)
    assert scene.render == {"png": True, "gif": False, "window_size": (320, 240)}
    o = sim.options
    assert (o.dt, o.cg_tol, o.cg_max_iter, o.require_convergence, o.newton_iters) == (0.005, 1e-5, 50, False, 2)
    assert (o.rayleigh_mass, o.rayleigh_stiffness) == (0.1, 0.01)
    assert sim.dtype == torch.float64 and len(sim.planes) == 1
    assert sim.bodies[0].material.model == "stvk" and sim.bodies[0].name == "b"
    assert float(sim.positions(0)[:, 1].min()) == 1.0  # origin applied
    assert torch.equal(sim.v[:, 2], torch.ones(sim.v.shape[0], dtype=torch.float64))
    # Overrides from the caller (the command line's --dtype / --model) win over the file.
    scene = load_scene(path, dtype="float32", model="hooke")
    assert scene.simulator.dtype == torch.float32 and scene.simulator.bodies[0].material.model == "hooke"


def test_mesh_from_file_relative_to_the_scene(tmp_path):
    pytest.importorskip("meshio")
    mesh = tm.beam_mesh(3, 1, 1, size=(1.0, 0.3, 0.3), dtype=torch.float64)
    (tmp_path / "meshes").mkdir()
    tm.save_mesh(tmp_path / "meshes" / "bar.vtu", mesh)
    path = write(tmp_path, """
        [[bodies]]
        mesh = { file = "meshes/bar.vtu", scale = 2.0, translate = [0, 0, 1] }
        material = { young = 1e5, poisson = 0.3 }
        fixed = { nodes = [0, 4] }
    """)
    sim = load_scene(path).simulator
    expected = mesh.vertices.float() * 2 + torch.tensor([0.0, 0.0, 1.0])
    assert torch.allclose(sim.positions(0), expected)
    assert sim.bodies[0].fixed.nonzero().flatten().tolist() == [0, 4]


def test_box_selects_the_face_it_touches(tmp_path):
    sim = load_scene(write(tmp_path, BEAM)).simulator
    fixed = sim.bodies[0].fixed
    x = sim.bodies[0].mesh.vertices[:, 0]
    assert torch.equal(fixed, x == 0) and int(fixed.sum()) == 4


def test_prescribed_nodes_follow_their_velocity(tmp_path):
    path = write(tmp_path, BEAM + """prescribed = { box = [[1, 0, 0], [1, 0.25, 0.25]], velocity = [0, 0, -0.5], stop = 0.02 }
    """)
    scene = load_scene(path)
    sim = scene.simulator
    moved = sim.bodies[0].prescribed
    rest = sim.bodies[0].mesh.vertices[moved]
    sim.step(3)  # t = 0.03 > stop: the nodes moved 0.5 * 0.02 and then held
    expected = rest + torch.tensor([0.0, 0.0, -0.01])
    assert torch.allclose(sim.positions(0)[moved], expected, atol=1e-6)


# -- mistakes: one line, the key path, the problem --------------------------------------------

MISTAKES = {
    "unknown top-level key": ("stepz = 3\n" + BEAM, "stepz: unknown key; did you mean 'steps'?"),
    "wrong type": (BEAM.replace("dt = 0.01", 'dt = "fast"'), "dt: must be a finite number"),
    "negative dt": (BEAM.replace("dt = 0.01", "dt = -1"), "dt: must be > 0"),
    "unknown model": (BEAM.replace('model = "hooke"', 'model = "stvkk"'),
                      "bodies[0].material.model: unknown model 'stvkk'; expected one of hooke, stvk, corotational"),
    "bad poisson": (BEAM.replace("poisson = 0.3", "poisson = 0.5"), "bodies[0].material: poisson must lie in"),
    "missing young": (BEAM.replace("young = 1e5, ", ""), "bodies[0].material.young: missing (required)"),
    "missing mesh file": (BEAM.replace('generator = "beam", cells = [4, 1, 1], size = [1.0, 0.25, 0.25]',
                                       'file = "nowhere.vtu"'), "bodies[0].mesh.file: mesh file not found"),
    "unknown body key": (BEAM + "velocty = [0, 0, 1]\n", "bodies[0].velocty: unknown key; did you mean 'velocity'?"),
    "unknown generator": (BEAM.replace('"beam"', '"bean"'), "bodies[0].mesh.generator: unknown generator 'bean'"),
    "generator key of another generator": (BEAM.replace("size =", "radius = 1, size ="),
                                           "bodies[0].mesh.radius: unknown key"),
    "empty fixed box": (BEAM.replace("[[0, 0, 0], [0, 0.25, 0.25]]", "[[5, 5, 5], [6, 6, 6]]"),
                        "bodies[0].fixed.box: selects no node"),
    "inverted box": (BEAM.replace("[[0, 0, 0], [0, 0.25, 0.25]]", "[[1, 0, 0], [0, 0.25, 0.25]]"),
                     "bodies[0].fixed.box: corner 0 must not exceed corner 1"),
    "node out of range": (BEAM.replace("box = [[0, 0, 0], [0, 0.25, 0.25]]", "nodes = [0, 99]"),
                          "bodies[0].fixed.nodes: node indices out of range [0, 20): [99]"),
    "box and nodes": (BEAM.replace("box =", "nodes = [0], box ="), "bodies[0].fixed: give exactly one of 'box' or 'nodes'"),
    "short vector": ("gravity = [0, -9]\n" + BEAM, "gravity: must be a list of 3 numbers"),
    "everything fixed": (BEAM.replace("[[0, 0, 0], [0, 0.25, 0.25]]", "[[-1, -1, -1], [2, 2, 2]]"),
                         "bodies[0]: every node of body"),
    "no bodies": ("dt = 0.01\n", "bodies: a scene needs at least one [[bodies]] table"),
    "bad TOML": ("steps = = 3\n" + BEAM, "invalid TOML"),
    "unknown solver option": (BEAM + "[solver]\ncg_tolerance = 1e-3\n", "solver.cg_tolerance: unknown key; did you mean 'cg_tol'?"),
    "plane without stiffness": (BEAM + "[[planes]]\nnormal = [0, 0, 1]\n", "planes[0].stiffness: missing (required)"),
    "bad dtype": ('dtype = "float16"\n' + BEAM, "dtype: unknown dtype 'float16'"),
    "unknown tool shape": (BEAM + '[[tools]]\nshape = "cone"\nradius = 1\n',
                           "tools[0].shape: unknown tool shape 'cone'; expected one of sphere, capsule, box"),
    "negative tool radius": (BEAM + '[[tools]]\nshape = "sphere"\nradius = -1\n',
                             "tools[0].radius: must be > 0"),
    "tool positions without times": (BEAM + '[[tools]]\nshape = "sphere"\nradius = 1\npositions = [[0, 0, 0]]\n',
                                     "tools[0].positions: needs times"),
    "tool NaN position": (BEAM + '[[tools]]\nshape = "box"\nhalf_extents = [1, 1, 1]\nposition = [0, nan, 0]\n',
                          "tools[0].position: entry 1 must be a finite number"),
    "tool bad rotation": (BEAM + '[[tools]]\nshape = "box"\nhalf_extents = [1, 1, 1]\n'
                          'rotation = [[2, 0, 0], [0, 1, 0], [0, 0, 1]]\n', "tools[0]: tool rotation must be a 3x3 rotation"),
    "bad device": ('device = "gpu0"\n' + BEAM, "device: not a torch device"),
    "negative contact stiffness": (BEAM + '[contact]\nstiffness = -1\n', "contact.stiffness: must be > 0"),
    "unknown contact key": (BEAM + '[contact]\nfrictions = 0.3\n', "contact.frictions"),
    "negative contact friction": (BEAM + '[contact]\nfriction = -0.3\n', "contact.friction: must be >= 0"),
    "bad contact tangent": (BEAM + '[contact]\ntangent = "full"\n', "contact.tangent: unknown contact tangent"),
    "negative contact rounds": (BEAM + '[contact]\nrounds = -1\n', "contact.rounds: must be >= 0"),
    "fractional contact rounds": (BEAM + '[contact]\nrounds = 1.5\n', "contact.rounds: must be an integer"),
    "zero contact tolerance": (BEAM + '[contact]\ntolerance = 0.0\n', "contact.tolerance: must be > 0"),
}


@pytest.mark.parametrize("case", sorted(MISTAKES))
def test_mistakes_name_the_key(tmp_path, case):
    text, expected = MISTAKES[case]
    path = write(tmp_path, text)
    with pytest.raises(tm.SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(str(path)) and expected in message, message
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene.toml"]  # nothing written


def test_tools_reach_the_simulator(tmp_path):
    path = write(tmp_path, BEAM + """
        [[tools]]
        shape = "capsule"
        radius = 0.1
        half_length = 0.2
        rotation = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
        times = [0, 1]
        positions = [[0.5, 0.1, 0.5], [0.5, 0.1, 0.3]]
        stiffness = 2e4
        thickness = 0.01
        name = "probe"
        """)
    sim = load_scene(path).simulator
    (tool,) = sim.tools.tools
    assert (tool.shape, tool.size, tool.stiffness, tool.thickness, tool.name) == ("capsule", (0.1, 0.2), 2e4, 0.01,
                                                                                   "probe")
    assert tool.origin(0.5) == pytest.approx((0.5, 0.1, 0.4))
    assert tool.rotation[2] == (-1.0, 0.0, 0.0)
    sim.step()
    assert sim.last_report.contact.tool_force.shape == (1, 3)


@pytest.mark.parametrize("line, expected", [("", tm.Contact().check_tol), ("check_tol = 0.05", 0.05),
                                            ("check_tol = false", None)])
def test_contact_check_tol_defaults_to_the_library_and_false_turns_it_off(tmp_path, line, expected):
    path = write(tmp_path, BEAM + f"""
        [contact]
        {line}
        """)
    assert load_scene(path).simulator.contact.check_tol == expected


@pytest.mark.parametrize("value", ["true", "0", "1.5", '"0.01"', "nan"])
def test_contact_check_tol_must_be_in_zero_one_or_false(tmp_path, value):
    path = write(tmp_path, BEAM + f"""
        [contact]
        check_tol = {value}
        """)
    with pytest.raises(tm.SceneError, match=r"contact\.check_tol: must be a number in \(0, 1\) or false"):
        load_scene(path)


def test_missing_scene_file(tmp_path):
    with pytest.raises(tm.SceneError, match="scene file not found"):
        load_scene(tmp_path / "nope.toml")


def test_contact_reaches_the_simulator(tmp_path):
    path = write(tmp_path, BEAM + """
        [contact]
        stiffness = 2e4
        thickness = 0.01
        search = 0.05
        self_contact = true
        swept = false
        friction = 0.4
        friction_velocity = 0.01
        rounds = 2
        tolerance = 2e-4
        recheck_tolerance = 5e-4
        check_tol = 0.03
        skin = 0.004
        check_margin = 0.002
        """)
    sim = load_scene(path).simulator
    assert sim.contact == tm.Contact(stiffness=2e4, thickness=0.01, search=0.05, self_contact=True, swept=False,
                                     friction=0.4, friction_velocity=0.01, rounds=2, tolerance=2e-4,
                                     recheck_tolerance=5e-4,
                                     check_tol=0.03, skin=0.004, check_margin=0.002)
    assert sim.body_contact is not None and sim.body_contact.search == 0.05
    assert sim.body_contact.tolerance == 2e-4
