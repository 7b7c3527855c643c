"""Kernel variants: which of the equivalent kernels the ops run, as explicit, frozen configuration.

Every variant computes the same system (bitwise, or CG's iterates rounded differently where
said); they differ in speed, and the tests run each. The solver carries one
:class:`KernelVariants` in its step options (``StepOptions.variants``) and passes it down to the
ops, which pass the C++ ones as arguments: no module global and no environment read decides a
kernel, so a CUDA graph captured with one configuration replays that configuration.

Environment variables, for benchmarks only, are read here and nowhere else
(:meth:`KernelVariants.from_env`, the default of ``StepOptions``):

    TENSORMASS_HOOKE_MATVEC=node|padded     hooke_matvec
    TENSORMASS_NODE_TANGENT=0|1             node_tangent
    TENSORMASS_NODE_GRAPH_WINDOW=<int>      node_graph_window
    TENSORMASS_PIPELINED_LAYOUTS=a,b        pipelined_layouts (shared, streamed)
    TENSORMASS_FUSED_STEP_END=0|1           fused_step_end
    TENSORMASS_SOLVE_STEP_RHS=0|1           solve_step_rhs
    TENSORMASS_NEIGHBOR_CACHE=0|1           neighbor_cache
    TENSORMASS_STREAM_CACHE_SLOTS=<int>     stream_cache_slots (-1: as many as fit)
    TENSORMASS_STREAM_PAIRS=0|1             stream_pairs
"""
from __future__ import annotations

import dataclasses
import os
from typing import Mapping, Optional, Tuple

__all__ = ["KernelVariants", "DEFAULT", "HOOKE_MATVEC_LAYOUTS", "PIPELINED_LAYOUTS"]

#: The layouts of the hooke tensor form's CG product: "node" (one kernel over the node graph,
#: ``hooke_node_system``) or "padded" (kernel 1 into PartialForce, then ``gather_system``).
HOOKE_MATVEC_LAYOUTS = ("node", "padded")
#: The layouts of the pipelined solve's node graph (csrc/solve/): "shared", chunks of 128 nodes
#: whose slots sit in shared memory for the whole solve (small systems: latency is all);
#: "streamed", chunks of 256 nodes, each node's first slots in shared memory and the rest read
#: from the graph every iteration (graphs beyond shared memory).
PIPELINED_LAYOUTS = ("shared", "streamed")


@dataclasses.dataclass(frozen=True)
class KernelVariants:
    """The kernel variants the ops run (all defaults: the fastest measured).

    Attributes:
        hooke_matvec: the hooke tensor form's CG product, "node" or "padded"
            (:data:`HOOKE_MATVEC_LAYOUTS`; bitwise the same).
        node_tangent: the CG products of stress-form stvk and corotational groups over the node
            graph with the differential at the linearisation as its slot tensors (once per
            linearisation), instead of an element pass per product.
        node_graph_window: the node graphs' rows: each object's nodes sorted by slot count,
            most first, within windows of this many nodes (a warp's threads then walk as many
            slots each); 0 or 1: rows in node order.
        pipelined_layouts: the pipelined solve's layouts, tried in this order (the first that
            fits one wave of the GPU runs; :data:`PIPELINED_LAYOUTS`).
        fused_step_end: a whole pipelined solve also ends the implicit Euler step
            (``hooke_node_solve_step``) instead of a separate ``euler_update``.
        solve_step_rhs: a solve that ends a step also computes its right-hand side
            (``hooke_node_steps``, chained steps in one kernel) instead of ``hooke_node_step_rhs``.
        neighbor_cache: the persistent CG (``hooke_node_cg``) keeps each node's neighbours in
            registers across iterations.
        stream_cache_slots: the streamed layout's cap on the slots of each node kept in shared
            memory (-1: as many as fit; 0 streams every slot).
        stream_pairs: the streamed layout's two threads a node walk its slots together.
    """

    hooke_matvec: str = "node"
    node_tangent: bool = True
    node_graph_window: int = 128
    pipelined_layouts: Tuple[str, ...] = PIPELINED_LAYOUTS
    fused_step_end: bool = True
    solve_step_rhs: bool = True
    neighbor_cache: bool = True
    stream_cache_slots: int = -1
    stream_pairs: bool = True

    def __post_init__(self):
        if self.hooke_matvec not in HOOKE_MATVEC_LAYOUTS:
            raise ValueError(f"KernelVariants.hooke_matvec: unknown layout {self.hooke_matvec!r}; "
                             f"known: {', '.join(HOOKE_MATVEC_LAYOUTS)}")
        layouts = tuple(self.pipelined_layouts)
        unknown = [name for name in layouts if name not in PIPELINED_LAYOUTS]
        if unknown or not layouts or len(set(layouts)) != len(layouts):
            raise ValueError(f"KernelVariants.pipelined_layouts: {layouts!r} must name each of "
                             f"{', '.join(PIPELINED_LAYOUTS)} at most once, and one at least")
        object.__setattr__(self, "pipelined_layouts", layouts)
        for name in ("node_graph_window", "stream_cache_slots"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int):
                raise TypeError(f"KernelVariants.{name} must be an int, got {value!r}")
        if self.stream_cache_slots < -1:
            raise ValueError(f"KernelVariants.stream_cache_slots must be >= -1, got {self.stream_cache_slots}")

    @property
    def solve_flags(self) -> int:
        """The C++ variant word of the solve family's ops: bit 0 neighbor_cache, bit 1
        stream_pairs (``csrc/solve/``)."""
        return int(self.neighbor_cache) | (int(self.stream_pairs) << 1)

    def replace(self, **changes) -> "KernelVariants":
        return dataclasses.replace(self, **changes)

    @classmethod
    def from_env(cls, environ: Optional[Mapping[str, str]] = None) -> "KernelVariants":
        """The variants the ``TENSORMASS_*`` environment variables of the module docstring name;
        the defaults for those unset. A bad value raises, naming the variable."""
        env = os.environ if environ is None else environ
        changes = {}

        def flag(var, field):
            text = env.get(var)
            if text is None:
                return
            if text.strip() not in ("0", "1"):
                raise ValueError(f"{var}={text!r}: use 0 or 1")
            changes[field] = text.strip() == "1"

        def integer(var, field):
            text = env.get(var)
            if text is None:
                return
            try:
                changes[field] = int(text)
            except ValueError:
                raise ValueError(f"{var}={text!r}: not an integer") from None

        if env.get("TENSORMASS_HOOKE_MATVEC") is not None:
            changes["hooke_matvec"] = env["TENSORMASS_HOOKE_MATVEC"].strip()
        flag("TENSORMASS_NODE_TANGENT", "node_tangent")
        integer("TENSORMASS_NODE_GRAPH_WINDOW", "node_graph_window")
        if env.get("TENSORMASS_PIPELINED_LAYOUTS") is not None:
            changes["pipelined_layouts"] = tuple(
                name.strip() for name in env["TENSORMASS_PIPELINED_LAYOUTS"].split(",") if name.strip())
        flag("TENSORMASS_FUSED_STEP_END", "fused_step_end")
        flag("TENSORMASS_SOLVE_STEP_RHS", "solve_step_rhs")
        flag("TENSORMASS_NEIGHBOR_CACHE", "neighbor_cache")
        integer("TENSORMASS_STREAM_CACHE_SLOTS", "stream_cache_slots")
        flag("TENSORMASS_STREAM_PAIRS", "stream_pairs")
        try:
            return cls(**changes)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"the TENSORMASS_* kernel variables: {exc}") from None


#: The variants of the ops' keyword defaults (all defaults; the environment is not read here).
DEFAULT = KernelVariants()
