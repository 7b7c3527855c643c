"""The mesh layer: simplicial meshes and everything made of them alone.

    meshes      TetMesh, TriMesh (checked, immutable)
    beams       beam_mesh, beam_tri_mesh (structured grids)
    implicit    meshes of implicit shapes (spheres, capsules, a rabbit-like body)
    surface     tetrahedralize (closed surfaces through TetGen or fTetWild)
    io          load_mesh, save_mesh (meshio)
    topology    gather plans, incidence slots, edge graphs (what the ops index by)
    cutting     cutting along a blade: the faces it crosses part, their nodes split
    geometry    rest shape vectors and measures of P1 elements

It calls nothing of the package but its errors.
"""
from .beams import beam_mesh, beam_tri_mesh
from .io import load_mesh, save_mesh
from .meshes import Mesh, TetMesh, TriMesh
from .surface import tetrahedralize

__all__ = ["Mesh", "TetMesh", "TriMesh", "beam_mesh", "beam_tri_mesh", "load_mesh", "save_mesh", "tetrahedralize"]
