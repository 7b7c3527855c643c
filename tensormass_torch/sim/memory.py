"""How much device memory a scene needs, before it is built; and a clear error, before anything is
allocated, where it cannot fit.

The estimate counts bytes an element and bytes a node: for each element kind, model and form,
what a scene of it holds while it steps, and what its peak over construction and the first steps
adds. A mesh's bytes depend on its nodes as much as on its elements: the node graph has a row of
blocks a node, and a small body has three times the nodes an element of a long beam (48-tet
cubes: 0.56 a tet; the paper's beam: 0.18), so a count by elements alone was 2.4 times under on
a batch of small bodies. Each is an index part (the same in every dtype) and a floating-point
part (4 bytes a number in float32, 8 in float64). How they were measured, and how close the
estimate is on the meshes measured: ``docs/scale.md``. Meshes of other shapes make it an
estimate, not a count.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, Sequence, Tuple, Union

import torch

from ..errors import SceneError

Parts = Tuple[int, int]  # (index bytes, floating-point bytes in float32)

#: held while stepping, by (element kind, model, form): (bytes an element, bytes a node), each
#: (index, float32 floating-point). Counted on the CPU (every tensor a simulator holds after two
#: steps) on two mesh families, a beam and a batch of small bodies, in float32 and float64: the
#: two families give the element and node parts, the two dtypes the index and float parts
#: (``benchmarks/studies/memory_parts.py``).
HELD: Dict[Tuple[str, str, str], Tuple[Parts, Parts]] = {
    ("tet", "hooke", "tensor"): ((28, 34), (172, 1155)),
    ("tet", "stvk", "stress"): ((102, 387), (509, 1908)),
    ("tet", "corotational", "stress"): ((102, 423), (509, 1908)),
    ("tri", "hooke", "tensor"): ((24, 40), (84, 464)),
    ("tri", "stvk", "stress"): ((73, 191), (191, 521)),
    ("tri", "corotational", "stress"): ((73, 275), (191, 521)),
}
#: what the peak adds to the held bytes, in the same form: the GPU's peaks (``torch.cuda
#: .max_memory_allocated``) on the paper's beam (hooke, stvk, corotational) and on a batch of
#: 48-tet stvk cubes, less the held bytes above at those meshes; the hooke construction's int64
#: temporaries a tet; the triangles' from their sheets (a CPU count)
PEAK_EXTRA: Dict[Tuple[str, str, str], Tuple[Parts, Parts]] = {
    ("tet", "hooke", "tensor"): ((122, 0), (0, 0)),
    ("tet", "stvk", "stress"): ((0, 14), (0, 879)),
    ("tet", "corotational", "stress"): ((0, 14), (0, 879)),
    ("tri", "hooke", "tensor"): ((0, 36), (0, 0)),
    ("tri", "stvk", "stress"): ((0, 68), (0, 0)),
    ("tri", "corotational", "stress"): ((0, 68), (0, 0)),
}
#: allocations of a GPU simulator that do not grow with its mesh (its captured graphs' pools,
#: small solver buffers), rounded up from what docs/scale.md measured
FIXED_BYTES = 64 * 2**20
#: the room a scene's estimated peak is given over it where the check decides: the estimate came
#: within 2 % of the GPU's measured peaks, on either side (docs/scale.md)
PEAK_MARGIN = 1.03
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
                    form: str = "auto", warm_start="none", precision: str = "full") -> MemoryEstimate:
    """The device memory a ``Simulator`` of ``bodies`` (a ``tm.Body`` or a list) needs, before it
    is built: a :class:`MemoryEstimate` (peak over construction and the first steps, and what it
    holds while stepping), from bytes an element and a node of each kind and model (``HELD``,
    ``PEAK_EXTRA``); on a GPU add ``FIXED_BYTES``.
    ``dtype``: the simulator's (float32 or float64); ``form``, ``warm_start``: as ``Simulator``'s
    (``"project"`` holds its basis, ``PROJECTION_VECTORS`` float64 vectors, and its operations
    make one more of that size at their peak; ``precision="mixed"`` holds a float32 copy of the
    model beside the float64 one, ``solver.refine``, and with ``"project"`` a copy of the basis
    that chained steps go back to where one of them fails)."""
    from ..physics.tensor_mass import _resolve_form
    from ..solver.guess import PROJECTION_VECTORS, warm_start_mode
    from .simulator import Body

    if isinstance(bodies, Body):
        bodies = [bodies]
    if dtype not in (torch.float32, torch.float64):
        raise SceneError(f"estimate_memory: dtype must be torch.float32 or torch.float64, got {dtype!r}")
    if precision not in ("full", "mixed"):
        raise SceneError(f"estimate_memory: precision must be 'full' or 'mixed', got {precision!r}")
    scale = torch.finfo(dtype).bits // 32  # floating-point parts are float32 bytes

    def bytes_of(parts: Tuple[Parts, Parts], count: int, nodes: int, scale: int = scale) -> int:
        (element_index, element_float), (node_index, node_float) = parts
        return (count * (element_index + scale * element_float)
                + nodes * (node_index + scale * node_float))

    basis_bytes = PROJECTION_VECTORS * 8 if warm_start_mode(warm_start) == "project" else 0  # a node, an axis
    elements = peak = held = 0
    for i, body in enumerate(bodies):
        if not isinstance(body, Body):
            raise SceneError(f"estimate_memory: bodies[{i}] is a {type(body).__name__}, not a tm.Body")
        material = body.material
        model_form = (material.model, _resolve_form(form, material))
        key = (body.mesh.kind, *_STAND_IN.get(model_form, model_form))
        count, nodes = int(body.mesh.elements.shape[0]), int(body.mesh.num_vertices)
        elements += count
        basis = basis_bytes * nodes * body.mesh.vertices.shape[1]
        body_held = bytes_of(HELD[key], count, nodes) + basis
        if precision == "mixed":  # the float32 copy the corrections run on; chained steps' copy of the basis
            body_held += bytes_of(HELD[key], count, nodes, 1) + basis
        held += body_held
        peak += body_held + bytes_of(PEAK_EXTRA[key], count, nodes) + basis
    return MemoryEstimate(elements, peak, held, dtype)


def free_bytes(device: torch.device) -> int:
    """Bytes the caching allocator can still give on a CUDA ``device``: the driver's free memory
    and what the allocator holds unused."""
    free, _ = torch.cuda.mem_get_info(device)
    return int(free + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device))


def check_fits(bodies, dtype: torch.dtype, device: torch.device, form: str = "auto", warm_start="none",
               precision: str = "full") -> None:
    """Raise ``SceneError`` before anything is allocated where a scene of ``bodies`` cannot fit on
    the CUDA ``device`` (its estimated peak over the free memory), saying the estimate, what is
    free and about how many elements would fit. Other devices: nothing (host memory is the
    operating system's to refuse)."""
    if device.type != "cuda" or not torch.cuda.is_available():
        return
    estimate = estimate_memory(bodies, dtype, form, warm_start, precision)
    free = free_bytes(device)
    room = max(int((free - FIXED_BYTES) / PEAK_MARGIN), 0)  # for the estimated peak
    if estimate.peak_bytes > room:
        raise SceneError(
            f"this scene does not fit on {device}: {estimate} (estimated, docs/scale.md), and "
            f"{free / 1e9:.3g} GB are free there; about {estimate.elements_that_fit(room):,} elements of these "
            f"kinds and models would fit. Use fewer elements, float32, or several GPUs "
            f"(tm.PartitionedSimulator, docs/distributed.md); check_memory=False skips this check")
