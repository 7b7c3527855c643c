"""Node selections (fixed or prescribed nodes) given as a mask or as indices."""
from __future__ import annotations

import torch

from ..errors import SceneError


def node_mask(nodes, num_nodes: int, name: str, device=None) -> torch.Tensor:
    """A bool mask ``[V]`` from a bool mask ``[V]``, an index tensor/list ``[k]`` or None.

    Raises SceneError naming ``name`` for a mask of the wrong length, non-integer indices or
    indices out of range.
    """
    if nodes is None:
        return torch.zeros(num_nodes, dtype=torch.bool, device=device)
    t = torch.as_tensor(nodes, device=device)
    if t.dtype == torch.bool:
        if t.shape != (num_nodes,):
            raise SceneError(f"{name}: a mask must have shape [{num_nodes}], got {tuple(t.shape)}")
        return t.clone()
    if t.dtype.is_floating_point or t.dtype.is_complex:
        raise SceneError(f"{name}: node indices must be integers or a bool mask, got {t.dtype}")
    t = t.reshape(-1).long()
    bad = (t < 0) | (t >= num_nodes)
    if bad.any():
        raise SceneError(f"{name}: node indices out of range [0, {num_nodes}): {t[bad][:10].tolist()}")
    mask = torch.zeros(num_nodes, dtype=torch.bool, device=t.device)
    mask[t] = True
    return mask
