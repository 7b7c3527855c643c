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
        query_start, query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body)
            -> counts [Q]: how many candidates each query keeps
    contact_fill_candidates(the same, offsets, vertex!, triangle!)
            the candidates, query q's from offsets[q] in run order

Why ops: as tensor ops the walk materialises every entry of every query's run before filtering
it, and the runs hold mostly the vertex's own body's triangles. The ops' output is the
reference's, in its order, so the narrow phase that follows sees the same pairs either way.
Not differentiable (indices).
"""
from __future__ import annotations

import torch

from . import library
from .library import OpDef

__all__ = ["hash_key", "covered_cells", "hash_queries", "candidate_pairs"]


def hash_key(cells: torch.Tensor) -> torch.Tensor:
    """An int64 key of integer cells ``[..., 3]``: distinct cells may share one (the candidates
    check the cell itself, so a collision costs work, never a contact)."""
    return (cells[..., 0] * 73856093) ^ (cells[..., 1] * 19349663) ^ (cells[..., 2] * 83492791)


def covered_cells(low: torch.Tensor, high: torch.Tensor, cell):
    """The cells of side ``cell`` that boxes [low, high] ``[N, 3]`` cover: (box ids ``[E]``,
    integer cells ``[E, 3]``), each box's cells in a row (one host read: their number)."""
    first = torch.floor(low / cell).to(torch.int64)
    span = torch.floor(high / cell).to(torch.int64) - first + 1  # [N, 3] cells per axis
    count = span.prod(-1)
    total = int(count.sum())
    box = torch.repeat_interleave(torch.arange(len(low), device=low.device), count, output_size=total)
    local = torch.arange(total, device=low.device) - (torch.cumsum(count, 0) - count)[box]
    ny, nz = span[box, 1], span[box, 2]
    offset = torch.stack([local // (ny * nz), (local // nz) % ny, local % nz], dim=-1)
    return box, first[box] + offset


def hash_queries(cell: torch.Tensor, low: torch.Tensor, high: torch.Tensor, point_low: torch.Tensor,
                 point_high: torch.Tensor):
    """The spatial hash of the triangles' grown boxes ``low, high [F, 3]`` and the queries of the
    vertices' boxes ``point_low, point_high [Sv, 3]`` (the same tensor twice: points, one query
    each, with no host read), cells of side ``cell`` (a 0-dim tensor): (query_vertex ``[Q]``,
    query_cells ``[Q, 3]``, query_start ``[Q]``, query_stop ``[Q]``, entry_triangle ``[E]``,
    entry_cells ``[E, 3]``), the entries sorted by key (stably: a key's entries in triangle order),
    every tensor contiguous int64."""
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
    return query_vertex, query_cells.contiguous(), start, stop, entry_triangle, entry_cells


# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
          entry_triangle, entry_cells, low, high, triangle_object, same_body):
    """(query ``[C]``, entry ``[C]``) of the kept candidates in the ops' order."""
    counts = query_stop - query_start
    total = int(counts.sum())
    device = query_start.device
    query = torch.repeat_interleave(torch.arange(len(query_start), device=device), counts, output_size=total)
    first_of = torch.repeat_interleave(query_start - (torch.cumsum(counts, 0) - counts), counts, output_size=total)
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
                                  query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body):
    query, _ = _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
                     entry_triangle, entry_cells, low, high, triangle_object, same_body)
    return torch.bincount(query, minlength=len(query_vertex))


def _ref_contact_fill_candidates(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                                 query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body,
                                 offsets, vertex, triangle):
    query, entry = _kept(cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                         query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body)
    vertex.copy_(query_vertex[query])
    triangle.copy_(entry_triangle[entry])


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
    return (cell.reshape(1), points, point_high, vertex_object, *queries[:4], queries[4], queries[5], low, high,
            triangle_object, False)


def _example_count(device, dtype):
    return _example_inputs(device, dtype), {}


def _example_fill(device, dtype):
    args = _example_inputs(device, dtype)
    counts = _ref_contact_count_candidates(*args)
    total = int(counts.sum())
    offsets = torch.cumsum(counts, 0) - counts
    vertex = torch.zeros(total, dtype=torch.int64, device=device)
    return (*args, offsets, vertex, torch.zeros_like(vertex)), {}


OPS = (
    OpDef("contact_count_candidates", _ref_contact_count_candidates, _fake_contact_count_candidates,
          differentiable=False, example=_example_count),
    OpDef("contact_fill_candidates", _ref_contact_fill_candidates, None, differentiable=False, mutates=True,
          example=_example_fill),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Group-level call
# ---------------------------------------------------------------------------------------------


@torch.no_grad()
def candidate_pairs(cell: torch.Tensor, low: torch.Tensor, high: torch.Tensor, triangle_object: torch.Tensor,
                    point_low: torch.Tensor, point_high: torch.Tensor, vertex_object: torch.Tensor, same_body: bool,
                    native: bool = True):
    """The broad phase (see the module): (vertex ids into the surface vertices ``[C]``, triangle
    ids ``[C]``), every candidate pair of a vertex box ``point_low, point_high [Sv, 3]`` (the same
    tensor twice for points) and a grown triangle box ``low, high [F, 3]`` of bodies
    ``vertex_object [Sv]``, ``triangle_object [F]`` (int64), through the ops where the extension
    serves the device (``native``), else their reference. ``cell``: the hash cell's side, a 0-dim
    tensor of the boxes' dtype, at least the largest grown triangle box's side. Two host reads
    (the entries' number, the candidates')."""
    queries = hash_queries(cell, low, high, point_low, point_high)
    args = (cell.reshape(1), point_low.contiguous(), point_high.contiguous(), vertex_object, *queries[:4],
            queries[4], queries[5], low.contiguous(), high.contiguous(), triangle_object, bool(same_body))
    count = library.op_or_reference("contact_count_candidates", low.device, native)
    if count is _ref_contact_count_candidates:  # one pass of the reference does both
        query, entry = _kept(*args)
        return queries[0][query], queries[4][entry]
    counts = count(*args)
    offsets = torch.cumsum(counts, 0) - counts
    total = int(counts.sum())
    vertex = torch.empty(total, dtype=torch.int64, device=low.device)
    triangle = torch.empty_like(vertex)
    library.op("contact_fill_candidates")(*args, offsets, vertex, triangle)
    return vertex, triangle
