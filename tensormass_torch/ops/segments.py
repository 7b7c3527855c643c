"""Per-object reductions over packed nodes (objects own contiguous node ranges)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch


@dataclass
class Segments:
    """Contiguous node ranges of B objects.

    Attributes:
        lengths: nodes per object ``[B]`` (int64).
        node_object: object id of each node ``[V]`` (int64).
    """

    lengths: torch.Tensor
    node_object: torch.Tensor

    @classmethod
    def from_lengths(cls, lengths, device=None) -> "Segments":
        lengths = torch.as_tensor(lengths, dtype=torch.long, device=device)
        node_object = torch.repeat_interleave(torch.arange(lengths.numel(), device=lengths.device), lengths)
        return cls(lengths, node_object)

    @classmethod
    def single(cls, num_nodes: int, device=None) -> "Segments":
        return cls.from_lengths([num_nodes], device)

    @property
    def num_objects(self) -> int:
        return self.lengths.numel()

    @property
    def ptr(self) -> torch.Tensor:
        """Offsets ``[B + 1]``: object b owns nodes ``ptr[b]:ptr[b+1]``."""
        return torch.cat([self.lengths.new_zeros(1), torch.cumsum(self.lengths, 0)])

    def sum(self, values: torch.Tensor) -> torch.Tensor:
        """Per-object sums of per-node values ``[V]`` or ``[V, d]`` -> ``[B]``.

        ``segment_reduce`` sums each segment in a fixed order (no atomics): reproducible.
        """
        if values.dim() > 1:
            values = values.sum(dim=tuple(range(1, values.dim())))
        return torch.segment_reduce(values, "sum", lengths=self.lengths)

    def dot(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Per-object dot products of ``[V, d]`` fields -> ``[B]``."""
        return self.sum(a * b)

    def spread(self, per_object: torch.Tensor) -> torch.Tensor:
        """Per-object scalars ``[B]`` -> per-node column ``[V, 1]`` for broadcasting."""
        return per_object[self.node_object].unsqueeze(-1)

    def to(self, device) -> "Segments":
        """The same ranges on ``device``."""
        return Segments(self.lengths.to(device), self.node_object.to(device))


@dataclass
class ChunkPlan:
    """The objects' nodes cut into chunks of at most ``chunk_nodes`` nodes, each inside one object:
    the unit of work (one GPU block) of the CG reductions and updates (``solver.cg_ops``).

    Attributes:
        chunk_start: node offsets ``[K + 1]``: chunk k owns nodes ``chunk_start[k]:chunk_start[k+1]``.
        chunk_object: the object of each chunk ``[K]``.
        object_chunk: chunk offsets ``[B + 1]``: object b owns chunks ``object_chunk[b]:object_chunk[b+1]``.
        segments: the objects' node ranges (for the pure-torch reference).
    """

    chunk_start: torch.Tensor
    chunk_object: torch.Tensor
    object_chunk: torch.Tensor
    segments: Segments

    @staticmethod
    def auto_chunk_nodes(num_nodes: int) -> int:
        """Nodes per chunk for ``num_nodes`` in all: ~512 chunks (enough blocks to fill a GPU), at
        least 256 nodes (a block's 256 threads get one node each in the matvec; smaller chunks
        leave threads idle and multiply the blocks that meet at every reduction: on an H100 the
        SOFA beam's CG took 206 us with chunks of 256 against 227 us with 64, the paper beam's
        722 against 1,029 us with ~120, benchmarks/studies/cg_one_op_bench.py) and at most 4096 (the last
        block of an object sums its chunk sums: 10M nodes give 2,400 of them)."""
        return int(min(4096, max(256, -(-int(num_nodes) // 512))))

    @classmethod
    def from_segments(cls, segments: Segments, chunk_nodes: Optional[int] = None) -> "ChunkPlan":
        """``chunk_nodes``: None picks :meth:`auto_chunk_nodes` of the total node count."""
        if chunk_nodes is None:
            chunk_nodes = cls.auto_chunk_nodes(int(segments.lengths.sum()))
        if chunk_nodes < 1:
            raise ValueError(f"chunk_nodes must be >= 1, got {chunk_nodes}")
        lengths = segments.lengths.cpu()
        if bool((lengths < 1).any()):
            raise ValueError("every object needs at least one node")
        per_object = (lengths + chunk_nodes - 1) // chunk_nodes
        chunk_object = torch.repeat_interleave(torch.arange(lengths.numel()), per_object)
        object_chunk = torch.cat([per_object.new_zeros(1), torch.cumsum(per_object, 0)])
        object_start = torch.cat([lengths.new_zeros(1), torch.cumsum(lengths, 0)])
        rank = torch.arange(chunk_object.numel()) - object_chunk[chunk_object]  # chunk index inside its object
        start = object_start[chunk_object] + rank * chunk_nodes
        chunk_start = torch.cat([start, object_start[-1:]])
        device = segments.lengths.device
        return cls(chunk_start.to(device), chunk_object.to(device), object_chunk.to(device), segments)

    @classmethod
    def from_tensors(cls, chunk_start: torch.Tensor, chunk_object: torch.Tensor,
                     object_chunk: torch.Tensor) -> "ChunkPlan":
        """The plan of the CG ops' arguments (``tensors()``), its segments recovered from them."""
        starts = chunk_start[object_chunk.long()]
        return cls(chunk_start, chunk_object, object_chunk, Segments.from_lengths(starts[1:] - starts[:-1]))

    @property
    def num_chunks(self) -> int:
        return self.chunk_object.numel()

    def tensors(self):
        """``(chunk_start, chunk_object, object_chunk)``: the plan arguments of the CG ops."""
        return self.chunk_start, self.chunk_object, self.object_chunk
