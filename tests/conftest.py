"""Shared fixtures of the physics tests: small jittered meshes, random materials, large deformations.

Everything is float64 on the CPU unless a test asks otherwise. Every test gets its own seed
(derived from its node id, so each parametrization has a fresh, reproducible one; the
environment variable ``TENSORMASS_TEST_SEED`` shifts them all) through the ``rng`` fixture, and
the factories below draw from it.

Element kinds (``KINDS``):
    ``tet``    a jittered 2 x 2 x 2 hex beam cut into 48 tetrahedra (TetMesh, [V, 3]);
    ``tri2d``  a jittered 3 x 3 quad rectangle cut into 18 triangles (TriMesh, [V, 2]);
    ``tri3d``  the same triangles lifted to 3-D, bent out of plane (a saddle plus a bend) and
               rigidly rotated and moved at random (TriMesh, [V, 3]); ``flat=True`` keeps it
               planar (only rotated/moved), for the tests that need a plane (patch test, FEM).
"""
from __future__ import annotations

import gc
import os
import zlib
from dataclasses import dataclass
from typing import Optional

import numpy as np
import pytest
import torch
from torch._subclasses.fake_tensor import FakeTensor

from tensormass_torch import Material, TetMesh, TriMesh, beam_mesh, beam_tri_mesh

KINDS = ("tet", "tri2d", "tri3d")
MODELS = ("hooke", "stvk")
FORMS = ("stress", "tensor")


@dataclass
class Scene:
    """A rest mesh and what the tests need to know about it."""

    kind: str                     # "tet" | "tri2d" | "tri3d"
    mesh: object                  # TetMesh | TriMesh
    rest: torch.Tensor            # [V, d] float64 rest positions (== mesh.vertices)
    interior: torch.Tensor        # [V] bool: nodes not on the boundary of the grid
    size: float                   # characteristic size of the object (largest box side)
    frame: Optional[np.ndarray]   # tri3d flat: [3, 2] orthonormal basis of the plane; else None

    @property
    def dim(self) -> int:
        return self.rest.shape[1]

    @property
    def elements(self) -> torch.Tensor:
        return self.mesh.elements


def random_rotation(rng: np.random.Generator, dim: int) -> np.ndarray:
    """A uniformly random proper rotation ``[dim, dim]`` (QR of a Gaussian matrix, sign-fixed)."""
    q, r = np.linalg.qr(rng.standard_normal((dim, dim)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def axis_rotation(axis, angle: float) -> np.ndarray:
    """Rotation by ``angle`` about ``axis`` (3-D, Rodrigues) or about the origin (2-D: axis None)."""
    c, s = np.cos(angle), np.sin(angle)
    if axis is None:
        return np.array([[c, -s], [s, c]])
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + s * k + (1 - c) * k @ k


def u_shape_surface(dtype=torch.float64):
    """A closed, non-convex surface: a block of 3 x 1 x 2 cells (0.3 x 0.1 x 0.2) without its
    middle top cell (vertices ``[V, 3]``, outward triangles ``[F, 3]``)."""
    from tensormass_torch.mesh.topology import boundary_faces

    mesh = beam_mesh(3, 1, 2, size=(0.3, 0.1, 0.2), dtype=dtype)
    centroids = mesh.vertices[mesh.elements].mean(1)
    notch = (centroids[:, 0] > 0.1) & (centroids[:, 0] < 0.2) & (centroids[:, 2] > 0.1)
    return mesh.vertices, boundary_faces(mesh.elements[~notch])


def rel_err(a, b) -> float:
    """||a - b|| / ||b|| (Frobenius), with tensors or arrays."""
    a = torch.as_tensor(a, dtype=torch.float64)
    b = torch.as_tensor(b, dtype=torch.float64)
    return float(torch.linalg.norm(a - b) / torch.linalg.norm(b))


def _seed(nodeid: str) -> int:
    # TENSORMASS_TEST_SEED shifts every seed (to fuzz the physics tests over more draws).
    return zlib.crc32(nodeid.encode()) + int(os.environ.get("TENSORMASS_TEST_SEED", "0"))


@pytest.fixture
def rng(request) -> np.random.Generator:
    """A generator seeded from the test's node id: fresh per parametrization, reproducible."""
    return np.random.default_rng(_seed(request.node.nodeid))


def build_scene(rng: np.random.Generator, kind: str, cells=None, jitter: float = 0.12,
                flat: bool = False, size=None) -> Scene:
    """A jittered small mesh of ``kind``; ``jitter`` is relative to the smallest cell side."""
    if kind == "tet":
        cells = cells or (2, 2, 2)
        size = size or (1.0, 0.8, 0.6)
        base = beam_mesh(*cells, size=size, dtype=torch.float64)
    elif kind in ("tri2d", "tri3d"):
        cells = cells or (3, 3)
        size = size or (1.0, 0.8)
        base = beam_tri_mesh(*cells, size=size, dim=2, dtype=torch.float64)
    else:
        raise ValueError(kind)
    grid = base.vertices.numpy()
    lo, hi = grid.min(0), grid.max(0)
    interior = np.all((grid > lo + 1e-9) & (grid < hi - 1e-9), axis=1)
    h = min(s / n for s, n in zip(size, cells))
    v = grid + rng.uniform(-jitter * h, jitter * h, grid.shape)
    frame = None
    if kind == "tri3d":
        z = np.zeros((v.shape[0], 1))
        if not flat:  # bend out of plane: a saddle and a cylinder-like bend, ~20% of the size
            z[:, 0] = 0.35 * (v[:, 0] - 0.5) * (v[:, 1] - 0.4) + 0.25 * v[:, 0] ** 2
        rot = random_rotation(rng, 3)
        v = np.concatenate([v, z], axis=1) @ rot.T + rng.uniform(-1, 1, 3)
        frame = rot[:, :2] if flat else None
    vertices = torch.tensor(v, dtype=torch.float64)
    mesh = TetMesh(vertices, base.elements) if kind == "tet" else TriMesh(vertices, base.elements)
    return Scene(kind, mesh, mesh.vertices, torch.tensor(interior), float(max(size)), frame)


def random_material(rng: np.random.Generator, model: str, **overrides) -> Material:
    """A random material (E in [1e3, 1e5], nu in [0.1, 0.45], rho in [500, 2000], t in [0.02, 0.2])
    with the exact tangent (the tests of the physics compare it with the energy's Hessian)."""
    params = dict(young=float(rng.uniform(1e3, 1e5)), poisson=float(rng.uniform(0.1, 0.45)),
                  density=float(rng.uniform(500, 2000)), thickness=float(rng.uniform(0.02, 0.2)), tangent="exact")
    params.update(overrides)
    return Material(model=model, **params)


def large_deformation(rng: np.random.Generator, scene: Scene, amplitude=(0.1, 0.3), rotate: bool = True,
                      noise: float = 0.05) -> torch.Tensor:
    """Positions ``[V, d]`` float64: a smooth random map with displacements of ``amplitude`` x size
    (an affine part plus a quadratic bend), nodal noise of ``noise`` x size, then a random rigid
    rotation and translation when ``rotate``."""
    X = scene.rest.numpy()
    d = X.shape[1]
    c = X.mean(0)
    Y = (X - c) / scene.size
    amp = rng.uniform(*amplitude)
    A = rng.uniform(-1, 1, (d, d))
    Q = rng.uniform(-1, 1, (d, d, d))
    u = Y @ A.T + np.einsum("aij,vi,vj->va", Q, Y, Y)
    u = amp * scene.size * u / np.abs(u).max()
    u = u + noise * scene.size * rng.uniform(-1, 1, u.shape)
    x = X + u
    if rotate:
        R = random_rotation(rng, d)
        x = (x - c) @ R.T + c + rng.uniform(-0.5, 0.5, d) * scene.size
    return torch.tensor(x, dtype=torch.float64)


# ---------------------------------------------------------------------------------------------
# Independent P1 finite-element oracle (numpy, dense), shared by the physics tests
# ---------------------------------------------------------------------------------------------


def per_element(value, n) -> np.ndarray:
    """A scalar or ``[n]`` parameter (float or tensor) as a float64 numpy array ``[n]``."""
    a = np.asarray(torch.as_tensor(value, dtype=torch.float64).detach().numpy(), float)
    return np.broadcast_to(a, (n,)).copy()


def element_measures(scene, thickness=1.0) -> np.ndarray:
    """|volume| of tets, |area| x thickness of triangles, from numpy determinants/cross products."""
    X = scene.rest.numpy()[scene.elements.numpy()]
    if scene.kind == "tet":
        return np.abs(np.linalg.det(X[:, 1:] - X[:, :1])) / 6.0
    e1, e2 = X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]
    if X.shape[-1] == 2:
        area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    else:
        area = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1)
    return area * per_element(thickness, X.shape[0])


def fem_stiffness(scene, young, poisson, thickness=1.0) -> np.ndarray:
    """Global stiffness ``[V d, V d]`` of linear P1 elasticity, standard B-matrix FEM.

    Tets: Voigt strain (xx, yy, zz, 2yz, 2xz, 2xy), D = lam 1 1^T + mu diag(2, 2, 2, 1, 1, 1).
    Triangles: plane stress in the element's own orthonormal frame (t1, t2), strain (xx, yy, 2xy),
    D = E / (1 - nu^2) [[1, nu, 0], [nu, 1, 0], [0, 0, (1 - nu) / 2]], measure area x thickness;
    in 3-D the 6 x 6 local matrix is rotated to the global frame by blocks of [t1 t2] (3 x 2).
    Shape-function gradients come from inverting [1, x, y(, z)] -- not from geometry.py.
    """
    X = scene.rest.numpy()
    T = scene.elements.numpy()
    V, d = X.shape
    n_elem, n = T.shape
    E = per_element(young, n_elem)
    nu = per_element(poisson, n_elem)
    th = per_element(thickness, n_elem)
    K = np.zeros((V * d, V * d))
    for e, nodes in enumerate(T):
        Xe = X[nodes]
        if n == 4:
            M = np.hstack([np.ones((4, 1)), Xe])
            G = np.linalg.inv(M)[1:, :].T  # [4, 3]: row j = grad N_j
            vol = abs(np.linalg.det(M)) / 6.0
            B = np.zeros((6, 12))
            for j, (gx, gy, gz) in enumerate(G):
                B[:, 3 * j:3 * j + 3] = [[gx, 0, 0], [0, gy, 0], [0, 0, gz], [0, gz, gy], [gz, 0, gx], [gy, gx, 0]]
            lam = E[e] * nu[e] / ((1 + nu[e]) * (1 - 2 * nu[e]))
            mu = E[e] / (2 * (1 + nu[e]))
            D = lam * np.outer([1, 1, 1, 0, 0, 0], [1, 1, 1, 0, 0, 0]) + mu * np.diag([2, 2, 2, 1, 1, 1])
            Ke = vol * B.T @ D @ B
        else:
            if d == 3:
                t1 = Xe[1] - Xe[0]
                t1 /= np.linalg.norm(t1)
                nrm = np.cross(Xe[1] - Xe[0], Xe[2] - Xe[0])
                nrm /= np.linalg.norm(nrm)
                frame = np.stack([t1, np.cross(nrm, t1)], axis=1)  # [3, 2]
            else:
                frame = np.eye(2)
            Xl = (Xe - Xe[0]) @ frame
            M = np.hstack([np.ones((3, 1)), Xl])
            G = np.linalg.inv(M)[1:, :].T  # [3, 2]
            area = abs(np.linalg.det(M)) / 2.0
            B = np.zeros((3, 6))
            for j, (gx, gy) in enumerate(G):
                B[:, 2 * j:2 * j + 2] = [[gx, 0], [0, gy], [gy, gx]]
            D = E[e] / (1 - nu[e] ** 2) * np.array([[1, nu[e], 0], [nu[e], 1, 0], [0, 0, (1 - nu[e]) / 2]])
            K2 = th[e] * area * B.T @ D @ B
            Tb = np.kron(np.eye(3), frame)  # [3 d, 6]
            Ke = Tb @ K2 @ Tb.T
        dofs = (d * nodes[:, None] + np.arange(d)).reshape(-1)
        K[np.ix_(dofs, dofs)] += Ke
    return K


def shape_gradients(scene):
    """Independent shape vectors (numpy): m ``[N, n, d]`` (grad of the barycentric coordinates,
    in the element's plane for membranes), |measure| ``[N]`` (thickness not applied) and the
    tangent projectors ``[N, d, d]`` (identity for tets and 2-D triangles)."""
    X = scene.rest.numpy()[scene.elements.numpy()]  # [N, n, d]
    N, n, d = X.shape
    m = np.zeros((N, n, d))
    measure = np.zeros(N)
    proj = np.tile(np.eye(d), (N, 1, 1))
    for e, Xe in enumerate(X):
        if n == 4 or d == 2:
            M = np.hstack([np.ones((n, 1)), Xe])
            m[e] = np.linalg.inv(M)[1:, :].T
            measure[e] = abs(np.linalg.det(M)) / (6.0 if n == 4 else 2.0)
        else:  # membrane: 2-D gradients in an orthonormal frame of the plane, mapped back to 3-D
            nrm = np.cross(Xe[1] - Xe[0], Xe[2] - Xe[0])
            measure[e] = 0.5 * np.linalg.norm(nrm)
            nrm /= np.linalg.norm(nrm)
            t1 = (Xe[1] - Xe[0]) / np.linalg.norm(Xe[1] - Xe[0])
            frame = np.stack([t1, np.cross(nrm, t1)], axis=1)
            M = np.hstack([np.ones((3, 1)), (Xe - Xe[0]) @ frame])
            m[e] = np.linalg.inv(M)[1:, :].T @ frame.T
            proj[e] = np.eye(3) - np.outer(nrm, nrm)
    return m, measure, proj


@pytest.fixture
def make_scene(rng):
    """Factory ``make_scene(kind, cells=None, jitter=0.12, flat=False, size=None) -> Scene``."""
    return lambda kind, **kw: build_scene(rng, kind, **kw)


@pytest.fixture
def make_material(rng):
    """Factory ``make_material(model, **overrides) -> Material`` (random parameters)."""
    return lambda model, **kw: random_material(rng, model, **kw)


@pytest.fixture
def deform(rng):
    """Factory ``deform(scene, amplitude=(0.1, 0.3), rotate=True, noise=0.05) -> x [V, d]``."""
    return lambda scene, **kw: large_deformation(rng, scene, **kw)


def beam_scene_file(path, solver: str, cells=(2, 1, 1), steps: int = 2, header: str = ""):
    """Write a scene file at ``path`` of one clamped hooke beam (1 x 0.5 x 0.5, ``cells``) with the
    ``[solver]`` table's lines ``solver`` (and top-level lines ``header``); returns ``path``."""
    path.write_text(f"""
dt = 0.01
steps = {steps}
{header}
[solver]
{solver}
[[bodies]]
mesh = {{ generator = "beam", cells = {list(cells)}, size = [1.0, 0.5, 0.5] }}
material = {{ model = "hooke", young = 1e5, poisson = 0.3, density = 1000.0 }}
fixed = {{ box = [[0.0, 0.0, 0.0], [0.0, 0.5, 0.5]] }}
""")
    return path


def on_each_cpu_backend(monkeypatch, run):
    """``[run() with the CPU extension's kernels, run() with the pure-torch ops]``
    (``TENSORMASS_BACKEND``); skips the test where the CPU extension is not built."""
    from tensormass_torch import _backend

    if not _backend.use_extension("cpu"):
        pytest.skip("the CPU extension is not built")
    results = []
    for mode in ("extension", "torch"):
        monkeypatch.setenv("TENSORMASS_BACKEND", mode)
        results.append(run())
    return results


def live_tensors():
    """(count, bytes of distinct storages) of the tensors the Python heap holds (fake tensors,
    which have no storage, left out)."""
    gc.collect()
    count, storages = 0, {}
    for obj in gc.get_objects():
        if issubclass(type(obj), torch.Tensor) and not isinstance(obj, FakeTensor):
            count += 1
            s = obj.untyped_storage()
            storages[(obj.device, s.data_ptr())] = s.nbytes()
    return count, sum(storages.values())


# ---------------------------------------------------------------- shared by the native-op tests

FORMS = ("stress", "tensor")
DTYPES = (torch.float64, torch.float32)
CASES = [pytest.param(k, m, f, id=f"{k}-{m}-{f}") for k in KINDS for m in MODELS for f in FORMS]


def tol(dtype, group=None):
    """Relative (norm-wise) tolerance of "equal to rounding". The stvk tensor form is a quartic
    polynomial in the absolute displacements: with a rigid motion on top its float32 rounding
    grows to ~3e-5 (see physics/test_forces_energy_tangent.py::test_float32_matches_float64), the others stay < 2e-6."""
    if dtype == torch.float64:
        return 1e-12
    if group is not None and group.form == "tensor" and group.model == "stvk":
        return 5e-4
    return 2e-5


def rel(a, b) -> float:
    """||a - b|| / ||b|| in float64."""
    a, b = a.double(), b.double()
    return float(torch.linalg.norm(a - b) / torch.linalg.norm(b).clamp_min(1e-300))


def load_native(*ops):
    """``tensormass_torch.ops.native`` (the group-level calls onto the compiled ops) when the
    compiled extension is built, its op families registered (``library.available()``) and it has
    ``ops``; else None. The ops' references: ``library.REGISTRY[name].reference``."""
    import importlib

    try:
        importlib.import_module("tensormass_torch._C")
    except ImportError:
        return None
    from tensormass_torch.ops import library, native

    if not library.available() or not all(hasattr(torch.ops.tensormass, op) for op in ops):
        return None
    return native


def reference(name: str):
    """The pure-torch reference of the op ``tensormass::<name>`` (its oracle, the op's signature)."""
    import importlib

    from tensormass_torch.ops import library

    for family in library.FAMILIES:  # each family module declares its ops (their references)
        importlib.import_module(f"tensormass_torch.ops.{family}")
    return library.REGISTRY[name].reference


def with_variants(sim, base=None, **changes):
    """``sim`` (a Simulator) with its steps' kernel variants ``base`` (a ``KernelVariants``; None:
    the defaults) with ``changes``: through its step options (``StepOptions.variants``), which
    the solver passes down to every op. Returns ``sim``."""
    import dataclasses

    from tensormass_torch.ops.variants import KernelVariants

    variants = (KernelVariants() if base is None else base).replace(**changes)
    sim.options = dataclasses.replace(sim.options, variants=variants)
    return sim


REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_script(folder: str, name: str):
    """The module of the script ``REPO/folder/name.py`` (benchmarks and examples are scripts, not
    packages), loaded by its path."""
    import importlib.util

    module_name = f"{folder}_{name}".replace("/", "_")
    spec = importlib.util.spec_from_file_location(module_name, os.path.join(REPO, folder, f"{name}.py"))
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def group_meshes(dtype=torch.float64):
    """One small mesh per element-group kind: ``{"tet", "tri2d", "membrane"}`` (the membrane
    lifted out of its plane, so that its projectors are not the identity's block)."""
    tet = beam_mesh(2, 2, 3, size=(0.1, 0.1, 0.3), dtype=dtype)
    planar = beam_tri_mesh(3, 2, size=(0.3, 0.2), dtype=dtype)
    membrane = beam_tri_mesh(3, 2, size=(0.3, 0.2), dim=3, dtype=dtype)
    gen = torch.Generator().manual_seed(0)
    lifted = membrane.vertices + torch.cat([torch.zeros(membrane.num_vertices, 2, dtype=dtype),
                                            0.05 * torch.rand(membrane.num_vertices, 1, generator=gen, dtype=dtype)], 1)
    return {"tet": tet, "tri2d": planar, "membrane": TriMesh(lifted, membrane.elements)}


#: (kind, model, form) of every element group a model builds (membranes have no corotational model)
GROUP_CASES = [(kind, model, form) for kind in ("tet", "tri2d", "membrane")
               for model, form in (("hooke", "tensor"), ("hooke", "stress"), ("stvk", "tensor"), ("stvk", "stress"),
                                   ("corotational", "stress"))
               if not (kind == "membrane" and model == "corotational")]


def shaken_pile_contact(dtype, device, settings, rows: int = 1):
    """A ``SurfaceContact`` with ``settings`` (a ``tm.Contact``) over 8 shaken blocks of 3 x 3 x 2
    cells in two offset columns, touching: (contact, positions ``[V, 3]``, velocities ``[V, 3]``,
    0.3 m/s at random). ``rows``: that many such piles, 0.5 m apart along y (blocks 8 r to 8 r + 7
    the r-th)."""
    from tensormass_torch.mesh.topology import boundary_faces
    from tensormass_torch.physics.body_contact import SurfaceContact

    gen = torch.Generator().manual_seed(2)
    block = beam_mesh(3, 3, 2, size=(0.2, 0.2, 0.1), dtype=torch.float64)
    faces = boundary_faces(block.elements)
    nodes = block.vertices.shape[0]
    count = 8 * rows
    x = torch.cat([block.vertices + torch.tensor([0.19 * (b % 2) + 0.03 * (b % 8 // 2), 0.5 * (b // 8),
                                                  0.095 * (b % 8 // 2)], dtype=torch.float64)
                   + 0.004 * torch.randn(nodes, 3, generator=gen, dtype=torch.float64) for b in range(count)])
    v = 0.3 * torch.randn(x.shape, generator=gen, dtype=torch.float64)
    triangles = torch.cat([faces + b * nodes for b in range(count)])
    node_object = torch.arange(count).repeat_interleave(nodes)
    contact = SurfaceContact(triangles.to(device), node_object.to(device), x.to(device=device, dtype=dtype), settings)
    return contact, x.to(device=device, dtype=dtype), v.to(device=device, dtype=dtype)
