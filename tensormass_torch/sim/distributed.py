"""A batch of bodies over several processes (``torch.distributed``): data-parallel scenes.

    torchrun --nproc-per-node N -m tensormass_torch run SCENE --out DIR

Each process (a rank: one GPU, or a share of the CPU with gloo) builds and steps the simulator of
its share of the scene's bodies; the bodies are dealt by element count (:func:`partition_bodies`:
the largest first, each onto the lightest share), so the shares take about the same time a step.
A body's step depends on that body alone (the batched CG keeps per-object scalars), so the
bodies step as they do in one process: to rounding (the chunks of a batch's reductions follow
its node count), 1e-12 in float64 (tested).

Each rank writes its bodies' frames (``.vtu``, named by the body's index in the scene) and rank
0 the ``.pvd`` series of all. Every collective step goes through :func:`collectively`: what one
rank raises, every rank raises (a :class:`DistributedError` naming the ranks and their errors),
so no rank waits for one that failed; a rank that dies outright is seen by the others as a broken
connection, within the process group's timeout (``TENSORMASS_DIST_TIMEOUT_S``, default 120 s).

Contact between bodies and scalpels need every body in one process: such scenes are refused by
name. One large mesh over several processes is ``sim.partitioned``.
"""
from __future__ import annotations

import datetime
import os
from typing import Callable, List, Optional, Sequence, TypeVar

import torch

from ..errors import TensorMassError

T = TypeVar("T")


class DistributedError(TensorMassError):
    """A step of a batch over several processes failed on some rank (every rank raises it)."""


def partition_bodies(weights: Sequence[int], parts: int) -> List[List[int]]:
    """Deal bodies of ``weights`` (element counts) into ``parts`` shares of about equal weight:
    the heaviest first, each onto the lightest share so far (the lowest one on a tie). Returns
    each share's body indices, ascending; deterministic."""
    if isinstance(parts, bool) or not isinstance(parts, int) or parts < 1:
        raise ValueError(f"parts must be a positive integer, got {parts!r}")
    shares: List[List[int]] = [[] for _ in range(parts)]
    load = [0] * parts
    for body in sorted(range(len(weights)), key=lambda i: (-int(weights[i]), i)):
        lightest = min(range(parts), key=lambda p: (load[p], p))
        shares[lightest].append(body)
        load[lightest] += int(weights[body])
    return [sorted(share) for share in shares]


def launched() -> bool:
    """Whether this process is one of several started by ``torchrun`` (``WORLD_SIZE`` > 1)."""
    return int(os.environ.get("WORLD_SIZE", "1")) > 1


def init(device: Optional[str] = None) -> torch.device:
    """Join the process group ``torchrun`` set up (NCCL for CUDA, gloo for the CPU) and return
    this rank's device: ``cuda:LOCAL_RANK`` where ``device`` is CUDA, else ``device`` (or the CPU)."""
    import torch.distributed as dist

    wanted = torch.device(device) if device is not None else torch.device("cpu")
    if wanted.type == "cuda":
        wanted = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
        torch.cuda.set_device(wanted)
    if not dist.is_initialized():
        timeout = datetime.timedelta(seconds=float(os.environ.get("TENSORMASS_DIST_TIMEOUT_S", "120")))
        dist.init_process_group("nccl" if wanted.type == "cuda" else "gloo", timeout=timeout)
    return wanted


def group_device(device: Optional[torch.device] = None) -> torch.device:
    """Where the process group's collectives take their tensors: NCCL reduces device tensors
    only (``device``, default this process's current CUDA device), gloo CPU ones."""
    import torch.distributed as dist

    if dist.get_backend() != "nccl":
        return torch.device("cpu")
    return device if device is not None else torch.device("cuda", torch.cuda.current_device())


def collectively(work: Callable[[], T], what: str) -> T:
    """``work()`` on every rank; if it raises on any, every rank raises one
    :class:`DistributedError` saying ``what`` failed, on which ranks and why (one collective when
    all went well)."""
    import torch.distributed as dist

    try:
        result, error = work(), None
    except Exception as exc:  # noqa: BLE001 (handed to every rank)
        result, error = None, f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
    flag = torch.tensor([0 if error is None else 1], dtype=torch.int64, device=group_device())
    dist.all_reduce(flag)
    if int(flag.item()):
        errors: List[Optional[str]] = [None] * dist.get_world_size()
        dist.all_gather_object(errors, error)
        failed = "; ".join(f"rank {r}: {e}" for r, e in enumerate(errors) if e)
        raise DistributedError(f"{what} failed ({failed})")
    return result


class BatchShare:
    """This rank's share of a scene's bodies, built and stepped in step with the other ranks.

    Args:
        load: ``select -> scene``: builds the scene with the bodies ``select(bodies)`` chooses
            (``load_scene(path, select=...)``, or a built-in scene rebuilt with a subset).

    Attributes:
        scene: the scene of this rank's bodies (``scene.simulator`` None where it has none).
        body_ids: the scene's index of each of this rank's bodies.
    """

    def __init__(self, load: Callable):
        import torch.distributed as dist

        self.rank, self.world = dist.get_rank(), dist.get_world_size()

        def select(bodies):
            return partition_bodies([b.mesh.num_elements for b in bodies], self.world)[self.rank]

        self.scene = collectively(lambda: load(select), "loading the scene")
        self.body_ids = list(self.scene.body_ids)

    @property
    def simulator(self):
        return self.scene.simulator

    def step(self, n: int = 1) -> None:
        """``n`` steps of this rank's bodies, then the collective check."""
        sim = self.simulator
        collectively(lambda: sim.step(n) if sim is not None else None, f"a step at t = "
                     f"{0.0 if sim is None else sim.time:.6g}")


def select_bodies(scene, select):
    """A built-in scene (one whose bodies are already built) with the bodies ``select`` chooses:
    its simulator rebuilt over them (``Simulator.rebuilt``), ``body_ids`` set; an empty choice
    leaves no simulator."""
    import dataclasses

    sim = scene.simulator
    ids = sorted({int(i) for i in select(sim.bodies)})
    new = sim.rebuilt([sim.initial_bodies[i] for i in ids]) if ids and len(ids) < sim.num_bodies else (
        sim if ids else None)
    scene = dataclasses.replace(scene, simulator=new)
    scene.body_ids = ids
    return scene


__all__ = ["BatchShare", "DistributedError", "partition_bodies", "launched", "init", "collectively", "group_device",
           "select_bodies"]
