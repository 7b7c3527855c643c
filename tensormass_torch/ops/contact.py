"""The contact op family (``csrc/contact/``): the broad phase of the contact between bodies'
surfaces, the candidate (surface vertex, surface triangle) pairs of a spatial hash. Each op's
pure-torch reference (the tests' oracle, and the path where the extension does not serve the
device), fake kernel and example, and the group-level call :func:`candidate_pairs`.

The hash is built by tensor ops (:func:`hash_queries`): the triangles' boxes, grown by the
contact's reach, listed once in every cell of side ``cell`` they cover and sorted by the cells'
hash key; each query is a (surface vertex, cell its box covers), with the run [start, stop) of
the entries of its key. The ops walk each query's run and keep a candidate where

- the entry's cell is the query's (keys of distinct cells may collide),
- the vertex's box meets the triangle's grown box,
- the low corner of the boxes' intersection is in the query's cell (a pair meeting in several
  cells is kept once),
- the bodies differ, unless ``same_body`` (self-contact, whose own filter the caller applies).

    contact_count_candidates(cell, point_low, point_high, vertex_object, query_vertex, query_cells,
        query_start, query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object,
        same_body, triangle_first?) -> counts [Q]: how many candidates each query keeps
    contact_fill_candidates(the same, offsets, vertex!, triangle!)
            the candidates, query q's from offsets[q] in run order

(``query_order``: the order the kernel takes the queries in, by run, so that the threads of one
warp walk one run together; it changes no output. ``triangle_first [B + 1]`` or None: the
triangles are in body order, body b's from ``triangle_first[b]`` to ``triangle_first[b + 1] - 1``;
a query then skips its own body's entries, one stretch of its run (a run lists its entries in
triangle order), found by binary search; no output changed.)

The narrow phase (:func:`nearest_pairs`): for each surface vertex and each other body, the nearest
of its candidate triangles within the reach, the lowest triangle id among those tied with it
(within the rounding of the distances), its side by the sum of the tied triangles' normals:

    contact_count_nearest(x, vertices, vertex_object, triangles, triangle_object, first,
        candidate_triangle, spread?, body_step?, reach) -> (counts [Sv] (-1: too many bodies
        near), chosen [Sv]: -1 no pair, 2 i + (1 if outside) one pair from candidate i, -2 more)
    contact_fill_nearest(the same, offsets, chosen, pair_vertex!, pair_triangle!, weights!, diff!,
        distance!, normal!, side!)

(``chosen`` spares the fill pass the walk for the vertices that keep no pair or one, most of
them: it queries the one candidate the count chose.)

The pairs' part of a step's matrix times a vector, in two kernels (a pair each, then a node each
over its entries in a fixed order):

    contact_pair_product(dx, nodes, coef, direction, normal, friction, order, offsets, vector!, out!,
        accumulate=False)   (accumulate: added to out, another product's, in place)

Why ops: as tensor ops the broad phase's walk materialises every entry of every query's run
before filtering it, and the runs hold mostly the vertex's own body's triangles. The ops' output is
the reference's, in its order, so the narrow phase that follows sees the same pairs either way.
Not differentiable (indices).
"""
from __future__ import annotations

import math
from typing import Optional

import torch

from ..mesh.distance import closest_point
from ..mesh.topology import add_at
from . import library
from .library import OpDef

__all__ = ["hash_key", "covered_cells", "hash_queries", "candidate_pairs", "nearest_pairs", "pair_product"]


def hash_key(cells: torch.Tensor) -> torch.Tensor:
    """An int32 key of integer cells ``[..., 3]``: distinct cells may share one (the candidates
    check the cell itself, so a collision costs work, never a contact). 31 bits: a 32-bit sort
    of the entries takes half the passes of a 64-bit one."""
    mixed = (cells[..., 0] * 73856093) ^ (cells[..., 1] * 19349663) ^ (cells[..., 2] * 83492791)
    return (mixed & 0x7FFFFFFF).to(torch.int32)


def _run_starts(counts: torch.Tensor) -> torch.Tensor:
    """Where each of the runs of ``counts [N]`` items starts when they are packed one after the
    other (the exclusive prefix sum, ``[N]``): the ops' fill passes write each run there."""
    return torch.cumsum(counts, 0) - counts


def covered_cells(low: torch.Tensor, high: torch.Tensor, cell):
    """The cells of side ``cell`` that boxes [low, high] ``[N, 3]`` cover: (box ids ``[E]``,
    integer cells ``[E, 3]``), each box's cells in a row (one host read: their number)."""
    first = torch.floor(low / cell).to(torch.int64)
    span = torch.floor(high / cell).to(torch.int64) - first + 1  # [N, 3] cells per axis
    count = span.prod(-1)
    total = int(count.sum())
    box = torch.repeat_interleave(torch.arange(len(low), device=low.device), count, output_size=total)
    local = torch.arange(total, device=low.device) - _run_starts(count)[box]
    ny, nz = span[box, 1], span[box, 2]
    offset = torch.stack([local // (ny * nz), (local // nz) % ny, local % nz], dim=-1)
    return box, first[box] + offset


def hash_queries(cell: torch.Tensor, low: torch.Tensor, high: torch.Tensor, point_low: torch.Tensor,
                 point_high: torch.Tensor):
    """The spatial hash of the triangles' grown boxes ``low, high [F, 3]`` and the queries of the
    vertices' boxes ``point_low, point_high [Sv, 3]`` (the same tensor twice: points, one query
    each, with no host read), cells of side ``cell`` (a 0-dim tensor): (query_vertex ``[Q]``,
    query_cells ``[Q, 3]``, query_start ``[Q]``, query_stop ``[Q]``, query_order ``[Q]``,
    entry_triangle ``[E]``, entry_cells ``[E, 3]``), the entries sorted by key (stably: a key's
    entries in triangle order), the queries in the vertices' order and query_order the
    permutation that sorts them by run, every tensor contiguous int64."""
    owners, cells = covered_cells(low, high, cell)
    keys, order = torch.sort(hash_key(cells), stable=True)
    entry_triangle, entry_cells = owners[order].contiguous(), cells[order].contiguous()
    if point_low is point_high:
        query_vertex = torch.arange(len(point_low), device=point_low.device)
        query_cells = torch.floor(point_low / cell).to(torch.int64)
    else:
        query_vertex, query_cells = covered_cells(point_low, point_high, cell)
    query_keys = hash_key(query_cells)
    start = torch.searchsorted(keys, query_keys, side="left")
    stop = torch.searchsorted(keys, query_keys, side="right")
    query_order = torch.argsort(start, stable=True)
    return query_vertex, query_cells.contiguous(), start, stop, query_order, entry_triangle, entry_cells


# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
          query_order, entry_triangle, entry_cells, low, high, triangle_object, same_body, triangle_first=None):
    """(query ``[C]``, entry ``[C]``) of the kept candidates in the ops' order (``triangle_first``
    only says where the ops may skip: it changes nothing here)."""
    counts = query_stop - query_start
    total = int(counts.sum())
    device = query_start.device
    query = torch.repeat_interleave(torch.arange(len(query_start), device=device), counts, output_size=total)
    first_of = torch.repeat_interleave(query_start - _run_starts(counts), counts, output_size=total)
    entry = first_of + torch.arange(total, device=device)
    triangle, vertex = entry_triangle[entry], query_vertex[query]
    cells = query_cells[query]
    corner = torch.maximum(point_low[vertex], low[triangle])
    meet = ((point_low[vertex] <= high[triangle]) & (point_high[vertex] >= low[triangle])).all(-1)
    kept = ((entry_cells[entry] == cells).all(-1) & meet
            & (torch.floor(corner / cell.reshape(())).to(torch.int64) == cells).all(-1))
    if not same_body:
        kept &= vertex_object[vertex] != triangle_object[triangle]
    chosen = kept.nonzero().squeeze(1)
    return query[chosen], entry[chosen]


def _ref_contact_count_candidates(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                                  query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object,
                                  same_body, triangle_first):
    query, _ = _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
                     query_order, entry_triangle, entry_cells, low, high, triangle_object, same_body)
    return torch.bincount(query, minlength=len(query_vertex))


def _ref_contact_fill_candidates(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                                 query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object,
                                 same_body, triangle_first, offsets, vertex, triangle):
    query, entry = _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                         query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object, same_body)
    vertex.copy_(query_vertex[query])
    triangle.copy_(entry_triangle[entry])


def nearest_reference(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle, spread,
                      body_step, reach):
    """The narrow phase as tensor ops (the ops' oracle; see the module): (pair_vertex ``[P]``,
    pair_triangle ``[P]``, weights ``[P, 3]``, diff ``[P, 3]``, distance ``[P]``, normal ``[P, 3]``,
    side ``[P]``), the pairs in the order of their chosen candidates."""
    return _nearest_with_candidates(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                                    spread, body_step, reach)[:7]


def _nearest_with_candidates(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                             spread, body_step, reach):
    """:func:`nearest_reference`'s pairs and each one's chosen candidate ``[P]`` (its index into
    ``candidate_triangle``)."""
    per_vertex = first[1:] - first[:-1]
    vertex = torch.repeat_interleave(torch.arange(len(vertices), device=x.device), per_vertex,
                                     output_size=len(candidate_triangle))
    triangle = candidate_triangle
    tri = triangles[triangle]
    node = vertices[vertex]
    w, diff, d, normal = closest_point(x[node], x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]])
    limit = reach
    if spread is not None:  # what the pair may close over the step joins its reach
        between = body_step[vertex_object[vertex]] - body_step[triangle_object[triangle]]
        limit = reach + spread[node] + spread[tri].amax(-1) + torch.linalg.vector_norm(between, dim=-1)
    near = (d < limit).nonzero().squeeze(1)
    vertex, triangle, node, w, diff, d, normal = (t[near] for t in (vertex, triangle, node, w, diff, d, normal))
    candidate = near  # each one's index into candidate_triangle
    # the nearest triangle per (vertex, body); ties to the lowest triangle id (deterministic).
    # Groups numbered by a sort of their keys, at most one per candidate (no host read).
    key = vertex * (1 << 32) + triangle_object[triangle]  # (bodies and vertices < 2^31)
    sorted_key, order = torch.sort(key)
    starts = torch.ones_like(sorted_key, dtype=torch.bool)
    starts[1:] = sorted_key[1:] != sorted_key[:-1]
    group = torch.empty_like(key).scatter_(0, order, torch.cumsum(starts, 0) - 1)
    groups = key.numel()
    least = d.new_full((groups,), math.inf).scatter_reduce(0, group, d, "amin")
    # The triangles whose closest point is the nearest one share it (an edge or a corner of the
    # surface): the vertex is outside when it is on the outer side of their normals' sum (the
    # side of one triangle's plane is wrong beyond a convex edge: outside the body, but behind
    # the plane of the face the edge bounds). Tied: within the rounding of the distances, which
    # two triangles compute differently for their shared edge (a few ulps of the coordinates: in
    # float32 far more than any fixed fraction of the reach; a missed tie leaves one grazing face
    # to decide the side).
    rounding = 32.0 * torch.finfo(d.dtype).eps * (x[node].abs().amax(-1) + reach)
    tied = d <= least[group] + rounding
    pseudo = add_at(normal.new_zeros(groups, 3), group, normal * tied[:, None].to(d.dtype))
    big = torch.iinfo(torch.int64).max
    lowest = torch.full((groups,), big, dtype=torch.int64, device=x.device).scatter_reduce(
        0, group, torch.where(tied, triangle, big), "amin")
    chosen = (tied & (triangle == lowest[group])).nonzero().squeeze(1)
    vertex, triangle, w, diff, d, normal, group, rounding, candidate = (
        t[chosen] for t in (vertex, triangle, w, diff, d, normal, group, rounding, candidate))
    side = torch.where((pseudo[group] * diff).sum(-1) >= 0, 1.0, -1.0).to(d.dtype)
    # The side is trusted where every triangle tied with the chosen one is among those within the
    # limit: where the chosen one is nearer than the reach by the rounding. Nearer the reach a
    # tied triangle may lie just past it (its shared edge computed a few ulps farther) and be left
    # out, and one face alone may put a vertex beside its edge behind its plane: "inside" by a
    # whole search, a penalty that pulls the bodies into each other (docs/contact.md). Past the
    # reach (swept, the limit grown) the candidates need not hold every nearer triangle either.
    # There a pair is kept only outside (a vertex that deep inside is lost to the body anyway).
    trusted = ((d < reach - rounding) | (side > 0)).nonzero().squeeze(1)
    return tuple(t[trusted] for t in (vertex, triangle, w, diff, d, normal, side, candidate))


def _ref_contact_count_nearest(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                               spread, body_step, reach):
    found = _nearest_with_candidates(x, vertices, vertex_object, triangles, triangle_object, first,
                                     candidate_triangle, spread, body_step, reach)
    vertex, side, candidate = found[0], found[6], found[7]
    counts = torch.bincount(vertex, minlength=len(vertices))
    chosen = torch.where(counts == 0, -1, -2)
    single = counts[vertex] == 1
    chosen[vertex[single]] = 2 * candidate[single] + (side[single] > 0).to(torch.int64)
    return counts, chosen


def _ref_contact_fill_nearest(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                              spread, body_step, reach, offsets, chosen, pair_vertex, pair_triangle, weights, diff,
                              distance, normal, side):
    found = nearest_reference(x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                              spread, body_step, reach)
    for out, value in zip((pair_vertex, pair_triangle, weights, diff, distance, normal, side), found):
        out.copy_(value)


def _ref_contact_pair_product(dx, nodes, coef, direction, normal, friction, order, offsets, vector, out,
                              accumulate=False):
    relative = (coef[:, :, None] * dx[nodes]).sum(1)  # J dx [C, 3]
    along = (relative * direction).sum(-1, keepdim=True)  # u . J dx [C, 1]
    # a u (u . J dx) + b (J dx - u (u . J dx))
    vector.copy_(friction[:, None] * relative + ((normal - friction)[:, None] * along) * direction)
    per_entry = (coef[:, :, None] * vector[:, None, :]).reshape(-1, 3)
    sums = torch.segment_reduce(per_entry[order], "sum", offsets=offsets, axis=0, unsafe=True)
    if accumulate:  # (a node with no entry keeps its value)
        out.copy_(torch.where((offsets[1:] > offsets[:-1])[:, None], out + sums, out))
    else:
        out.copy_(sums)


# ---------------------------------------------------------------------------------------------
# Fake kernels and examples
# ---------------------------------------------------------------------------------------------


def _fake_contact_count_candidates(cell, point_low, point_high, vertex_object, query_vertex, *rest):
    return query_vertex.new_empty(query_vertex.shape)


def _example_inputs(device, dtype):
    """Two bodies of a few random triangles and vertices near each other, some boxes swept."""
    gen = torch.Generator().manual_seed(11)
    corners = torch.rand(12, 3, 3, generator=gen, dtype=torch.float64) * 0.6
    low, high = corners.amin(1) - 0.05, corners.amax(1) + 0.05
    points = torch.rand(10, 3, generator=gen, dtype=torch.float64) * 0.6
    point_high = points + torch.rand(10, 3, generator=gen, dtype=torch.float64) * 0.2
    triangle_object = (torch.arange(12) % 2).to(device)
    vertex_object = (torch.arange(10) // 5).to(device)
    low, high, points, point_high = (t.to(device=device, dtype=dtype) for t in (low, high, points, point_high))
    cell = (high - low).amax()
    queries = hash_queries(cell, low, high, points, point_high)
    return (cell.reshape(1), points, point_high, vertex_object, *queries, low, high, triangle_object, False, None)


def _fake_contact_count_nearest(x, vertices, *rest):
    return vertices.new_empty(vertices.shape), vertices.new_empty(vertices.shape)


def _example_nearest_inputs(device, dtype, swept=True):
    """Two touching tetrahedra's surfaces (bodies 0 and 1), every triangle a candidate of every
    vertex of the other body."""
    x = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1],
                      [0.2, 0.2, 0.3], [1.2, 0.2, 0.3], [0.2, 1.2, 0.3], [0.2, 0.2, 1.3]], dtype=dtype, device=device)
    faces = torch.tensor([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], device=device)
    triangles = torch.cat([faces, faces + 4])
    triangle_object = torch.tensor([0] * 4 + [1] * 4, device=device)
    vertices = torch.arange(8, device=device)
    vertex_object = vertices // 4
    candidate = [t for v in range(8) for t in range(8) if t // 4 != v // 4]
    candidate_triangle = torch.tensor(candidate, device=device)
    first = torch.arange(0, 8 * 4 + 1, 4, device=device)
    spread = torch.full((8,), 0.01, dtype=dtype, device=device) if swept else None
    body_step = torch.tensor([[0.0, 0, -0.01], [0, 0, 0.01]], dtype=dtype, device=device) if swept else None
    return (x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle, spread, body_step, 0.5)


def _example_count_nearest(device, dtype):
    return _example_nearest_inputs(device, dtype), {}


def _example_fill_nearest(device, dtype):
    args = _example_nearest_inputs(device, dtype)
    counts, chosen = _ref_contact_count_nearest(*args)
    total = int(counts.sum())
    offsets = _run_starts(counts)
    index = torch.zeros(total, dtype=torch.int64, device=device)
    values = torch.zeros(total, dtype=dtype, device=device)
    vectors = torch.zeros(total, 3, dtype=dtype, device=device)
    return (*args, offsets, chosen, index, index.clone(), vectors, vectors.clone(), values, vectors.clone(),
            values.clone()), {}


def _example_pair_product(device, dtype):
    """Three pairs over 6 nodes and a padding row, sorted by node as PairStiffness sorts them."""
    gen = torch.Generator().manual_seed(3)
    nodes = torch.tensor([[0, 3, 4, 5], [1, 3, 5, 4], [2, 0, 1, 3], [0, 0, 0, 0]])
    coef = torch.rand(4, 4, generator=gen, dtype=torch.float64)
    coef[3] = 0.0
    direction = torch.nn.functional.normalize(torch.randn(4, 3, generator=gen, dtype=torch.float64), dim=-1)
    normal = torch.tensor([2.0, 3.0, 1.5, 0.0], dtype=torch.float64)
    friction = torch.tensor([0.5, 0.0, 0.25, 0.0], dtype=torch.float64)
    targets, order = torch.sort(nodes[:3].reshape(-1), stable=True)
    order = torch.cat([order, torch.arange(12, 16)])
    offsets = torch.searchsorted(targets, torch.arange(7))
    dx = torch.randn(6, 3, generator=gen, dtype=torch.float64)
    floats = [t.to(device=device, dtype=dtype) for t in (dx, coef, direction, normal, friction)]
    return (floats[0], nodes.to(device), floats[1], floats[2], floats[3], floats[4], order.to(device),
            offsets.to(device), torch.zeros(4, 3, dtype=dtype, device=device),
            torch.zeros(6, 3, dtype=dtype, device=device)), {}


def _example_count(device, dtype):
    return _example_inputs(device, dtype), {}


def _example_fill(device, dtype):
    args = _example_inputs(device, dtype)
    counts = _ref_contact_count_candidates(*args)
    total = int(counts.sum())
    offsets = _run_starts(counts)
    vertex = torch.zeros(total, dtype=torch.int64, device=device)
    return (*args, offsets, vertex, torch.zeros_like(vertex)), {}


OPS = (
    OpDef("contact_count_candidates", _ref_contact_count_candidates, _fake_contact_count_candidates,
          differentiable=False, example=_example_count),
    OpDef("contact_fill_candidates", _ref_contact_fill_candidates, None, differentiable=False, mutates=True,
          example=_example_fill),
    OpDef("contact_count_nearest", _ref_contact_count_nearest, _fake_contact_count_nearest, differentiable=False,
          example=_example_count_nearest),
    OpDef("contact_fill_nearest", _ref_contact_fill_nearest, None, differentiable=False, mutates=True,
          example=_example_fill_nearest),
    OpDef("contact_pair_product", _ref_contact_pair_product, None, differentiable=False, mutates=True,
          example=_example_pair_product, scratch=("vector",)),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Group-level call
# ---------------------------------------------------------------------------------------------


@torch.no_grad()
def candidate_pairs(cell: torch.Tensor, low: torch.Tensor, high: torch.Tensor, triangle_object: torch.Tensor,
                    point_low: torch.Tensor, point_high: torch.Tensor, vertex_object: torch.Tensor, same_body: bool,
                    native: bool = True, triangle_first: "torch.Tensor | None" = None):
    """The broad phase (see the module): (vertex ids into the surface vertices ``[C]``, triangle
    ids ``[C]``), every candidate pair of a vertex box ``point_low, point_high [Sv, 3]`` (the same
    tensor twice for points) and a grown triangle box ``low, high [F, 3]`` of bodies
    ``vertex_object [Sv]``, ``triangle_object [F]`` (int64), through the ops where the extension
    serves the device (``native``), else their reference. ``cell``: the hash cell's side, a 0-dim
    tensor of the boxes' dtype, at least the largest grown triangle box's side. ``triangle_first
    [B + 1]`` (or None): where each body's triangles start, the triangles being in body order (the
    ops then skip each vertex's own body's entries; the same output). Two host reads (the
    entries' number, the candidates')."""
    queries = hash_queries(cell, low, high, point_low, point_high)
    args = (cell.reshape(1), point_low.contiguous(), point_high.contiguous(), vertex_object, *queries,
            low.contiguous(), high.contiguous(), triangle_object, bool(same_body), triangle_first)
    count = library.op_or_reference("contact_count_candidates", low.device, native)
    if count is _ref_contact_count_candidates:  # one pass of the reference does both
        query, entry = _kept(*args)
        return queries[0][query], queries[5][entry]
    counts = count(*args)
    offsets = _run_starts(counts)
    total = int(counts.sum())
    vertex = torch.empty(total, dtype=torch.int64, device=low.device)
    triangle = torch.empty_like(vertex)
    library.op("contact_fill_candidates")(*args, offsets, vertex, triangle)
    return vertex, triangle


def nearest_pairs(x: torch.Tensor, vertices: torch.Tensor, vertex_object: torch.Tensor, triangles: torch.Tensor,
                  triangle_object: torch.Tensor, candidate_vertex: torch.Tensor, candidate_triangle: torch.Tensor,
                  spread: "torch.Tensor | None", body_step: "torch.Tensor | None", reach: float,
                  native: bool = True):
    """The narrow phase (see the module) over the broad phase's candidates ``candidate_vertex,
    candidate_triangle [C]`` (grouped by vertex, ascending) at positions ``x [V, 3]``: (pair_vertex
    into ``vertices``, pair_triangle, weights ``[P, 3]``, diff ``[P, 3]``, distance ``[P]``, normal
    ``[P, 3]``, side ``[P]``). ``spread [V]`` and ``body_step [B, 3]`` (both or neither): the swept
    reach. Through the ops where the extension serves the device (``native``), else the
    reference; a vertex near more bodies than the kernel holds takes the reference, over its own
    candidates only (the memory stays that of the few such vertices in a jammed pile). One host
    read (the pairs' number, with the ops; two with such vertices). Where ``x`` requires grad, the
    reference (the weights, diff, distance and normal then carry the gradient: the energy's
    derivative flows through them)."""
    first = torch.searchsorted(candidate_vertex, torch.arange(len(vertices) + 1, device=x.device))
    args = (x.contiguous(), vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
            None if spread is None else spread.contiguous(), None if body_step is None else body_step.contiguous(),
            float(reach))
    count = library.op_or_reference("contact_count_nearest", x.device, native)
    if count is not _ref_contact_count_nearest and not (x.requires_grad and torch.is_grad_enabled()):
        counts, chosen = count(*args)
        fewest = counts.amin() if len(counts) else counts.new_zeros(())
        total, fewest = torch.stack([counts.sum(), fewest]).tolist()
        over = None
        if fewest < 0:  # (the fill pass writes nothing for a vertex past the kernel's slots)
            over = (counts < 0).nonzero().squeeze(1)
            counts = counts.clamp(min=0)
            total = int(counts.sum())
        offsets = _run_starts(counts)
        index = torch.empty(total, dtype=torch.int64, device=x.device)
        outputs = (index, torch.empty_like(index), x.new_empty(total, 3), x.new_empty(total, 3),
                   x.new_empty(total), x.new_empty(total, 3), x.new_empty(total))
        library.op("contact_fill_nearest")(*args, offsets, chosen, *outputs)
        return outputs if over is None else _with_crowded_vertices(outputs, over, args)
    return nearest_reference(*args)


def _with_crowded_vertices(outputs: tuple, over: torch.Tensor, args: tuple) -> tuple:
    """:func:`nearest_pairs`' ``outputs`` of the op with the pairs of the surface vertices ``over``
    (near more bodies than the kernel holds, which it left out) from the reference over their
    runs of candidates alone, in the reference's order (by vertex, then candidate)."""
    x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle, spread, body_step, reach = args
    lengths = first[over + 1] - first[over]
    packed = _run_starts(lengths)  # where each run starts among the crowded vertices' candidates
    total = int(lengths.sum())
    sub_first = torch.cat([packed, packed.new_full((1,), total)])
    entry = torch.repeat_interleave(first[over] - packed, lengths, output_size=total) + torch.arange(
        total, device=x.device)
    candidates = candidate_triangle[entry]
    crowded = nearest_reference(x, vertices[over], vertex_object[over], triangles, triangle_object, sub_first,
                                candidates, spread, body_step, reach)
    crowded = (over[crowded[0]], *crowded[1:])
    merged = [torch.cat([ours, theirs]) for ours, theirs in zip(outputs, crowded)]
    order = torch.sort(merged[0], stable=True)[1]
    return tuple(t[order] for t in merged)


def pair_product(dx: torch.Tensor, nodes: torch.Tensor, coef: torch.Tensor, direction: torch.Tensor,
                 normal: torch.Tensor, friction: torch.Tensor, order: torch.Tensor, offsets: torch.Tensor,
                 vector: torch.Tensor, native: bool = True,
                 add_to: Optional[torch.Tensor] = None, out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The pairs' product ``[V, 3]`` for ``dx [V, 3]`` (``contact_pair_product``; the buffers as
    ``body_contact.PairStiffness`` holds them, ``vector [C, 3]`` scratch), through the op where
    the extension serves the device (``native``), else its reference. ``add_to``: a contiguous
    ``[V, 3]`` product (not ``dx``) the pairs' is added to in place and returned; else ``out``: a
    contiguous ``[V, 3]`` buffer (not ``dx``) it is written into and returned (None: a new one)."""
    accumulate = add_to is not None
    out = add_to if accumulate else (torch.empty_like(dx) if out is None else out)
    library.op_or_reference("contact_pair_product", dx.device, native)(
        dx.contiguous(), nodes, coef, direction, normal, friction, order, offsets, vector, out, accumulate)
    return out
