"""How much device memory a scene needs, before it is built; and a clear error, before anything is
allocated, where it cannot fit.

The estimate counts bytes an element: for each element kind, model and form, what a scene of it
holds while it steps and its peak over construction and the first steps, measured through the
public API (``benchmarks/studies/setup_memory.py``; the runs and the estimate's accuracy on other
meshes: ``docs/scale.md``). Each is an index part (the same in every dtype) and a floating-point
part (4 bytes a number in float32, 8 in float64): meshes of other shapes, with other node and edge
counts an element, make it an estimate, not a count.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Sequence, Tuple, Union

import torch

from ..errors import SceneError

#: bytes an element (index part, floating-point part in float32) by (element kind, model, form):
#: (held while stepping, peak over construction and the first steps), from the measurements of
#: the module docstring (float32 and float64 runs of each, the parts their difference); the held
#: index parts less what the groups' int32 indices saved (the held bytes before and after, counted
#: on the CPU: 52-66 B an element, docs/scale.md). The peaks are kept: the hooke beam's measured
#: peak did not fall (the construction's int64 temporaries), and a high estimate only refuses
#: early, where a low one would let a scene run out of memory.
BYTES_PER_ELEMENT: Dict[Tuple[str, str, str], Tuple[Tuple[int, int], Tuple[int, int]]] = {
    ("tet", "hooke", "tensor"): ((67, 238), (192, 250)),
    ("tet", "stvk", "stress"): ((202, 713), (272, 815)),
    ("tet", "corotational", "stress"): ((204, 748), (272, 851)),
    ("tri", "hooke", "tensor"): ((76, 273), (140, 309)),
    ("tri", "stvk", "stress"): ((179, 447), (231, 515)),
    ("tri", "corotational", "stress"): ((179, 531), (231, 599)),
}
#: the stress form of hooke, and stvk's tensor form, were not measured: the nearest that was
_STAND_IN = {("hooke", "stress"): ("stvk", "stress"), ("stvk", "tensor"): ("stvk", "stress")}


@dataclass(frozen=True)
class MemoryEstimate:
    """What a scene needs on its device: ``peak_bytes`` (construction and the first steps) and
    ``held_bytes`` (while it steps), for ``elements`` elements in ``dtype``."""

    elements: int
    peak_bytes: int
    held_bytes: int
    dtype: torch.dtype

    def elements_that_fit(self, free_bytes: int) -> int:
        """About how many elements of this scene's kinds and models would fit in ``free_bytes``."""
        return int(self.elements * free_bytes / max(self.peak_bytes, 1))

    def __str__(self) -> str:
        return (f"{self.elements:,} elements in {str(self.dtype).replace('torch.', '')}: peak "
                f"{self.peak_bytes / 1e9:.3g} GB, held while stepping {self.held_bytes / 1e9:.3g} GB")


def estimate_memory(bodies: Union["Body", Sequence["Body"]], dtype: torch.dtype = torch.float32,  # noqa: F821
                    form: str = "auto") -> MemoryEstimate:
    """The device memory a ``Simulator`` of ``bodies`` (a ``tm.Body`` or a list) needs, before it
    is built: a :class:`MemoryEstimate` (peak over construction and the first steps, and what it
    holds while stepping), from bytes an element of each kind and model (``BYTES_PER_ELEMENT``).
    ``dtype``: the simulator's (float32 or float64); ``form``: as ``Simulator``'s."""
    from ..physics.tensor_mass import _resolve_form
    from .simulator import Body

    if isinstance(bodies, Body):
        bodies = [bodies]
    if dtype not in (torch.float32, torch.float64):
        raise SceneError(f"estimate_memory: dtype must be torch.float32 or torch.float64, got {dtype!r}")
    scale = torch.finfo(dtype).bits // 32  # floating-point parts are float32 bytes
    elements = peak = held = 0
    for i, body in enumerate(bodies):
        if not isinstance(body, Body):
            raise SceneError(f"estimate_memory: bodies[{i}] is a {type(body).__name__}, not a tm.Body")
        material = body.material
        model_form = (material.model, _resolve_form(form, material))
        model_form = _STAND_IN.get(model_form, model_form)
        (held_index, held_float), (peak_index, peak_float) = BYTES_PER_ELEMENT[(body.mesh.kind, *model_form)]
        count = int(body.mesh.elements.shape[0])
        elements += count
        held += count * (held_index + scale * held_float)
        peak += count * (peak_index + scale * peak_float)
    return MemoryEstimate(elements, peak, held, dtype)


def free_bytes(device: torch.device) -> int:
    """Bytes the caching allocator can still give on a CUDA ``device``: the driver's free memory
    and what the allocator holds unused."""
    free, _ = torch.cuda.mem_get_info(device)
    return int(free + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device))


def check_fits(bodies, dtype: torch.dtype, device: torch.device, form: str = "auto") -> None:
    """Raise ``SceneError`` before anything is allocated where a scene of ``bodies`` cannot fit on
    the CUDA ``device`` (its estimated peak over the free memory), saying the estimate, what is
    free and about how many elements would fit. Other devices: nothing (host memory is the
    operating system's to refuse)."""
    if device.type != "cuda" or not torch.cuda.is_available():
        return
    estimate = estimate_memory(bodies, dtype, form)
    free = free_bytes(device)
    if estimate.peak_bytes > free:
        raise SceneError(
            f"this scene does not fit on {device}: {estimate} (estimated, docs/scale.md), and "
            f"{free / 1e9:.3g} GB are free there; about {estimate.elements_that_fit(free):,} elements of these "
            f"kinds and models would fit. Use fewer elements, float32, or several GPUs "
            f"(tm.PartitionedSimulator, docs/distributed.md); check_memory=False skips this check")
