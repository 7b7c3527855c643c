"""Cutting a mesh along a blade: faces the blade crosses become boundary, and the nodes on them
are split so that the two sides part.

A blade is a triangle surface in 3-D (``Blade``: vertices ``[B, 3]``, triangles ``[T, 3]``; a
scalpel's edge swept between two poses is two triangles: :meth:`Blade.swept`). An interior face
(a triangle shared by two tetrahedra, or an edge shared by two membrane triangles) is cut when
the blade crosses the segment between its two elements' centroids, at the positions given (the
deformed shape: a blade cuts where the body is now).

Splitting: around each node, its elements fall into groups that stay connected through the faces
(containing the node) that were not cut; the first group keeps the node, each other group gets a
new node (a copy of it). Elements are never divided, so every element keeps n distinct nodes and
its rest shape; a cut that separates a body into pieces leaves them unconnected. The topology is
pure tensor work (label propagation, no Python loop over elements), on the mesh's device.

    Blade                    the cutting surface
    cut_faces(...)           which interior faces a blade crosses
    split_nodes(...)         the elements re-pointed and the new nodes' parents
    cut(mesh, blade, x)      both: the cut mesh, the new nodes' parents, the faces cut

A cut that ends inside the body (a slit) splits no node along its front edge, where the elements
stay joined around it; its faces stay parted for the cuts that follow (``cut(..., slit=)``), so a
scalpel that cuts a strip per step separates the body once the strips cross it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from ..errors import MeshError

#: The two triangles of a swept edge's strip over its corners (:meth:`Blade.swept`'s order).
STRIP_TRIANGLES = ((0, 1, 2), (0, 2, 3))
#: The faces of an element (local node ids): a tetrahedron's triangles, a triangle's edges.
_FACES = {4: ((1, 2, 3), (0, 2, 3), (0, 1, 3), (0, 1, 2)), 3: ((1, 2), (0, 2), (0, 1))}


@dataclass(frozen=True)
class Blade:
    """A cutting surface: ``vertices [B, 3]`` and ``triangles [T, 3]`` (int64)."""

    vertices: torch.Tensor
    triangles: torch.Tensor

    def __post_init__(self):
        v, t = self.vertices, self.triangles
        if not isinstance(v, torch.Tensor) or v.dim() != 2 or v.shape[1] != 3 or not v.is_floating_point():
            raise MeshError(f"blade vertices must be a float tensor [B, 3], got {getattr(v, 'shape', type(v))}")
        if not bool(torch.isfinite(v).all()):
            raise MeshError("blade vertices must be finite")
        if not isinstance(t, torch.Tensor) or t.dim() != 2 or t.shape[1] != 3 or t.shape[0] == 0:
            got = getattr(t, "shape", type(t))
            raise MeshError(f"blade triangles must be an integer tensor [T >= 1, 3], got {got}")
        if t.is_floating_point() or int(t.min()) < 0 or int(t.max()) >= v.shape[0]:
            raise MeshError(f"blade triangles must index the {v.shape[0]} blade vertices")

    @classmethod
    def swept(cls, start_a, start_b, end_a, end_b, dtype=torch.float64, device=None) -> "Blade":
        """The surface a straight edge sweeps from (start_a, start_b) to (end_a, end_b): two
        triangles (a scalpel's edge between two poses)."""
        vertices = torch.tensor([list(map(float, p)) for p in (start_a, start_b, end_b, end_a)], dtype=dtype,
                                device=device)
        return cls(vertices, torch.tensor(STRIP_TRIANGLES, device=device))

    @classmethod
    def strip(cls, corners: torch.Tensor) -> "Blade":
        """The two triangles (0, 1, 2), (0, 2, 3) over ``corners [4, 3]`` in :meth:`swept`'s order
        (a scalpel's strip: ``Scalpel.strip``)."""
        return cls(corners, torch.tensor(STRIP_TRIANGLES, device=corners.device))

    def to(self, like: torch.Tensor) -> "Blade":
        return Blade(self.vertices.to(like), self.triangles.to(like.device))


def shared_face_incidences(elements: torch.Tensor):
    """The faces two elements share, as incidences (``element * n + k``: the face of the element
    opposite its local node k): ``(first, second)`` ``[F]`` each, first < second, faces in the
    order of their sorted node ids; and every incidence's sorted node ids ``[N n, n - 1]``. Faces
    on the boundary (one element) are left out; a face held by more than two elements pairs its
    holders in order."""
    n = elements.shape[1]
    local = torch.tensor(_FACES[n], device=elements.device)  # [n, n - 1]
    faces = torch.sort(elements.long()[:, local], dim=-1).values.reshape(-1, n - 1)  # [N n, n - 1]
    base = int(elements.max()) + 1 if elements.numel() else 1
    if base ** (n - 1) < 2 ** 62:  # one integer a face (a sort of [N n], not of rows): the same order
        flat = faces[:, 0]
        for k in range(1, n - 1):
            flat = flat * base + faces[:, k]
        _, inverse = torch.unique(flat, return_inverse=True)
    else:
        _, inverse = torch.unique(faces, dim=0, return_inverse=True)
    order = torch.argsort(inverse, stable=True)
    sorted_ids = inverse[order]
    pair = sorted_ids[1:] == sorted_ids[:-1]  # a face met twice: shared by two elements
    return order[:-1][pair], order[1:][pair], faces


def interior_faces(elements: torch.Tensor):
    """The faces two elements share: ``(first, second)`` element ids ``[F]`` each, and the faces'
    node ids ``[F, n - 1]`` (sorted). Faces on the boundary (one element) are left out."""
    n = elements.shape[1]
    first, second, faces = shared_face_incidences(elements)
    return first // n, second // n, faces[second].to(elements.dtype)


def _segments_cross(p: torch.Tensor, q: torch.Tensor, blade: Blade) -> torch.Tensor:
    """``[F]`` bool: whether segment p -> q (``[F, 3]`` each) crosses a blade triangle
    (Moller-Trumbore; touching the blade's plane exactly at an end does not count)."""
    a = blade.vertices[blade.triangles[:, 0]]
    e1 = blade.vertices[blade.triangles[:, 1]] - a
    e2 = blade.vertices[blade.triangles[:, 2]] - a
    d = (q - p)[:, None, :]  # [F, 1, 3]
    h = torch.linalg.cross(d.expand(-1, e2.shape[0], -1), e2[None].expand(d.shape[0], -1, -1), dim=-1)
    det = (e1[None] * h).sum(-1)  # [F, T]
    ok = det.abs() > torch.finfo(det.dtype).eps * (d.norm(dim=-1) * e1.norm(dim=-1)[None] * e2.norm(dim=-1)[None])
    inv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))
    s = p[:, None, :] - a[None]
    u = inv * (s * h).sum(-1)
    qv = torch.linalg.cross(s, e1[None].expand_as(s), dim=-1)
    v = inv * (d * qv).sum(-1)
    t = inv * (e2[None] * qv).sum(-1)
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < 1)
    return hit.any(dim=1)


def _near_blade(elements: torch.Tensor, x: torch.Tensor, blade: Blade):
    """The elements whose centroid could end a segment that crosses ``blade``: within the blade's
    box grown by twice the largest element radius (a centroid's distance to its nodes), since two
    elements that share a face have centroids at most two radii apart. Returns their ids ``[K]``
    (sorted) and centroids ``[K, 3]``."""
    nodes = x[elements]  # [N, n, 3]
    centroids = nodes.mean(1)
    radius = float((nodes - centroids[:, None]).norm(dim=-1).max()) if elements.shape[0] else 0.0
    low, high = blade.vertices.min(0).values - 2 * radius, blade.vertices.max(0).values + 2 * radius
    near = torch.nonzero(((centroids >= low) & (centroids <= high)).all(1)).flatten()
    return near, centroids[near]


def cut_faces(elements: torch.Tensor, x: torch.Tensor, blade: Blade):
    """The interior faces ``blade`` crosses at positions ``x [V, 3]``: ``(first, second, faces)``
    as :func:`interior_faces` gives them, those crossed only. Only the elements near the blade
    are looked at (:func:`_near_blade`): the work follows the blade's size, not the mesh's."""
    blade = blade.to(x)
    near, centroids = _near_blade(elements, x, blade)
    local_first, local_second, faces = interior_faces(elements[near])
    first, second = near[local_first], near[local_second]
    low, high = blade.vertices.min(0).values, blade.vertices.max(0).values
    p, q = centroids[local_first], centroids[local_second]
    # only segments whose box meets the blade's box can cross it
    close = ((torch.minimum(p, q) <= high) & (torch.maximum(p, q) >= low)).all(1)
    crossed = torch.zeros_like(close)
    if bool(close.any()):
        crossed[close] = _segments_cross(p[close], q[close], blade)
    return first[crossed], second[crossed], faces[crossed]


def split_nodes(elements: torch.Tensor, num_nodes: int, cut_first: torch.Tensor, cut_second: torch.Tensor):
    """Elements re-pointed so that the faces between ``cut_first[k]`` and ``cut_second[k]`` no
    longer join them, and the new nodes' parents.

    Around each node of a cut face, the elements that share a face not cut (a face holding the
    node) stay on one copy of it: groups of incidences (element, node) joined through those
    faces, found by propagating the smallest incidence id until nothing changes. The group
    holding the node's first incidence keeps its id; every other group gets a new node, numbered
    from ``num_nodes`` on in the order of (node, the group's smallest incidence). Nodes on no cut
    face never split, so only the elements holding a cut face's node (their stars) are looked at:
    the work follows the cut's size, not the mesh's. Pairs that do not share a face are ignored.

    Returns:
        elements ``[N, n]`` (new ids where split) and parents ``[V_new]`` (the original node each
        new node copies).
    """
    n = elements.shape[1]
    device = elements.device
    parents = torch.arange(num_nodes, device=device)
    if cut_first.numel() == 0:
        return elements.clone(), parents
    # the cut faces' nodes: those the two elements of a pair share (n - 1 of them: a face)
    a, b = elements[cut_first], elements[cut_second]
    shared = (a[:, :, None] == b[:, None, :]).any(-1)  # [C, n]
    shared &= (shared.sum(1) == n - 1)[:, None]
    on_cut = torch.zeros(num_nodes, dtype=torch.bool, device=device)
    on_cut[a[shared]] = True
    star = torch.nonzero(on_cut[elements].any(1)).flatten()  # sorted: local order = global order
    local = elements[star]
    first, second, faces = interior_faces(local)
    k = star.shape[0]
    key = torch.minimum(first, second) * k + torch.maximum(first, second)
    pair_first, pair_second = torch.searchsorted(star, cut_first), torch.searchsorted(star, cut_second)
    cut_key = torch.minimum(pair_first, pair_second) * k + torch.maximum(pair_first, pair_second)
    cut = torch.isin(key, cut_key)
    keep_first, keep_second, keep_faces = first[~cut], second[~cut], faces[~cut]

    # each joined face links the incidence of each of its nodes in the two elements
    def incidence(elements_of, nodes):  # [F, n - 1] incidence ids of `nodes` in elements `elements_of`
        rows = local[elements_of]  # [F, n]
        slot = (rows[:, None, :] == nodes[:, :, None]).int().argmax(-1)  # [F, n - 1]
        return elements_of[:, None] * n + slot

    ia = incidence(keep_first, keep_faces).reshape(-1)
    ib = incidence(keep_second, keep_faces).reshape(-1)
    labels = torch.arange(k * n, device=device)  # local incidence ids, in the global order
    while True:  # smallest label over each joined pair, until stable (a group spans one node's star)
        low = torch.minimum(labels[ia], labels[ib])
        updated = labels.clone()
        updated.scatter_reduce_(0, ia, low, reduce="amin")
        updated.scatter_reduce_(0, ib, low, reduce="amin")
        updated = updated[updated]  # pointer jumping: labels point at their group's smallest
        if torch.equal(updated, labels):
            break
        labels = updated
    flat = local.reshape(-1)
    # a group per (cut node, label); the node's first group (smallest label) keeps the node
    mine = on_cut[flat]
    groups, group_of = torch.unique(flat[mine] * (k * n) + labels[mine], return_inverse=True)
    group_node = groups // (k * n)
    first_of_node = torch.ones_like(group_node, dtype=torch.bool)
    first_of_node[1:] = group_node[1:] != group_node[:-1]
    splits = ~first_of_node
    new_ids = torch.cumsum(splits.long(), 0) - 1 + num_nodes
    group_id = torch.where(splits, new_ids, group_node)
    flat = flat.clone()
    flat[mine] = group_id[group_of]
    out = elements.clone()
    out[star] = flat.reshape(k, n)
    return out, torch.cat([parents, group_node[splits]])


@dataclass
class CutResult:
    """What :func:`cut` did: the cut mesh's ``elements [N, n]``, ``parents [V_new]`` (the original
    node of every node; a new node copies its parent's rest position and state), the element
    pairs whose shared face this blade cut (``cut_first, cut_second [C]``), the node count before,
    and ``slit [S, 2]``: the pairs cut so far (this blade's and the earlier ``slit``) whose
    elements still share the face, for the next cut."""

    elements: torch.Tensor
    parents: torch.Tensor
    cut_first: torch.Tensor
    cut_second: torch.Tensor
    num_old_nodes: int
    slit: torch.Tensor

    @property
    def new_nodes(self) -> int:
        """How many nodes the cut added."""
        return int(self.parents.shape[0]) - self.num_old_nodes


def still_joined(elements: torch.Tensor, pairs: torch.Tensor) -> torch.Tensor:
    """``[P]`` bool: whether the element pairs ``pairs [P, 2]`` still share a face (n - 1 nodes)."""
    a, b = elements[pairs[:, 0]], elements[pairs[:, 1]]
    return (a[:, :, None] == b[:, None, :]).any(-1).sum(-1) == elements.shape[1] - 1


def cut(elements: torch.Tensor, num_nodes: int, x: torch.Tensor, blade: Blade, removed: Optional[torch.Tensor] = None,
        slit: Optional[torch.Tensor] = None):
    """Cut the mesh ``elements [N, n]`` over ``num_nodes`` nodes at positions ``x [V, 3]`` along
    ``blade``: the faces it crosses part, and their nodes split (:func:`split_nodes`).
    ``removed``: ``[N]`` bool, elements already gone (they join nothing and are left as they are).
    ``slit``: element pairs ``[S, 2]`` whose face earlier cuts crossed but that still share it (a
    cut that ends inside the body splits no node along its front): they stay parted, so that
    successive cuts (a scalpel, step after step) add up to the cut of their whole surface.

    Raises:
        MeshError: the blade crosses no interior face (nothing would change).
    """
    if x.shape != (num_nodes, 3):
        raise MeshError(f"positions must be [{num_nodes}, 3] to cut along a 3-D blade, got {tuple(x.shape)}")
    alive = torch.ones(elements.shape[0], dtype=torch.bool, device=elements.device) if removed is None else ~removed
    ids = torch.nonzero(alive).flatten()
    first, second, _ = cut_faces(elements[ids], x, blade)
    if first.numel() == 0:
        raise MeshError("the blade crosses no interior face of the body: nothing to cut")
    first, second = ids[first], ids[second]
    pairs = torch.stack([first, second], 1)
    if slit is not None and slit.numel():
        slit = slit.to(device=elements.device, dtype=torch.int64)
        pairs = torch.cat([pairs, slit[alive[slit].all(1)]])
    live_elements, parents = split_nodes(elements[ids], num_nodes, torch.searchsorted(ids, pairs[:, 0].contiguous()),
                                         torch.searchsorted(ids, pairs[:, 1].contiguous()))
    out = elements.clone()
    out[ids] = live_elements
    return CutResult(out, parents, first, second, num_nodes, pairs[still_joined(out, pairs)])
