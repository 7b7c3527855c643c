"""Per-object reductions over packed nodes (objects own contiguous node ranges)."""
from __future__ import annotations

from dataclasses import dataclass

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
        return Segments(self.lengths.to(device), self.node_object.to(device))
