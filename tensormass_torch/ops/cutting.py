"""The cutting op family (``csrc/cutting/``): :func:`mesh.cutting.cut <tensormass_torch.mesh.cutting.cut>`
in one native call on the host.

The pure-torch cut costs hundreds of small tensor ops and several host synchronisations per call,
on whatever device the mesh is on; the op is one host algorithm (a pass over the elements, then
hash tables and union-find over the few elements near the blade), so it runs on the CPU only
(``OpDef.devices``): :func:`cut_mesh` copies the mesh and positions there and the results back.

    cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit)
        -> (elements, parents, first, second, slit)
            the cut of ``elements [N, n]`` (alive ones only) at positions ``x [V, 3]`` along the
            blade: the elements re-pointed, every node's parent ``[V_new]``, the element pairs
            whose face the blade crossed ``[C]`` each, and the pairs still joined ``[S', 2]``
    cut_mesh(elements, num_nodes, x, blade, removed, slit) -> mesh.cutting.CutResult
            the op on any device (results on the elements' device), or mesh.cutting.cut where
            the extension is not available

The op computes what ``mesh.cutting.cut`` computes, bit for bit (its reference below is ``cut``'s
steps with the op's signature), with three differences in what is defined: with no face crossed it
returns the mesh unchanged (``first``, ``second`` empty) where ``cut`` raises (:func:`cut_mesh`
raises the same ``MeshError``); pairs that share no face are ignored (``cut`` passes them to
``split_nodes``, whose lookup of the parted faces can then take one of them for another pair: the
reference here leaves them out first); and int32 elements stay int32 (``split_nodes`` writes int64
ids into them and fails: the reference here splits an int64 copy).

Not differentiable (a change of topology).
"""
from __future__ import annotations

from typing import Optional

import torch

from .. import _backend
from ..errors import MeshError
from ..mesh import cutting as mesh_cutting
from . import library
from .library import OpDef

__all__ = ["cut_mesh"]

NAME = "cutting_cut_mesh"


# ---------------------------------------------------------------------------------------------
# Reference, fake kernel, example
# ---------------------------------------------------------------------------------------------


def _ref_cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit):
    """``mesh.cutting.cut``'s steps in the op's signature (see the module docstring)."""
    num_nodes = x.shape[0]
    ids = torch.nonzero(alive).flatten()
    blade = mesh_cutting.Blade(blade_vertices, blade_triangles)
    first, second, _ = mesh_cutting.cut_faces(elements[ids], x, blade)
    first, second = ids[first], ids[second]
    pairs = torch.cat([torch.stack([first, second], 1), slit[alive[slit].all(1)]])
    parents = torch.arange(num_nodes, device=elements.device)
    out = elements.clone()
    if first.numel():
        parting = pairs[mesh_cutting.still_joined(elements, pairs)]  # the pairs that share a face
        # split_nodes writes int64 ids into the elements: it takes int64 ones
        live, parents = mesh_cutting.split_nodes(elements[ids].long(), num_nodes,
                                                 torch.searchsorted(ids, parting[:, 0].contiguous()),
                                                 torch.searchsorted(ids, parting[:, 1].contiguous()))
        out[ids] = live.to(elements.dtype)
    return out, parents, first, second, pairs[mesh_cutting.still_joined(out, pairs)]


def _fake_cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit):
    ctx = torch.library.get_ctx()
    num_nodes, num_crossed, num_slit = ctx.new_dynamic_size(), ctx.new_dynamic_size(), ctx.new_dynamic_size()
    index = dict(dtype=torch.int64, device=elements.device)
    return (elements.new_empty(elements.shape), torch.empty((num_nodes,), **index),
            torch.empty((num_crossed,), **index), torch.empty((num_crossed,), **index),
            torch.empty((num_slit, 2), **index))


def _example(device, dtype):
    """A 4 x 2 x 1 beam of tetrahedra (int32) with one element removed, a slit row from an earlier
    cut, and a blade that cuts half of the section at x = 0.51 (a slit of its own)."""
    from ..mesh.beams import beam_mesh

    mesh = beam_mesh(4, 2, 1, size=(1.0, 0.5, 0.25), dtype=torch.float64)
    elements = mesh.elements.to(device=device, dtype=torch.int32)
    alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
    alive[-1] = False
    blade = mesh_cutting.Blade.swept((0.51, -1, -1), (0.51, 0.2, -1), (0.51, -1, 2), (0.51, 0.2, 2))
    first, second, _ = mesh_cutting.interior_faces(mesh.elements)
    slit = torch.stack([first, second], 1)[:1].to(device)
    x = mesh.vertices.to(device=device, dtype=dtype)
    return (elements, alive, x, blade.vertices.to(x), blade.triangles.to(device), slit), {}


OPS = (OpDef(NAME, _ref_cutting_cut_mesh, _fake_cutting_cut_mesh, differentiable=False, example=_example,
             devices=("cpu",)),)
library.define(OPS, lambda: library.register(OPS))


# ---------------------------------------------------------------------------------------------
# The call
# ---------------------------------------------------------------------------------------------


def _native_available() -> bool:
    """Whether the op can run: the extension serves the CPU (where the op runs, whatever the
    mesh's device) and has it."""
    return (_backend.use_extension("cpu") and library.ensure_registered()
            and hasattr(torch.ops.tensormass, NAME))


@torch.no_grad()
def cut_mesh(elements: torch.Tensor, num_nodes: int, x: torch.Tensor, blade: mesh_cutting.Blade,
             removed: Optional[torch.Tensor] = None, slit: Optional[torch.Tensor] = None, *,
             native: bool = True) -> mesh_cutting.CutResult:
    """:func:`mesh.cutting.cut <tensormass_torch.mesh.cutting.cut>` (same arguments, result and
    errors) through ``cutting_cut_mesh`` where the extension is available (and ``native``): the
    inputs are copied to the CPU, the results back to ``elements.device``. Else ``cut`` itself.

    Raises:
        MeshError: ``x`` is not ``[num_nodes, 3]``; the blade crosses no interior face.
    """
    if x.shape != (num_nodes, 3):
        raise MeshError(f"positions must be [{num_nodes}, 3] to cut along a 3-D blade, got {tuple(x.shape)}")
    if not (native and x.dtype in (torch.float32, torch.float64) and _native_available()):
        return mesh_cutting.cut(elements, num_nodes, x, blade, removed, slit)
    device, host = elements.device, torch.device("cpu")
    index = elements.dtype if elements.dtype in (torch.int32, torch.int64) else torch.int64
    host_elements = elements.to(device=host, dtype=index).contiguous()
    alive = (torch.ones(elements.shape[0], dtype=torch.bool) if removed is None
             else ~removed.to(device=host, dtype=torch.bool))
    if slit is None or slit.numel() == 0:
        slit = torch.zeros((0, 2), dtype=torch.int64)
    out, parents, first, second, joined = library.op(NAME)(
        host_elements, alive.contiguous(), x.detach().to(host).contiguous(),
        blade.vertices.to(device=host, dtype=x.dtype).contiguous(), blade.triangles.to(host, torch.int64).contiguous(),
        slit.to(device=host, dtype=torch.int64).contiguous())
    if first.numel() == 0:
        raise MeshError("the blade crosses no interior face of the body: nothing to cut")
    return mesh_cutting.CutResult(out.to(device=device, dtype=elements.dtype), parents.to(device), first.to(device),
                                  second.to(device), num_nodes, joined.to(device))
