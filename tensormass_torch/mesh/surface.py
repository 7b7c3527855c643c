"""Volume meshes from closed surfaces, through a well-kept tetrahedraliser.

    mesh = tm.tetrahedralize("organ.stl")                        # TetGen, quality options on
    mesh = tm.tetrahedralize("organ.stl", max_volume=1e-6)       # no tet above 1 cm^3 (in m^3)
    mesh = tm.tetrahedralize(surface, method="ftetwild")         # fTetWild: repairs bad surfaces

Two methods, each an optional package (``pip install 'tensormass_torch[mesh]'`` installs both):

* ``"tetgen"`` (default; the ``tetgen`` package, TetGen 1.6 under the AGPL): a constrained
  Delaunay tetrahedralisation that keeps the surface's triangles as the boundary, refined to a
  quality bound (``min_ratio``, the largest circumradius / shortest edge of a tet;
  ``min_dihedral`` in degrees) and, optionally, a size bound (``max_volume``). Fast (milliseconds
  for thousands of tets) but it needs a clean closed surface: no holes, no self-intersections.
* ``"ftetwild"`` (the ``pytetwild`` package, fTetWild under the MPL): a tolerant mesher that
  accepts open, self-intersecting or otherwise broken surfaces and returns a mesh within
  ``epsilon`` (relative to the bounding box diagonal) of them, with edges about
  ``edge_length`` times that diagonal. Seconds rather than milliseconds.

The result is a checked, positively oriented :class:`TetMesh` with no unused vertex.
"""
from __future__ import annotations

import importlib
from pathlib import Path

import numpy as np
import torch

from ..errors import MeshError
from .meshes import TetMesh, TriMesh

__all__ = ["tetrahedralize", "METHODS"]

#: ``tetrahedralize(method=...)`` values and the package each needs.
METHODS = {"tetgen": "tetgen", "ftetwild": "pytetwild"}
#: The options each method takes (any other is an error), with their defaults.
OPTIONS = {
    "tetgen": {"min_ratio": 1.5, "min_dihedral": 10.0, "max_volume": None, "quality": True},
    "ftetwild": {"edge_length": 0.05, "epsilon": 1e-3},
}


def _surface_arrays(surface):
    """(vertices [V, 3] float64, triangles [F, 3] int32) numpy arrays of ``surface``."""
    if isinstance(surface, (str, Path)):
        from .io import load_mesh

        path = Path(surface)
        if not path.is_file():
            raise MeshError(f"surface file not found: '{path}'")
        mesh = load_mesh(path)
        if not isinstance(mesh, TriMesh):
            raise MeshError(f"'{path}' holds tetrahedra, not a surface: load it with tm.load_mesh")
        surface = mesh
    if isinstance(surface, TriMesh):
        vertices, triangles = surface.vertices, surface.elements
    elif hasattr(surface, "points") and hasattr(surface, "faces"):  # a pyvista PolyData
        if not getattr(surface, "is_all_triangles", True):
            surface = surface.triangulate()
        vertices, triangles = surface.points, np.asarray(surface.faces).reshape(-1, 4)[:, 1:]
    elif isinstance(surface, (tuple, list)) and len(surface) == 2:
        vertices, triangles = surface
    else:
        raise MeshError("surface must be a file path, a tm.TriMesh, (vertices [V, 3], triangles [F, 3]) or a "
                        f"pyvista PolyData; got {type(surface).__name__}")
    vertices = np.asarray(torch.as_tensor(vertices).detach().cpu(), dtype=np.float64)
    triangles = np.asarray(torch.as_tensor(triangles).detach().cpu())
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 4:
        raise MeshError(f"surface vertices must be [V, 3] with V >= 4, got shape {list(vertices.shape)}")
    if triangles.ndim != 2 or triangles.shape[1] != 3 or len(triangles) < 4:
        raise MeshError(f"surface triangles must be [F, 3] with F >= 4, got shape {list(triangles.shape)}")
    if not np.issubdtype(triangles.dtype, np.integer):
        raise MeshError(f"surface triangles must hold integer node ids, got {triangles.dtype}")
    if not np.isfinite(vertices).all():
        raise MeshError("surface vertices must be finite (NaN or inf found)")
    if triangles.min() < 0 or triangles.max() >= len(vertices):
        raise MeshError(f"surface triangles index vertices outside [0, {len(vertices)})")
    return vertices, triangles.astype(np.int32)


def _open_edges(triangles: np.ndarray) -> int:
    """How many edges of ``triangles [F, 3]`` are not shared by exactly two triangles."""
    edges = np.sort(triangles[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts != 2).sum())


def _import(method: str):
    package = METHODS[method]
    try:
        return importlib.import_module(package)
    except ImportError:
        raise MeshError(f"tetrahedralize(method={method!r}) needs the {package} package: pip install {package} "
                        "(or pip install 'tensormass_torch[mesh]')") from None


def _tetgen(vertices, triangles, min_ratio, min_dihedral, max_volume, quality):
    tetgen = _import("tetgen")
    open_edges = _open_edges(triangles)
    if open_edges:
        raise MeshError(f"the surface is not closed ({open_edges} edges not shared by exactly two triangles): "
                        "TetGen needs a closed surface; method='ftetwild' meshes open or broken ones")
    try:
        nodes, tets, *_ = tetgen.TetGen(vertices, triangles).tetrahedralize(
            quality=quality, minratio=min_ratio, mindihedral=min_dihedral, fixedvolume=max_volume is not None,
            maxvolume=-1.0 if max_volume is None else max_volume)
    except RuntimeError as exc:  # TetGen reports self-intersections and internal failures so
        raise MeshError(f"TetGen failed on this surface ({exc}); method='ftetwild' meshes self-intersecting "
                        "or otherwise broken surfaces") from None
    return nodes, tets


def _ftetwild(vertices, triangles, edge_length, epsilon):
    pytetwild = _import("ftetwild")
    return pytetwild.tetrahedralize(vertices, triangles, edge_length_fac=edge_length, epsilon=epsilon, quiet=True)


def _positive(name: str, value, allow_none: bool = False):
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value) or value <= 0:
        raise MeshError(f"{name} must be a positive number, got {value!r}")


def tetrahedralize(surface, *, method: str = "tetgen", dtype: torch.dtype = torch.float32, device=None,
                   **options) -> TetMesh:
    """A tetrahedral mesh of the solid a closed triangle surface bounds.

    Args:
        surface: a surface file (any meshio format with triangles: .stl, .obj, .ply, .off, .vtk,
            ...), a 3-D :class:`TriMesh`, a pair ``(vertices [V, 3], triangles [F, 3])`` or a
            pyvista ``PolyData``.
        method: ``"tetgen"`` (default) or ``"ftetwild"`` (see the module's notes).
        dtype, device: of the returned mesh's vertices (float32 on the CPU by default).
        **options: the method's options, in the surface's units:
            ``"tetgen"``: ``min_ratio`` (radius-edge bound, default 1.5, >= 1 in practice),
            ``min_dihedral`` (degrees, default 10), ``max_volume`` (largest tet volume, default
            None: no bound), ``quality`` (default True; False keeps the surface's vertices only);
            ``"ftetwild"``: ``edge_length`` (target edge over the bounding box diagonal, default
            0.05), ``epsilon`` (allowed deviation from the surface over that diagonal, 1e-3).

    Returns:
        a :class:`TetMesh`, positively oriented, every vertex used.

    Raises:
        MeshError: the package is missing (with the pip command), the surface is malformed, not
            closed (tetgen) or the mesher fails, an option is unknown or out of range.
    """
    if method not in METHODS:
        raise MeshError(f"unknown tetrahedralize method {method!r}; expected one of {', '.join(METHODS)}")
    unknown = sorted(set(options) - set(OPTIONS[method]))
    if unknown:
        raise MeshError(f"method {method!r} takes no option {unknown[0]!r}; its options are "
                        f"{', '.join(OPTIONS[method])}")
    settings = {**OPTIONS[method], **options}
    if method == "tetgen":
        _positive("min_ratio", settings["min_ratio"])
        if not isinstance(settings["min_dihedral"], (int, float)) or not 0 <= settings["min_dihedral"] < 70:
            raise MeshError(f"min_dihedral must be in [0, 70) degrees, got {settings['min_dihedral']!r}")
        _positive("max_volume", settings["max_volume"], allow_none=True)
        if not isinstance(settings["quality"], bool):
            raise MeshError(f"quality must be True or False, got {settings['quality']!r}")
    else:
        _positive("edge_length", settings["edge_length"])
        _positive("epsilon", settings["epsilon"])
    vertices, triangles = _surface_arrays(surface)
    mesher = _tetgen if method == "tetgen" else _ftetwild
    nodes, tets = mesher(vertices, triangles, **settings)
    nodes, tets = np.asarray(nodes, dtype=np.float64), np.asarray(tets, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
        raise MeshError(f"{method} returned no tetrahedra for this surface")
    used, tets = np.unique(tets, return_inverse=True)  # drop the vertices no tet uses
    nodes, tets = nodes[used], tets.reshape(-1, 4)
    vertices_t = torch.as_tensor(nodes, dtype=dtype, device=device)
    # Each mesher has its own orientation convention: flip the tets that come out negative.
    return TetMesh(vertices_t, torch.as_tensor(tets, device=vertices_t.device), orient=True)
