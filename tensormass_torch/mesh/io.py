"""Mesh files through meshio (imported lazily: it is only needed here).

    mesh = load_mesh("liver.msh")                      # TetMesh if the file has tetra cells
    save_mesh("out/beam.vtu", mesh, u=displacement)    # point data [V] or [V, k], k <= 3

Formats checked by the tests: ``.vtu``, ``.vtk``, ``.msh`` (written as gmsh 4.1 binary),
``.mesh`` (medit, which stores no point data). Other meshio formats are passed through.
"""
from __future__ import annotations

import contextlib
import io as _stdio
import os
from pathlib import Path
from typing import Dict, Union

import numpy as np
import torch

from ..errors import InvertedElementsError, MeshError
from .meshes import Mesh, TetMesh, TriMesh, _native_numpy

__all__ = ["load_mesh", "save_mesh"]

PathLike = Union[str, "os.PathLike[str]"]

# Our element kinds <-> meshio cell type names.
_CELL_TYPE = {"tet": "tetra", "tri": "triangle"}
# Point-data keys meshio adds for its own bookkeeping (not user data): dropped on load.
_BOOKKEEPING_PREFIXES = ("gmsh:", "medit:")
# Formats that cannot store point data: refuse rather than silently drop the user's data.
_NO_POINT_DATA = {"medit"}


def _import_meshio():
    try:
        import meshio
    except ImportError as exc:  # pragma: no cover - meshio is a dependency of this module
        raise ImportError(
            "tensormass_torch.load_mesh/save_mesh need meshio: pip install meshio"
        ) from exc
    return meshio


def _file_format(meshio, path: Path) -> str:
    """meshio's format name for ``path``'s extension; MeshError if meshio knows none.

    ``.msh`` is ambiguous in meshio (ANSYS is listed first); we always mean gmsh, whose
    files keep point data and float64 coordinates.
    """
    name = path.name.lower()
    if name.endswith(".msh"):
        return "gmsh"
    # Longest match first, so ".vol.gz" wins over ".gz"-like shorter keys.
    for ext in sorted(meshio.extension_to_filetypes, key=len, reverse=True):
        if name.endswith(ext):
            return meshio.extension_to_filetypes[ext][0]
    raise MeshError(
        f"cannot write '{path}': unknown mesh file extension {path.suffix!r} "
        "(use .vtu, .vtk, .msh or .mesh)"
    )


# ---------------------------------------------------------------------------------------------
# Loading
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _captured_output():
    """Capture what meshio prints (it reports failures on stdout/stderr) -> a StringIO."""
    buffer = _stdio.StringIO()
    with contextlib.redirect_stdout(buffer), contextlib.redirect_stderr(buffer):
        yield buffer


def _reason(exc: BaseException, printed: str) -> str:
    """meshio's reason for a failure: the exception's text, or what meshio printed before
    exiting (its SystemExit carries only the exit code)."""
    text = "" if isinstance(exc, SystemExit) else str(exc)
    return text or " ".join(printed.split()) or type(exc).__name__


def _read(meshio, path: Path):
    if not path.exists():
        raise FileNotFoundError(f"mesh file not found: '{path}'")
    # ".msh" is gmsh here, as for writing: left to guess, meshio tries its ANSYS reader first,
    # which loops forever on some files that are not ANSYS.
    file_format = "gmsh" if path.name.lower().endswith(".msh") else None
    try:
        with _captured_output() as printed:
            return meshio.read(str(path), file_format=file_format)
    # meshio raises many types (ReadError, KeyError, ValueError...) and, when no reader
    # accepts the file, prints the reason and calls sys.exit(1): SystemExit is caught too
    # (and only here, around the library call) so a bad file cannot end the program.
    except (Exception, SystemExit) as exc:
        raise MeshError(
            f"could not read mesh file '{path}': {_reason(exc, printed.getvalue())}"
        ) from exc


def _cells_of_type(data, cell_type: str) -> np.ndarray:
    """All blocks of ``cell_type`` concatenated -> ``[N, n]`` (N may be 0)."""
    blocks = [_native_numpy(block.data) for block in data.cells if block.type == cell_type]
    if not blocks:
        return np.empty((0, 0), dtype=np.int64)
    return np.concatenate(blocks, axis=0)


def _user_point_data(data) -> Dict[str, torch.Tensor]:
    out = {}
    for key, values in data.point_data.items():
        if key.startswith(_BOOKKEEPING_PREFIXES):
            continue
        out[key] = torch.as_tensor(_native_numpy(np.asarray(values)))
    return out


def load_mesh(path: PathLike, *, orient: bool = False, with_point_data: bool = False):
    """Read a mesh file through meshio.

    If the file has tetra cells, all of them make a :class:`TetMesh` (other cells are
    ignored); otherwise its triangle cells make a :class:`TriMesh`, 2-D if the file stores
    2-D points and 3-D otherwise (even when every z is 0). All points are kept, so point
    data stays aligned; use ``mesh.unused_vertices()`` to find points no element uses.
    Coordinates keep the file's dtype (float64 stays float64).

    Args:
        path: the file; its extension selects the format.
        orient: flip inverted elements instead of raising (see :class:`TetMesh`).
        with_point_data: also return the file's point data as a dict of CPU tensors
            ``[V]`` / ``[V, k]`` (meshio's own ``gmsh:*`` / ``medit:*`` keys left out).

    Returns:
        the mesh, or ``(mesh, point_data)`` when ``with_point_data`` is true.

    Raises:
        FileNotFoundError: the file does not exist.
        MeshError: meshio cannot read it, it holds no tetra or triangle cells, or the mesh
            fails validation (the message names the file).
    """
    meshio = _import_meshio()
    path = Path(path)
    data = _read(meshio, path)

    tets = _cells_of_type(data, "tetra")
    if len(tets):
        cls, elements = TetMesh, tets
    else:
        tris = _cells_of_type(data, "triangle")
        if not len(tris):
            found = sorted({block.type for block in data.cells}) or ["none"]
            raise MeshError(
                f"'{path}' has no tetra or triangle cells (cell types found: {', '.join(found)})"
            )
        cls, elements = TriMesh, tris

    points = _native_numpy(np.asarray(data.points))
    try:
        mesh = cls(points, elements, orient=orient)
    except MeshError as exc:
        if isinstance(exc, InvertedElementsError):
            raise InvertedElementsError(f"'{path}': {exc}", exc.ids) from exc
        raise MeshError(f"'{path}': {exc}") from exc
    if with_point_data:
        return mesh, _user_point_data(data)
    return mesh


# ---------------------------------------------------------------------------------------------
# Saving
# ---------------------------------------------------------------------------------------------


def _point_data_array(key: str, value, num_vertices: int) -> np.ndarray:
    """One point-data field as a CPU numpy array ``[V]`` or ``[V, k]`` (k = 2 padded to 3)."""
    if isinstance(value, torch.Tensor):
        arr = value.detach().cpu().numpy()
    else:
        try:
            arr = np.asarray(value)
        except Exception as exc:
            raise MeshError(f"point data '{key}' is not an array: {exc}") from exc
    if arr.dtype.kind == "b":
        arr = arr.astype(np.uint8)  # file formats have no bool type
    if arr.dtype.kind not in "iuf":
        raise MeshError(f"point data '{key}' must be numeric (got dtype {arr.dtype})")
    ok = arr.ndim in (1, 2) and arr.shape[0] == num_vertices
    if ok and arr.ndim == 2:
        ok = 1 <= arr.shape[1] <= 3
    if not ok:
        raise MeshError(
            f"point data '{key}' has shape {list(arr.shape)}; expected [V] or [V, k] with "
            f"V = {num_vertices} (the mesh's vertices) and 1 <= k <= 3"
        )
    if arr.ndim == 2 and arr.shape[1] == 2:
        # File vectors are 3-D (VTK readers expect 3 components): pad with z = 0.
        arr = np.concatenate([arr, np.zeros((num_vertices, 1), dtype=arr.dtype)], axis=1)
    return _native_numpy(arr)


def _points_for_file(mesh: Mesh, file_format: str) -> np.ndarray:
    """``[V, 3]`` CPU numpy coordinates (2-D meshes padded with z = 0)."""
    points = mesh.vertices.detach().cpu().numpy()
    if points.shape[1] == 2:
        points = np.concatenate([points, np.zeros((len(points), 1), dtype=points.dtype)], 1)
    if file_format == "gmsh" or points.dtype not in (np.float32, np.float64):
        # Binary gmsh stores doubles only (meshio would convert with a warning); half
        # precision is not a file type anywhere.
        points = points.astype(np.float64)
    return np.ascontiguousarray(points)


def _write_atomically(meshio, path: Path, data, file_format: str) -> None:
    """Write to a temporary file next to ``path``, then rename: a failed write leaves no
    half-written file behind (and never clobbers an existing good one)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    # Keep the real extension last: some meshio writers look at it (medit: ".meshb" = binary).
    tmp = path.with_name(f".{path.name}.{os.getpid()}.partial{path.suffix}")
    try:
        with _captured_output() as printed:
            meshio.write(str(tmp), data, file_format=file_format)
        os.replace(tmp, path)
    except (Exception, SystemExit) as exc:  # SystemExit: as in _read
        raise MeshError(
            f"could not write mesh file '{path}': {_reason(exc, printed.getvalue())}"
        ) from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def save_mesh(path: PathLike, mesh: Mesh, **point_data) -> None:
    """Write ``mesh`` (and optional point data) with meshio; the extension picks the format.

    Args:
        path: destination; parent directories are created. ``.msh`` is written as gmsh 4.1
            (binary); ``.vtu``, ``.vtk``, ``.mesh`` (medit) and other meshio formats by
            extension.
        mesh: a :class:`TetMesh` or :class:`TriMesh` (any device; copied to the CPU).
        **point_data: fields ``[V]`` or ``[V, k]`` (k <= 3), torch tensors or numpy arrays;
            2-D vectors are padded with a zero third component, as are 2-D vertices.

    Everything is validated before anything is written.

    Raises:
        MeshError: not a mesh, unknown extension, a point-data field of the wrong shape or
            type (named), point data for a format that cannot store it (medit), or meshio
            failing to write.
    """
    meshio = _import_meshio()
    if not isinstance(mesh, Mesh):
        raise MeshError(f"save_mesh needs a TetMesh or TriMesh (got {type(mesh).__name__})")
    path = Path(path)
    file_format = _file_format(meshio, path)

    fields = {key: _point_data_array(key, value, mesh.num_vertices)
              for key, value in point_data.items()}
    if fields and file_format in _NO_POINT_DATA:
        raise MeshError(
            f"cannot write '{path}': the {file_format} format stores no point data "
            f"(got {', '.join(fields)}); use .vtu, .vtk or .msh"
        )

    cells = [(_CELL_TYPE[mesh.kind], mesh.elements.detach().cpu().numpy())]
    data = meshio.Mesh(_points_for_file(mesh, file_format), cells, point_data=fields)
    _write_atomically(meshio, path, data, file_format)
