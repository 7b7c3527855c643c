"""Scene files: a simulation described in TOML, checked key by key, built into a ``scenes.Scene``.

    scene = load_scene("scenes/drop.toml")      # -> FileScene (a scenes.Scene)
    scene.simulator.step(scene.steps)

The format (every key but ``bodies`` and the body's ``mesh`` / ``material`` is optional)::

    name = "drop"                     # default: the file's stem
    description = "..."
    dt = 0.01                         # s
    steps = 100
    output_every = 5                  # a frame every N steps
    gravity = [0, 0, -9.81]
    device = "cpu"                    # or "cuda", "cuda:1"
    dtype = "float32"                 # or "float64"

    [solver]                          # Simulator options
    cg_tol = 1e-4                     # relative residual (default 1e-6)
    cg_max_iter = 500                 # default: 10 x the largest body's free degrees of freedom
    require_convergence = true
    newton_iters = 1
    check_every = 8
    rayleigh_mass = 0.5
    rayleigh_stiffness = 0.002
    form = "auto"                     # "stress", "tensor"
    preconditioner = "auto"           # "none", "jacobi", "rigid", "multigrid", "cholesky"
                                      # (auto: Jacobi where bodies touch)
    paired_blocks = true              # Jacobi's blocks merge the two nodes a contact pair couples most
    integrator = "backward_euler"     # "newmark" (no numerical damping), "bdf2" (second order)
    warm_start = false                # true / "extrapolate": each CG from the last steps' extrapolated
                                      # solution; "project": their span's projection (hooke: best)
    precision = "full"                # "mixed" (dtype "float64"): float64 residuals, float32 CG iterations
    check_memory = true               # on a GPU: refuse at once a scene whose estimated peak does not fit
    cut_on_device = false             # scalpels ([[cuts]]) cut with kernels on the device where they can
                                      # (one hooke body: docs/topology-changes.md)

    [distributed]                     # under torchrun --nproc-per-node N (docs/distributed.md)
    split = "bodies"                  # the bodies dealt over the processes; "mesh": the one body's
                                      # mesh partitioned over them (PartitionedSimulator)

    [render]                          # off-screen pictures of the frames (pyvista)
    png = false                       # one PNG per frame
    gif = false                       # an animated GIF of all frames
    window_size = [800, 600]

    [[planes]]                        # penalty contact: the half-space n.x >= offset
    normal = [0, 0, 1]
    offset = -0.5
    stiffness = 1e5
    friction = 0.0                    # Coulomb coefficient against the plane (0: none)
    friction_velocity = 1e-3          # slip speed (m/s) below which friction is viscous

    [[tools]]                         # a rigid tool pressing on the bodies' nodes (tm.Sphere, ...)
    shape = "sphere"                  # "sphere" (radius), "capsule" (radius, half_length along its
    radius = 0.05                     #   first axis), "box" (half_extents = [a, b, c]) or "mesh"
                                      #   (file = "probe.stl": a closed surface in the tool's frame,
                                      #   relative to the scene file; resolution = 32 grid cells)
    position = [0.5, 0, 0.2]          # its origin (or keyframes: times = [...], positions = [[...]])
    # rotation = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]   (its axes, as columns)
    stiffness = 1e5                   # penalty (N/m per node)
    thickness = 0.0                   # contact distance
    name = "probe"                    # tangent = "exact": the curvature in the step's stiffness
    friction = 0.0                    # Coulomb coefficient against the tool (friction_velocity too)

    [contact]                         # contact between the bodies' surfaces (tm.Contact)
    stiffness = 1e5                   # penalty (N/m per vertex in contact)
    thickness = 0.0                   # surfaces are pushed apart once closer than this
    # search = 0.05                   # how far pairs are looked for (default: mean surface edge)
    self_contact = false              # a body's surface also meets its own far parts
    swept = true                      # find pairs over each step's motion (fast bodies)
    friction = 0.0                    # Coulomb coefficient between the bodies (0: none)
    friction_velocity = 1e-3          # slip speed (m/s) below which friction is viscous
    rounds = 2                        # more solves a step may take to check its contact set (0: none)
    # tolerance = 5e-5                # how deep past its model a vertex may end before a round (default: search / 400)
    # recheck_tolerance = 2e-4        # the same after a round's solve (default: search / 100)
    check_tol = 1e-2                  # CG tolerance of the solves a round's check reads (false: cg_tol)
    # skin = 0.005                    # keep the broad phase's candidates while surfaces move less (search / 10; 0: off)
    # check_margin = 0.002            # with skin = 0: checks take the step's search near its prediction (search / 16)

    [[bodies]]
    name = "beam"
    mesh = { generator = "beam", cells = [20, 2, 2], size = [1, 0.1, 0.1] }
    # mesh = { file = "meshes/liver.vtu", orient = true }  (relative to the scene file; any meshio
    #                                                         format; orient flips inverted elements)
    # mesh = { surface = "meshes/liver.stl", max_volume = 1e-6 }  (a closed surface, tetrahedralised by
    #                                          tm.tetrahedralize: method = "tetgen" | "ftetwild", options)
    # generators: beam, tri_beam, sphere, capsule, rabbit (see MESH_GENERATORS);
    # every mesh table also takes scale = s and translate = [dx, dy, dz] (applied in that order)
    material = { model = "stvk", young = 5e6, poisson = 0.3, density = 1000 }  # tangent = "definite"
    fixed = { box = [[-1, -1, -1], [0, 1, 1]] }  # or { nodes = [0, 1, 2] }
    prescribed = { box = [[...], [...]], velocity = [0, 0, -0.1], stop = 1.0 }
    velocity = [0, 0, 0]                         # initial velocity
    spare_nodes = 512                 # rows for the nodes cuts add, cut in place while they last
                                      # (default: 0, or room for a body a [[cuts]] table names)

    [[cuts]]                          # a scalpel (tm.Scalpel): a blade edge through keyframes,
    body = "beam"                     # cutting this body (a name or index; default 0) as it moves
    times = [0.1, 0.5]                # keyframe times (s), increasing
    edges = [[[0.3, -1, -1], [0.3, -1, 1]],   # the edge's two end points at each keyframe
             [[0.3, 1, -1], [0.3, 1, 1]]]

Every problem raises one ``SceneError`` whose message starts with the file and the key path,
e.g. ``drop.toml: bodies[1].material.model: unknown model 'stvkk'; expected one of hooke, stvk,
corotational``. Loading writes nothing.
"""
from __future__ import annotations

import difflib
import math

try:
    import tomllib
except ModuleNotFoundError:  # Python < 3.11: the package still imports; reading a scene needs tomli
    try:
        import tomli as tomllib
    except ModuleNotFoundError:
        tomllib = None
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional, Sequence

import torch

from ..errors import InvertedElementsError, MaterialError, MeshError, SceneError
from ..mesh.beams import beam_mesh, beam_tri_mesh
from ..mesh.meshes import Mesh
from ..physics.body_contact import TANGENTS as CONTACT_TANGENTS
from ..physics.body_contact import Contact
from ..physics.contact import Plane
from ..physics.materials import MODELS, ROTATIONS, TANGENTS, Material
from ..physics.tools import TANGENTS as TOOL_TANGENTS
from ..physics.tools import Box, Capsule, MeshTool, Sphere, Tool
from ..solver.guess import WARM_STARTS, warm_start_mode
from ..solver.implicit_euler import INTEGRATORS
from ..solver.preconditioner import PRECONDITIONERS
from ..solver.refine import PRECISIONS
from .builtin import Scene
from .scalpel import Scalpel
from .simulator import MIN_SPARE_NODES, SPARE_FRACTION, Body, Simulator

__all__ = ["FileScene", "load_scene", "MESH_GENERATORS"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}
FORMS = ("auto", "stress", "tensor")
CUTS = ("alternating", "uniform")

_REQUIRED = object()


@dataclass
class FileScene(Scene):
    """A :class:`scenes.Scene` read from a file, with the file's rendering options.

    Attributes:
        path: the scene file.
        render: ``{"png": bool, "gif": bool, "window_size": (w, h)}``.
    """

    path: Optional[Path] = None
    render: Dict[str, Any] = field(default_factory=dict)
    #: the file's index of each body of the simulator (all of them, unless ``load_scene``'s
    #: ``select`` chose some)
    body_ids: Optional[List[int]] = None


# ---------------------------------------------------------------------------------------------
# Reading typed values out of TOML tables, with the key path in every message
# ---------------------------------------------------------------------------------------------


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _describe(value) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


class _Table:
    """One TOML table under key path ``where``; every read is checked, unknown keys are errors."""

    def __init__(self, data, where: str, fail: Callable[[str, str], SceneError]):
        if not isinstance(data, dict):
            raise fail(where, f"must be a table, got {_describe(data)}")
        self.data = data
        self.where = where
        self.fail = fail
        self.seen = set()

    def path(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def has(self, key: str) -> bool:
        self.seen.add(key)
        return key in self.data

    def error(self, key: str, message: str) -> SceneError:
        return self.fail(self.path(key), message)

    def get(self, key: str, kind: str, default=_REQUIRED):
        """The value of ``key`` checked as ``kind`` (see ``_check``); ``default`` if absent."""
        self.seen.add(key)
        if key not in self.data:
            if default is _REQUIRED:
                # A misspelt required key is an unknown key, not a missing one: name it.
                unread = [k for k in self.data if k not in self.seen]
                close = difflib.get_close_matches(key, unread, n=1)
                if close:
                    raise self.fail(self.path(close[0]), f"unknown key; did you mean '{key}'?")
                raise self.fail(self.path(key), "missing (required)")
            return default
        return _check(self.data[key], kind, lambda msg: self.error(key, msg))

    def table(self, key: str, required: bool = False) -> Optional["_Table"]:
        self.seen.add(key)
        if key not in self.data:
            if required:
                raise self.fail(self.path(key), "missing (required)")
            return None
        return _Table(self.data[key], self.path(key), self.fail)

    def tables(self, key: str) -> List["_Table"]:
        """An array of tables (``[[key]]``), each with its own path ``key[i]``."""
        self.seen.add(key)
        items = self.data.get(key, [])
        if not isinstance(items, list):
            raise self.error(key, f"must be an array of tables ([[{key}]]), got {_describe(items)}")
        return [_Table(item, f"{self.path(key)}[{i}]", self.fail) for i, item in enumerate(items)]

    def done(self) -> None:
        """Raise on the first key that was never read (a typo, or an option that does not exist)."""
        for key in self.data:
            if key not in self.seen:
                known = sorted(self.seen)
                close = difflib.get_close_matches(key, known, n=1)
                hint = f"did you mean '{close[0]}'? " if close else ""
                raise self.fail(self.path(key), f"unknown key; {hint}expected one of {', '.join(known)}")


def _check(value, kind: str, error: Callable[[str], SceneError]):
    """``value`` checked as ``kind``; returns it converted (tuples for vectors)."""
    if kind == "str":
        if not isinstance(value, str):
            raise error(f"must be a string, got {_describe(value)}")
        return value
    if kind == "bool":
        if not isinstance(value, bool):
            raise error(f"must be true or false, got {_describe(value)}")
        return value
    if kind in ("number", "positive", "nonnegative"):
        if not _is_number(value) or not math.isfinite(value):
            raise error(f"must be a finite number, got {_describe(value)}")
        if kind == "positive" and not value > 0:
            raise error(f"must be > 0, got {value!r}")
        if kind == "nonnegative" and not value >= 0:
            raise error(f"must be >= 0, got {value!r}")
        return float(value)
    if kind in ("int", "posint", "nonnegative_int"):
        if not isinstance(value, int) or isinstance(value, bool):
            raise error(f"must be an integer, got {_describe(value)}")
        if kind == "posint" and value < 1:
            raise error(f"must be >= 1, got {value}")
        if kind == "nonnegative_int" and value < 0:
            raise error(f"must be >= 0, got {value}")
        return value
    if kind[:-1].endswith("vec"):  # vec2, vec3, posvec3, intvec3, posintvec2...
        length = int(kind[-1])
        if not isinstance(value, list) or len(value) != length:
            raise error(f"must be a list of {length} numbers, got {_describe(value)}")
        item = "posint" if "int" in kind and "pos" in kind else "int" if "int" in kind else \
            "positive" if "pos" in kind else "number"
        return tuple(_check(v, item, lambda msg, i=i: error(f"entry {i} {msg}")) for i, v in enumerate(value))
    if kind == "box":
        if not isinstance(value, list) or len(value) != 2:
            raise error(f"must be two corners [[x0, y0, z0], [x1, y1, z1]], got {_describe(value)}")
        lo, hi = (_check(c, "vec3", lambda msg, i=i: error(f"corner {i} {msg}")) for i, c in enumerate(value))
        if any(a > b for a, b in zip(lo, hi)):
            raise error(f"corner 0 must not exceed corner 1 on any axis, got {list(lo)} and {list(hi)}")
        return lo, hi
    if kind == "nodes":
        if not isinstance(value, list) or not value:
            raise error(f"must be a non-empty list of node indices, got {_describe(value)}")
        for v in value:
            if not isinstance(v, int) or isinstance(v, bool):
                raise error(f"node indices must be integers, got {_describe(v)}")
        return value
    raise AssertionError(f"unknown kind {kind}")


def _warm_start(solver: _Table) -> str:
    """``[solver] warm_start``: true, false or one of ``guess.WARM_STARTS``, as one of them."""
    if isinstance(solver.data.get("warm_start"), bool) or not solver.has("warm_start"):
        return warm_start_mode(solver.get("warm_start", "bool", False))
    return _choice(solver, "warm_start", WARM_STARTS, what="warm start")


def _check_tol(contact: _Table) -> Optional[float]:
    """``[contact] check_tol``: a number, or false for None (every solve to the solver's cg_tol)."""
    value = contact.data.get("check_tol", Contact.check_tol)
    contact.seen.add("check_tol")
    if value is False:
        return None
    if not _is_number(value) or not 0 < value < 1:
        raise contact.error("check_tol", f"must be a number in (0, 1) or false, got {_describe(value)}")
    return float(value)


def _choice(table: _Table, key: str, choices, default=_REQUIRED, what: str = "value") -> str:
    value = table.get(key, "str", default)
    if value not in choices:
        raise table.error(key, f"unknown {what} {value!r}; expected one of {', '.join(choices)}")
    return value


# ---------------------------------------------------------------------------------------------
# Meshes
# ---------------------------------------------------------------------------------------------


def _beam(t: _Table) -> Mesh:
    cells = t.get("cells", "posintvec3")
    size = t.get("size", "posvec3", (1.0, 1.0, 1.0))
    origin = t.get("origin", "vec3", (0.0, 0.0, 0.0))
    cut = _choice(t, "cut", CUTS, "alternating", "cut")
    return beam_mesh(*cells, size=size, origin=origin, cut=cut, dtype=torch.float64)


def _tri_beam(t: _Table) -> Mesh:
    cells = t.get("cells", "posintvec2")
    size = t.get("size", "posvec2", (1.0, 1.0))
    origin = t.get("origin", "vec2", (0.0, 0.0))
    cut = _choice(t, "cut", CUTS, "alternating", "cut")
    return beam_tri_mesh(*cells, size=size, origin=origin, cut=cut, dim=3, dtype=torch.float64)


def _sphere(t: _Table) -> Mesh:
    from ..mesh import implicit as meshgen

    radius = t.get("radius", "positive")
    center = t.get("center", "vec3", (0.0, 0.0, 0.0))
    cell = t.get("cell", "positive", radius / 4)
    return meshgen.sphere_mesh(radius, center=center, cell=cell)


def _capsule(t: _Table) -> Mesh:
    from ..mesh import implicit as meshgen

    radius = t.get("radius", "positive")
    length = t.get("length", "positive")
    center = t.get("center", "vec3", (0.0, 0.0, 0.0))
    cell = t.get("cell", "positive", radius / 3)
    return meshgen.capsule_mesh(radius, length, center=center, cell=cell)


def _rabbit(t: _Table) -> Mesh:
    from ..mesh import implicit as meshgen

    scale = t.get("size", "positive", 1.0)
    cell = t.get("cell", "positive", 0.08 * scale)
    origin = t.get("origin", "vec3", (0.0, 0.0, 0.0))
    return meshgen.rabbit_mesh(size=scale, cell=cell, origin=origin)


#: Mesh generators of scene files: ``mesh = { generator = NAME, ... }`` and their keys.
MESH_GENERATORS: Dict[str, Callable[[_Table], Mesh]] = {
    "beam": _beam,            # cells = [nx, ny, nz], size, origin, cut (tm.beam_mesh)
    "tri_beam": _tri_beam,    # cells = [nx, ny], size, origin, cut (tm.beam_tri_mesh, a membrane at z = 0)
    "sphere": _sphere,        # radius, center, cell (lattice spacing)
    "capsule": _capsule,      # radius, length (of the axis, along x), center, cell
    "rabbit": _rabbit,        # size (body length), origin (centre of the base), cell
}


#: Options of ``mesh = { surface = ... }`` by method, with their TOML kinds.
SURFACE_OPTIONS = {
    "tetgen": {"min_ratio": "positive", "min_dihedral": "nonnegative", "max_volume": "positive", "quality": "bool"},
    "ftetwild": {"edge_length": "positive", "epsilon": "positive"},
}


def _surface(t: _Table, base_dir: Path) -> Mesh:
    from ..mesh.surface import METHODS, tetrahedralize

    file = base_dir / t.get("surface", "str")
    method = _choice(t, "method", list(METHODS), "tetgen", "method")
    options = {key: t.get(key, kind) for key, kind in SURFACE_OPTIONS[method].items() if t.has(key)}
    for other, keys in SURFACE_OPTIONS.items():
        for key in keys:
            if other != method and key not in SURFACE_OPTIONS[method] and key in t.data:
                raise t.error(key, f"is an option of method '{other}', not of '{method}'")
    return file, lambda: tetrahedralize(file, method=method, dtype=torch.float64, **options)


def _mesh(t: _Table, base_dir: Path, device, dtype) -> Mesh:
    sources = [key for key in ("file", "generator", "surface") if t.has(key)]
    if len(sources) != 1:
        raise t.fail(t.where, "give exactly one of 'file' (a volume mesh), 'surface' (a closed triangle surface "
                              f"to tetrahedralize) or 'generator'{'; got ' + ', '.join(sources) if sources else ''}")
    scale = t.get("scale", "positive", 1.0)
    translate = t.get("translate", "vec3", (0.0, 0.0, 0.0))
    if sources == ["file"]:
        file = base_dir / t.get("file", "str")
        orient = t.get("orient", "bool", False)
        t.done()
        if not file.is_file():
            raise t.error("file", f"mesh file not found: '{file}'")
        from ..mesh.io import load_mesh

        try:
            mesh = load_mesh(file, orient=orient)
        except InvertedElementsError as exc:
            raise t.error("file", f"'{file}' has inverted elements: {exc.ids}; add orient = true to this mesh "
                                  "table to flip them") from exc
        except MeshError as exc:
            raise t.error("file", str(exc)) from exc
    elif sources == ["surface"]:
        file, build = _surface(t, base_dir)
        t.done()
        if not file.is_file():
            raise t.error("surface", f"surface file not found: '{file}'")
        try:
            mesh = build()
        except MeshError as exc:
            raise t.error("surface", str(exc)) from exc
    else:
        name = _choice(t, "generator", list(MESH_GENERATORS), what="generator")
        try:
            mesh = MESH_GENERATORS[name](t)
        except MeshError as exc:
            raise t.fail(t.where, str(exc)) from exc
        t.done()
    mesh = mesh.to(device=device, dtype=dtype)
    if scale != 1.0 or any(translate):
        vertices = mesh.vertices * scale
        if vertices.shape[1] == 2:
            vertices = torch.cat([vertices, vertices.new_zeros(vertices.shape[0], 1)], dim=1)
        vertices = vertices + torch.tensor(translate, dtype=dtype, device=device)
        mesh = type(mesh)._trusted(vertices, mesh.elements)
    return mesh


# ---------------------------------------------------------------------------------------------
# Bodies
# ---------------------------------------------------------------------------------------------


def _material(t: _Table, model_override: Optional[str]) -> Material:
    model = _choice(t, "model", MODELS, "hooke", "model")
    kwargs = dict(
        young=t.get("young", "positive"),
        poisson=t.get("poisson", "number"),
        density=t.get("density", "positive", 1000.0),
        thickness=t.get("thickness", "positive", 1.0),
        rotation=_choice(t, "rotation", ROTATIONS, "polar", "rotation"),
        tangent=_choice(t, "tangent", TANGENTS, "auto", "tangent"),
        model=model_override or model,
    )
    t.done()
    try:
        return Material(**kwargs)
    except MaterialError as exc:
        raise t.fail(t.where, str(exc)) from exc


def _selection(t: _Table, mesh: Mesh, extra: Dict[str, str]):
    """Nodes chosen by ``box`` or ``nodes`` -> bool mask ``[V]``, plus the ``extra`` keys' values."""
    if t.has("box") == t.has("nodes"):
        raise t.fail(t.where, "give exactly one of 'box' or 'nodes'")
    values = {key: t.get(key, kind) if not isinstance(kind, tuple) else t.get(key, *kind)
              for key, kind in extra.items()}
    vertices = mesh.vertices
    if vertices.shape[1] == 2:
        vertices = torch.cat([vertices, vertices.new_zeros(vertices.shape[0], 1)], dim=1)
    if t.has("box"):
        lo, hi = t.get("box", "box")
        lo_t = torch.tensor(lo, dtype=vertices.dtype, device=vertices.device)
        hi_t = torch.tensor(hi, dtype=vertices.dtype, device=vertices.device)
        # A box that touches a face of the mesh exactly must catch that face's nodes.
        extent = float((vertices.max(0).values - vertices.min(0).values).norm())
        slack = 1e-6 * max(extent, 1e-30)
        mask = ((vertices >= lo_t - slack) & (vertices <= hi_t + slack)).all(dim=1)
        if not bool(mask.any()):
            bounds = [[round(float(c), 6) for c in vertices.min(0).values],
                      [round(float(c), 6) for c in vertices.max(0).values]]
            raise t.error("box", f"selects no node (box {[list(lo), list(hi)]}, mesh bounds {bounds})")
    else:
        nodes = t.get("nodes", "nodes")
        bad = [n for n in nodes if not 0 <= n < mesh.num_vertices]
        if bad:
            raise t.error("nodes", f"node indices out of range [0, {mesh.num_vertices}): {bad[:10]}")
        mask = torch.zeros(mesh.num_vertices, dtype=torch.bool, device=vertices.device)
        mask[torch.tensor(nodes, device=vertices.device)] = True
    t.done()
    return mask, values


class _LinearMotion:
    """Prescribed nodes moving at a constant velocity until ``stop``: ``motion(t) -> [k, 3]``."""

    def __init__(self, start: torch.Tensor, velocity, stop: float):
        self.start = start
        self.velocity = torch.tensor(velocity, dtype=start.dtype, device=start.device)
        self.stop = stop

    def __call__(self, t: float) -> torch.Tensor:
        return self.start + self.velocity * min(t, self.stop)


def _body(t: _Table, index: int, base_dir: Path, device, dtype, model_override) -> Body:
    name = t.get("name", "str", f"body{index}")
    mesh = _mesh(t.table("mesh", required=True), base_dir, device, dtype)
    material = _material(t.table("material", required=True), model_override)
    fixed = prescribed = motion = None
    fixed_table = t.table("fixed")
    if fixed_table is not None:
        fixed, _ = _selection(fixed_table, mesh, {})
    prescribed_table = t.table("prescribed")
    if prescribed_table is not None:
        prescribed, opts = _selection(prescribed_table, mesh,
                                      {"velocity": "vec3", "stop": ("nonnegative", math.inf)})
        start = mesh.vertices[prescribed]
        if start.shape[1] == 2:
            start = torch.cat([start, start.new_zeros(start.shape[0], 1)], dim=1)
        motion = _LinearMotion(start, opts["velocity"], opts["stop"])
    velocity = t.get("velocity", "vec3", None)
    t.done()
    try:
        return Body(mesh, material, fixed=fixed, prescribed=prescribed, motion=motion,
                    velocity=None if velocity is None else list(velocity), name=name)
    except SceneError as exc:
        raise t.fail(t.where, str(exc)) from exc


# ---------------------------------------------------------------------------------------------
# The scene
# ---------------------------------------------------------------------------------------------


def _spare_nodes(t: _Table):
    """A ``[[bodies]]`` table's ``spare_nodes`` (an integer >= 0), or None where it has none."""
    value = t.get("spare_nodes", "int", None)
    if value is not None and value < 0:
        raise t.error("spare_nodes", f"must be >= 0, got {value}")
    return value


#: ``[[tools]]`` shapes: the tool constructor and the keys of its size, in its argument order
TOOL_SHAPES = {"sphere": (Sphere, (("radius", "positive"),)),
               "capsule": (Capsule, (("radius", "positive"), ("half_length", "nonnegative"))),
               "box": (Box, (("half_extents", "vec3"),)),
               "mesh": (MeshTool, (("file", "str"),))}


def _tool(t: _Table, base_dir: Path) -> Tool:
    """A ``[[tools]]`` table: shape and its sizes (a mesh: its file, relative to ``base_dir``,
    and resolution), position or keyframes (times, positions), rotation, stiffness, thickness,
    name, tangent, friction, friction_velocity."""
    shape = _choice(t, "shape", tuple(TOOL_SHAPES), what="tool shape")
    make, sizes = TOOL_SHAPES[shape]
    args = [t.get(key, kind) for key, kind in sizes]
    if shape == "mesh":
        args = [base_dir / args[0]]
        if not args[0].is_file():
            raise t.error("file", f"tool surface file not found: '{args[0]}'")
    kwargs = dict(position=t.get("position", "vec3", (0.0, 0.0, 0.0)), stiffness=t.get("stiffness", "positive", 1e5),
                  thickness=t.get("thickness", "nonnegative", 0.0), name=t.get("name", "str", None),
                  tangent=_choice(t, "tangent", TOOL_TANGENTS, "projected", "tool tangent"),
                  friction=t.get("friction", "nonnegative", 0.0),
                  friction_velocity=t.get("friction_velocity", "positive", 1e-3))
    if shape != "sphere":
        rotation = t.data.get("rotation")
        t.seen.add("rotation")
        if rotation is not None:
            if not isinstance(rotation, list) or len(rotation) != 3:
                raise t.error("rotation", f"must be 3 rows [[..], [..], [..]], got {_describe(rotation)}")
            rotation = [_check(r, "vec3", lambda msg, i=i: t.error("rotation", f"row {i} {msg}"))
                        for i, r in enumerate(rotation)]
        kwargs["rotation"] = rotation
    times = t.data.get("times")
    t.seen.update(("times", "positions"))
    if times is not None:
        if not isinstance(times, list) or not times:
            raise t.error("times", f"must be a list of keyframe times, got {_describe(times)}")
        times = [_check(v, "number", lambda msg, i=i: t.error("times", f"entry {i} {msg}"))
                 for i, v in enumerate(times)]
        positions = t.data.get("positions")
        if not isinstance(positions, list) or len(positions) != len(times):
            raise t.error("positions", f"must be a list of {len(times)} points (one per time), "
                                       f"got {_describe(positions)}")
        kwargs["times"] = times
        kwargs["positions"] = [_check(p, "vec3", lambda msg, i=i: t.error("positions", f"entry {i} {msg}"))
                               for i, p in enumerate(positions)]
    elif "positions" in t.data:
        raise t.error("positions", "needs times = [...] (one per position)")
    if shape == "mesh":
        kwargs["resolution"] = t.get("resolution", "posint", 32)
    t.done()
    try:
        return make(*args, **kwargs)
    except (SceneError, MeshError) as exc:
        raise t.fail(t.where, str(exc)) from exc


def _scalpel(t: _Table) -> Scalpel:
    """A ``[[cuts]]`` table: body, times [K], edges [K, 2, 3]."""
    t.seen.add("body")
    body = t.data.get("body", 0)
    if isinstance(body, bool) or not isinstance(body, (int, str)):
        raise t.error("body", f"must be a body's name or index, got {_describe(body)}")
    times = t.data.get("times")
    t.seen.update(("times", "edges"))
    if not isinstance(times, list) or len(times) < 2:
        raise t.error("times", f"must be a list of at least 2 keyframe times, got {_describe(times)}")
    times = [_check(v, "number", lambda msg, i=i: t.error("times", f"entry {i} {msg}")) for i, v in enumerate(times)]
    edges = t.data.get("edges")
    if not isinstance(edges, list) or len(edges) != len(times):
        raise t.error("edges", f"must be a list of {len(times)} edges (one per time), each two points "
                               f"[[x, y, z], [x, y, z]], got {_describe(edges)}")
    points = []
    for i, edge in enumerate(edges):
        if not isinstance(edge, list) or len(edge) != 2:
            raise t.error("edges", f"entry {i} must be two points [[x, y, z], [x, y, z]], got {_describe(edge)}")
        points.append([_check(p, "vec3", lambda msg, i=i, j=j: t.error("edges", f"entry {i} point {j} {msg}"))
                       for j, p in enumerate(edge)])
    t.done()
    try:
        return Scalpel(body, times, points)
    except SceneError as exc:
        raise t.error("times", str(exc)) from exc


def _device(t: _Table, override) -> torch.device:
    text = override if override is not None else t.get("device", "str", "cpu")
    t.seen.add("device")
    try:
        device = torch.device(text)
    except (RuntimeError, TypeError) as exc:
        raise t.error("device", f"not a torch device: {text!r}") from exc
    if device.type == "cuda" and not torch.cuda.is_available():
        raise t.error("device", f"{text!r} requested but torch sees no CUDA device")
    return device


#: how a scene is spread over the processes of a group (``[distributed] split``)
SPLITS = ["bodies", "mesh"]


def _check_mesh_split(bodies, options, planes, tools, contact, scalpels, select, fail) -> None:
    """One SceneError naming what a scene split by mesh has that the partitioned step does not do."""
    problems = []
    if len(bodies) != 1:
        problems.append(f"{len(bodies)} bodies (one body's mesh is what is partitioned)")
    if any(b.motion is not None for b in bodies):
        problems.append("prescribed nodes")
    if tools:
        problems.append("tools")
    if contact is not None:
        problems.append("contact between bodies")
    if scalpels:
        problems.append("cuts")
    if any(p.friction > 0 for p in planes):
        problems.append("friction on a plane")
    unsupported = {"newton_iters": 1, "integrator": "backward_euler", "warm_start": "none",
                   "require_convergence": True, "precision": "full"}
    problems += [f"[solver] {key} = {options[key]!r}" for key, value in unsupported.items()
                 if options[key] != value]
    if options["preconditioner"] not in ("auto", "none"):
        problems.append(f"[solver] preconditioner = {options['preconditioner']!r}")
    if select is not None:
        problems.append("a selection of bodies")
    if problems:
        raise fail("distributed.split", "a mesh partitioned over processes takes one body stepped by backward "
                                        "Euler to convergence, with fixed nodes and frictionless planes; this "
                                        "scene has " + ", ".join(problems))


def _partitioned(body, dt, gravity, planes, options, device, dtype, fail):
    """The rank's ``PartitionedSimulator`` of ``body`` in a process group of several, else None."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() < 2:
        return None
    from .partitioned import PartitionedSimulator

    try:
        return PartitionedSimulator(body, dt=dt, gravity=gravity, rayleigh_mass=options["rayleigh_mass"],
                                    rayleigh_stiffness=options["rayleigh_stiffness"], planes=planes,
                                    cg_tol=options["cg_tol"], cg_max_iter=options["cg_max_iter"], device=device,
                                    dtype=dtype)
    except (SceneError, MaterialError, MeshError) as exc:
        raise fail("", str(exc)) from exc


def _peek(path) -> dict:
    """The file's TOML, read without checking or building anything ({} where it cannot be read:
    :func:`load_scene` names the problem)."""
    try:
        return tomllib.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, AttributeError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return {}


def scene_split(path) -> str:
    """The file's ``[distributed] split`` (``"bodies"`` where it has none), read without building
    anything; :func:`load_scene` checks it with the rest."""
    table = _peek(path).get("distributed")
    return table.get("split", "bodies") if isinstance(table, dict) else "bodies"


def scene_device(path) -> Optional[str]:
    """The file's ``device`` (None where it has none), read without building anything: a process
    group is started for it before the scene is loaded (NCCL and a GPU a rank for CUDA)."""
    device = _peek(path).get("device")
    try:
        return str(torch.device(device)) if isinstance(device, str) else None
    except RuntimeError:  # (not a device: load_scene names it)
        return None


def load_scene(path, *, device=None, dtype=None, model: Optional[str] = None,
               select: Optional[Callable[[List[Body]], Sequence[int]]] = None,
               split: Optional[str] = None) -> FileScene:
    """Read, check and build a TOML scene file.

    Args:
        path: the ``.toml`` file; mesh files in it are relative to its folder.
        device, dtype: override the file's ``device`` / ``dtype`` (a torch device or string; a
            torch dtype or ``"float32"`` / ``"float64"``).
        model: override every body's material model (one of ``tm.MODELS``).
        select: ``bodies -> indices``: build the simulator of these of the file's bodies only
            (a process's share of a batch over several: ``sim.distributed``); ``body_ids`` says
            which. Bodies of the scene's other parts (contact between bodies, scalpels) must
            then be among them; an empty selection builds no simulator (``simulator`` None).
        split: override the file's ``[distributed] split``. ``"mesh"``: in a process group of
            several (``torch.distributed``, as torchrun starts), ``simulator`` is this rank's
            :class:`PartitionedSimulator` of the scene's one body; in one process the usual
            ``Simulator`` (the same physics). The scene must then be what the partitioned step
            does: one body, no prescribed nodes, tools, contact between bodies, scalpels or
            friction, backward Euler with one Newton iteration and CG to convergence.

    Returns:
        a :class:`FileScene` holding the built :class:`Simulator`.

    Raises:
        SceneError: one line naming the file and the key path of the first problem (a TOML
            syntax error, an unknown key, a wrong type, a missing mesh file, an unknown model,
            a box selecting no node, ...). Nothing is written.
    """
    path = Path(path)

    def fail(where: str, message: str) -> SceneError:
        return SceneError(f"{path}: {where}: {message}" if where else f"{path}: {message}")

    if not path.is_file():
        raise SceneError(f"scene file not found: '{path}'")
    if tomllib is None:
        raise SceneError(f"{path}: reading scene files needs Python >= 3.11 (tomllib) or `pip install tomli`")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: invalid TOML: {exc}") from exc
    if model is not None and model not in MODELS:
        raise SceneError(f"unknown model {model!r}; expected one of {', '.join(MODELS)}")

    top = _Table(data, "", fail)
    name = top.get("name", "str", path.stem)
    description = top.get("description", "str", "")
    dt = top.get("dt", "positive", 0.01)
    steps = top.get("steps", "posint", 100)
    output_every = top.get("output_every", "posint", 10)
    gravity = top.get("gravity", "vec3", (0.0, 0.0, -9.81))
    torch_device = _device(top, device)
    if dtype is None:
        torch_dtype = DTYPES[_choice(top, "dtype", list(DTYPES), "float32", "dtype")]
    else:
        top.seen.add("dtype")
        torch_dtype = DTYPES[dtype] if isinstance(dtype, str) else dtype

    solver = top.table("solver") or _Table({}, "solver", fail)
    options = dict(
        cg_tol=solver.get("cg_tol", "positive", 1e-6),
        cg_max_iter=solver.get("cg_max_iter", "posint", None),
        require_convergence=solver.get("require_convergence", "bool", True),
        newton_iters=solver.get("newton_iters", "posint", 1),
        check_every=solver.get("check_every", "posint", 8),
        rayleigh_mass=solver.get("rayleigh_mass", "nonnegative", 0.0),
        rayleigh_stiffness=solver.get("rayleigh_stiffness", "nonnegative", 0.0),
        form=_choice(solver, "form", FORMS, "auto", "form"),
        preconditioner=_choice(solver, "preconditioner", PRECONDITIONERS, "auto", "preconditioner"),
        integrator=_choice(solver, "integrator", list(INTEGRATORS), "backward_euler", "integrator"),
        warm_start=_warm_start(solver),
        paired_blocks=solver.get("paired_blocks", "bool", True),
        precision=_choice(solver, "precision", list(PRECISIONS), "full", "precision"),
        check_memory=solver.get("check_memory", "bool", True),
        cut_on_device=solver.get("cut_on_device", "bool", False),
    )
    solver.done()

    render_table = top.table("render") or _Table({}, "render", fail)
    render = dict(png=render_table.get("png", "bool", False), gif=render_table.get("gif", "bool", False),
                  window_size=render_table.get("window_size", "posintvec2", (800, 600)))
    render_table.done()

    planes = []
    for plane in top.tables("planes"):
        normal = plane.get("normal", "vec3")
        if not any(normal):
            raise plane.error("normal", "must not be the zero vector")
        planes.append(Plane(normal, plane.get("offset", "number", 0.0), plane.get("stiffness", "positive"),
                            friction=plane.get("friction", "nonnegative", 0.0),
                            friction_velocity=plane.get("friction_velocity", "positive", 1e-3)))
        plane.done()

    tools = [_tool(t, path.parent) for t in top.tables("tools")]
    contact_table = top.table("contact")
    contact = None
    if contact_table is not None:
        search = contact_table.get("search", "positive", None)
        contact = Contact(stiffness=contact_table.get("stiffness", "positive", 1e5),
                          thickness=contact_table.get("thickness", "nonnegative", 0.0), search=search,
                          self_contact=contact_table.get("self_contact", "bool", False),
                          swept=contact_table.get("swept", "bool", True),
                          friction=contact_table.get("friction", "nonnegative", 0.0),
                          friction_velocity=contact_table.get("friction_velocity", "positive", 1e-3),
                          rounds=contact_table.get("rounds", "nonnegative_int", Contact.rounds),
                          tolerance=contact_table.get("tolerance", "positive", None),
                          recheck_tolerance=contact_table.get("recheck_tolerance", "positive", None),
                          check_tol=_check_tol(contact_table),
                          skin=contact_table.get("skin", "nonnegative", None),
                          check_margin=contact_table.get("check_margin", "nonnegative", None),
                          tangent=_choice(contact_table, "tangent", CONTACT_TANGENTS, "projected", "contact tangent"))
        contact_table.done()
    distributed_table = top.table("distributed") or _Table({}, "distributed", fail)
    file_split = _choice(distributed_table, "split", SPLITS, "bodies", "split")
    distributed_table.done()
    if split is not None and split not in SPLITS:
        raise SceneError(f"unknown split {split!r}; expected one of {', '.join(SPLITS)}")
    split = split or file_split
    cut_tables = top.tables("cuts")
    scalpels = [_scalpel(c) for c in cut_tables]
    body_tables = top.tables("bodies")
    top.done()  # every top-level key is known before the (possibly slow) meshes are built
    if not body_tables:
        raise fail("bodies", "a scene needs at least one [[bodies]] table")
    spare = [_spare_nodes(b) for b in body_tables]
    bodies = [_body(b, i, path.parent, torch_device, torch_dtype, model) for i, b in enumerate(body_tables)]
    # a body a scalpel cuts gets room for cuts in place from the start (unless the file says)
    targets = {scalpel.body for scalpel in scalpels}
    spare = [(max(MIN_SPARE_NODES, b.mesh.num_vertices // SPARE_FRACTION)
              if {i, i - len(bodies), b.name} & targets else 0) if room is None else room
             for i, (b, room) in enumerate(zip(bodies, spare))]
    if split == "mesh":
        _check_mesh_split(bodies, options, planes, tools, contact, scalpels, select, fail)
        partitioned = _partitioned(bodies[0], dt, gravity, planes, options, torch_device, torch_dtype, fail)
        if partitioned is not None:
            if not description:
                description = (f"{name}: 1 body of {bodies[0].mesh.num_elements} elements over "
                               f"{partitioned.world} processes, dt {dt:g} s, {steps} steps")
            return FileScene(name, partitioned, steps, output_every, description, path=path, render=render,
                             body_ids=[0])
    body_ids = list(range(len(bodies)))
    if select is not None:
        body_ids = sorted({int(i) for i in select(bodies)})
        if any(not 0 <= i < len(bodies) for i in body_ids):
            raise fail("bodies", f"select chose bodies {body_ids}; the file has {len(bodies)}")
        if len(body_ids) < len(bodies) and (contact is not None or scalpels):
            raise fail("", "a scene with contact between bodies or scalpels runs with all of its bodies in one "
                           "process (its bodies meet or are cut by name and index)")
        bodies, spare = [bodies[i] for i in body_ids], [spare[i] for i in body_ids]
        if not bodies:
            return FileScene(name, None, steps, output_every, description or name, path=path, render=render,
                             body_ids=[])

    try:
        simulator = Simulator(bodies, dt=dt, gravity=gravity, planes=planes, device=torch_device,
                              dtype=torch_dtype, spare_nodes=spare, tools=tools, contact=contact, **options)
    except (SceneError, MaterialError, MeshError) as exc:
        raise fail("", str(exc)) from exc
    for table, scalpel in zip(cut_tables, scalpels):
        try:
            simulator.add_scalpel(scalpel)
        except SceneError as exc:
            raise table.error("body", str(exc)) from exc
    if not description:
        tets = sum(b.mesh.num_elements for b in bodies)
        description = f"{name}: {len(bodies)} bodies, {tets} elements, dt {dt:g} s, {steps} steps"
    return FileScene(name, simulator, steps, output_every, description, path=path, render=render,
                     body_ids=body_ids)
