"""The op library ``torch.ops.tensormass``: how an op is declared on the Python side, and the
registration every family module shares.

Each op family (``csrc/<family>/`` in C++, ``tensormass_torch.ops.<family>`` in Python) declares
its ops with :class:`OpDef`: the pure-torch reference (the tests' oracle, and the path of every
gradient the op does not compute itself), the fake kernel (output metadata, for torch.compile,
export and ``opcheck``), its autograd (fast gradients from the ops themselves, the rest through
``torch.func.vjp`` of the reference) and a small example (the inputs ``opcheck`` runs on). The
C++ fragment of a family names its Python module (``set_python_module``), so torch imports it when
it needs a fake kernel; :func:`ensure_registered` imports every family.

    FAMILIES                 the family modules, in registration order
    OpDef                    one op's Python side
    define(defs, register)   a family declares its ops (registered now if the extension is loaded)
    REGISTRY                 name -> OpDef of every declared op
    ensure_registered()      load the extension and register every family once
    available()              whether the ops are defined and registered
    pack(name, **named)      an op's positional arguments from its arguments' (and list members') names

Shared helpers of the families: ``MODEL_IDS`` (the ``model`` integer of the schemas), the cached
native index tensors of a gather plan (:func:`plan_indices`), and small tensor utilities.
"""
from __future__ import annotations

import dataclasses
import importlib
import threading
from typing import Callable, Dict, Optional, Tuple

import torch

from .reference import gather as ref_gather

__all__ = ["FAMILIES", "OpDef", "REGISTRY", "define", "register", "ensure_registered", "available", "pack", "MODEL_IDS",
           "ROTATION_IDS", "model_name", "plan_indices", "unchanged", "contiguous", "wants_grad", "slot_mask", "op",
           "Example", "supports", "op_or_reference"]

#: The op families, each a folder of csrc/ and a module of this package.
FAMILIES = ("stress", "tensor_form", "gather", "node_graph", "cg", "solve", "topology", "cutting", "multigrid",
            "contact")

#: The ``model`` integer of the op schemas ("stvk_definite": stvk with ``tangent="definite"``,
#: see ``reference.stress_form.kernel_model``).
MODEL_IDS = {"hooke": 0, "stvk": 1, "corotational": 2, "stvk_definite": 3}
MODEL_NAMES = {v: k for k, v in MODEL_IDS.items()}
#: The ``method`` integer of ``corotational_rotations``.
ROTATION_IDS = {"qr": 0, "polar": 1}


def model_name(model: int) -> str:
    try:
        return MODEL_NAMES[int(model)]
    except KeyError:
        raise ValueError(f"unknown model id {model!r} (0 = hooke, 1 = stvk, 2 = corotational, "
                         "3 = stvk with a definite tangent)") from None


@dataclasses.dataclass(frozen=True)
class OpDef:
    """The Python side of one op ``tensormass::<name>``.

    Attributes:
        name: the op's name in the library.
        reference: pure-torch function with the op's signature computing what the op computes (for
            ops that write into their arguments: the same writes; for ops returning whether they
            ran: True, having done the work).
        fake: the fake kernel (output metadata only; None for ops that return nothing).
        fast_gradients: ``(inputs, grad, needs) -> {position: gradient}``, the gradients the ops
            compute themselves; every other float input that needs one gets the reference's vjp.
        differentiable: False for solver kernels (run under no grad): their backward raises.
        mutates: the op writes into arguments (``Tensor(a!)``): no autograd is registered.
        example: ``(device, dtype) -> (args, kwargs)``: small valid inputs (``opcheck``, tests).
        scratch: the names of written arguments that are work buffers (contents unspecified
            between calls, or zero again after it): the reference need not reproduce them.
        defined: ``(args, output) -> output`` with the entries the op leaves unspecified zeroed
            (PartialForce's unused slots), or None: every entry is defined.
        members: for each list argument (``Tensor[]``, ``Tensor?[]``, ``float[]``), the names of the
            values it packs, in order (:func:`pack` builds the list from them; ``scratch`` may
            name them).
        devices: the device types the op has a kernel for; elsewhere it raises
            ``NotImplementedError``, changing nothing.
    """

    name: str
    reference: Callable
    fake: Optional[Callable]
    fast_gradients: Optional[Callable] = None
    differentiable: bool = True
    mutates: bool = False
    example: Optional[Callable] = None
    scratch: Tuple[str, ...] = ()
    defined: Optional[Callable] = None
    members: Dict[str, Tuple[str, ...]] = dataclasses.field(default_factory=dict)
    devices: Tuple[str, ...] = ("cpu", "cuda")


#: Every declared op: name -> OpDef.
REGISTRY: Dict[str, OpDef] = {}
_lock = threading.RLock()
_registered = set()
_family_registrations = []
_registered_families = -1  # len(_family_registrations) when available() last registered them all


def op(name: str):
    """The overload ``torch.ops.tensormass.<name>.default``."""
    return getattr(torch.ops.tensormass, name).default


def op_or_reference(name: str, device: torch.device, native: bool = True):
    """The op ``name`` where the extension serves ``device`` and has it (and ``native``), else its
    reference (the path of a family's calls where the extension is not built)."""
    from .. import _backend

    if native and _backend.use_extension(device) and ensure_registered() and hasattr(torch.ops.tensormass, name):
        return op(name)
    return REGISTRY[name].reference


def pack(name: str, **named):
    """The positional arguments of ``tensormass::<name>`` from its arguments by name, the values
    of each list argument by their names (``OpDef.members``) instead of the list: e.g.
    ``pack("hooke_node_solve", neighbor=..., node_k=..., ..., x=..., r=..., ...)``. Arguments with
    a default may be left out (they then take it)."""
    d = REGISTRY[name]
    args, missing, defaulted = [], [], False
    used = set()
    for a in op(name)._schema.arguments:
        if a.name in d.members:
            members = d.members[a.name]
            absent = [m for m in members if m not in named]
            missing += absent
            args.append([named.get(m) for m in members])
            used.update(members)
        elif a.name in named:
            if defaulted:
                raise TypeError(f"pack({name!r}): {a.name} given after an argument left to its default")
            args.append(named[a.name])
            used.add(a.name)
        elif a.has_default_value():
            defaulted = True
        else:
            missing.append(a.name)
    unknown = sorted(set(named) - used)
    if missing or unknown:
        raise TypeError(f"pack({name!r}): " + "; ".join(
            part for part in (f"missing {missing}" if missing else "", f"unknown {unknown}" if unknown else "")
            if part))
    return tuple(args)


def _ops_defined() -> bool:
    try:
        torch.ops.tensormass.stress_forces  # noqa: B018
    except (AttributeError, RuntimeError):
        return False
    return True


def define(defs, register: Callable[[], None]) -> None:
    """Declare a family's ops ``defs`` (OpDefs). ``register``: ``lambda: library.register(OPS)``
    written in the family module: torch checks that an op's fake kernel is registered from the
    Python module its C++ fragment names (``set_python_module``), and it looks at the frame that
    calls :func:`register`. Registered at once when the extension is loaded, else by
    :func:`ensure_registered`."""
    with _lock:
        for d in defs:
            known = REGISTRY.get(d.name)
            if known is not None and known is not d:
                raise ValueError(f"tensormass::{d.name} is declared twice")
            REGISTRY[d.name] = d
        _family_registrations.append(register)
        if _ops_defined():
            register()


def register(defs) -> None:
    """Register the fake kernels and autograd of ``defs`` with torch (once each); called through a
    family's ``register`` (see :func:`define`)."""
    with _lock:
        for d in defs:
            if d.name in _registered or not hasattr(torch.ops.tensormass, d.name):
                continue  # an extension built before this op existed has no schema for it
            qualname = "tensormass::" + d.name
            # _stacklevel=2: the frame that registers is the family module's (register's caller)
            torch.library.register_fake(qualname, d.fake if d.fake is not None else _returns_nothing, _stacklevel=2)
            if not d.mutates:
                torch.library.register_autograd(qualname, _make_backward(d), setup_context=_setup_context)
            _registered.add(d.name)


def _returns_nothing(*args, **kwargs):
    return None


def _import_families() -> None:
    for family in FAMILIES:
        importlib.import_module(f"{__package__}.{family}")


def available() -> bool:
    """Whether the ops are defined (the extension is loaded) and every family registered. Every
    op call asks: once each family is imported and registered (their count unchanged since), it
    answers without importing them again (a module lookup per family, on every eager op call)."""
    global _registered_families
    if not _ops_defined():
        return False
    if _registered_families == len(_family_registrations):
        return True
    with _lock:
        _import_families()
        for family_register in _family_registrations:
            family_register()
        _registered_families = len(_family_registrations)
    return True


def ensure_registered() -> bool:
    """Load the extension (unless forced off) and register fake kernels and autograd once."""
    from .. import _backend

    if _backend.load_extension() is None:
        return False
    return available()


# ---------------------------------------------------------------------------------------------
# Autograd: the fast gradients of the family, the rest through the reference's vjp
# ---------------------------------------------------------------------------------------------


def _is_float(x) -> bool:
    return isinstance(x, torch.Tensor) and x.is_floating_point()


def _setup_context(ctx, inputs, output):
    ctx.save_for_backward(*[x if isinstance(x, torch.Tensor) else None for x in inputs])
    ctx.plain = [None if isinstance(x, torch.Tensor) else x for x in inputs]


def _inputs(ctx):
    return [t if t is not None else p for t, p in zip(ctx.saved_tensors, ctx.plain)]


def reference_vjp(reference: Callable, inputs, wanted, cotangent):
    """Gradients of ``reference`` at ``inputs`` for the input positions ``wanted``."""
    if not wanted:
        return {}

    def fn(*diff):
        args = list(inputs)
        for pos, value in zip(wanted, diff):
            args[pos] = value
        return reference(*args)

    _, vjp_fn = torch.func.vjp(fn, *[inputs[i] for i in wanted])
    return dict(zip(wanted, vjp_fn(cotangent)))


def _make_backward(d: OpDef):
    if not d.differentiable:
        def refuse(ctx, *grads):
            raise RuntimeError(f"tensormass::{d.name} is not differentiable (a solver kernel): use the composed "
                               "path (tensormass_torch.ops.system_matvec falls back to it when gradients are needed)")

        return refuse

    def backward(ctx, grad):
        inputs = _inputs(ctx)
        # the dispatcher drops trailing arguments equal to their defaults (rest_elements=None)
        # from the autograd inputs, while setup_context sees them filled in
        passed = len(ctx.needs_input_grad)
        needs = list(ctx.needs_input_grad) + [False] * (len(inputs) - passed)
        fast = d.fast_gradients(inputs, grad.contiguous(), needs) if d.fast_gradients is not None else {}
        wanted = [i for i, x in enumerate(inputs) if needs[i] and _is_float(x) and i not in fast]
        slow = reference_vjp(d.reference, inputs, wanted, grad)
        grads = []
        for i in range(len(inputs)):
            g = fast.get(i, slow.get(i))
            grads.append(g if needs[i] else None)
        return tuple(grads[:passed])

    return backward


# ---------------------------------------------------------------------------------------------
# Fake kernels shared by the element families
# ---------------------------------------------------------------------------------------------


def fake_element(u, items, *_):
    """``[N, n, d]``: one partial force per item node."""
    return u.new_empty((items.shape[0], items.shape[1], u.shape[1]))


def fake_element_d(u, du, items, *_):
    return u.new_empty((items.shape[0], items.shape[1], u.shape[1]))


def fake_partial(u, items, force_index, num_slots, *_):
    """PartialForce ``[N_n, V, d]``."""
    return u.new_empty((num_slots, u.shape[0], u.shape[1]))


def fake_partial_d(u, du, items, force_index, num_slots, *_):
    return u.new_empty((num_slots, u.shape[0], u.shape[1]))


def fake_nodes(u, *_):
    """``[V, d]``."""
    return u.new_empty(u.shape)


# ---------------------------------------------------------------------------------------------
# Helpers of the families' references and wrappers
# ---------------------------------------------------------------------------------------------

_INT32_MAX = 2**31 - 1


def scatter(partial, index, force_index, num_slots, num_nodes):
    """Compact partial forces ``[N, n, d]`` into PartialForce ``[N_n, V, d]`` (zeros in unused slots)."""
    return ref_gather.scatter_partial_forces(partial, index, force_index, num_slots, num_nodes)


def gather(partial, index, force_index, num_slots, incidences, node_term=None):
    """Kernel 2's reference on compact partial forces ``[N, n, d]`` -> ``[V, d]``."""
    return ref_gather.node_gather(partial, index, force_index, num_slots, incidences.shape[0], node_term)


def partial_defined(items_position: int):
    """``OpDef.defined`` of the ops that write PartialForce ``[N_n, V, d]``: the slots of the
    items (``args[items_position]`` ``[N, n]``, their ``force_index`` the next argument) kept,
    the others zeroed (the op leaves them uninitialised)."""

    def defined(args, partial):
        items, force_index = args[items_position].long(), args[items_position + 1].long()
        used = torch.zeros(partial.shape[:2], dtype=torch.bool, device=partial.device)
        used[force_index.reshape(-1), items.reshape(-1)] = True
        return torch.where(used[..., None], partial, partial.new_zeros(()))

    return defined


def slot_mask(num_slots, incidences):
    """``[N_n, V, 1]``: whether slot s of node i is used (s < incidences[i])."""
    slots = torch.arange(num_slots, device=incidences.device)
    return (slots[:, None] < incidences[None, :])[:, :, None]


def unchanged(cache, tensors) -> bool:
    """Whether ``cache`` (tensors, versions, value) was made from these very tensors, unmodified."""
    return (cache is not None and len(cache[0]) == len(tensors)
            and all(a is b for a, b in zip(cache[0], tensors))
            and cache[1] == tuple(t._version for t in tensors))


def plan_indices(plan):
    """(index, force_index, incidences) of a GatherPlan, as int32 when every value fits (half
    the index bytes the kernels read), cached on the plan while its tensors are unchanged."""
    tensors = (plan.index, plan.force_index, plan.incidences)
    cache = getattr(plan, "_native_indices", None)
    if unchanged(cache, tensors):
        return cache[2]
    small = (plan.num_nodes <= _INT32_MAX and plan.num_slots <= _INT32_MAX
             and plan.index.numel() <= _INT32_MAX)
    dtype = torch.int32 if small else torch.int64
    value = tuple(t.to(dtype).contiguous() for t in tensors)
    try:
        plan._native_indices = (tensors, tuple(t._version for t in tensors), value)
    except AttributeError:  # a plan type without a __dict__: no cache
        pass
    return value


@torch.no_grad()
def refresh_plan_indices(plan):
    """:func:`plan_indices` after the plan's tensors changed in place or grew (a topology change):
    each native copy of the same shape is overwritten in place (captured CUDA graphs read it), one
    that grew is made again; returns them."""
    cache = getattr(plan, "_native_indices", None)
    if cache is None:
        return plan_indices(plan)
    tensors = (plan.index, plan.force_index, plan.incidences)
    value = []
    for tensor, native in zip(tensors, cache[2]):
        if native is not tensor and native.shape == tensor.shape:
            native.copy_(tensor)
        elif native is not tensor:
            native = tensor.to(native.dtype).contiguous()
        value.append(native)
    plan._native_indices = (tensors, tuple(t._version for t in tensors), tuple(value))
    return tuple(value)


def supports(group, u: torch.Tensor) -> bool:
    """Whether the ops can evaluate ``group`` at ``u`` (dtype and device of the group's data)."""
    if u.dtype not in (torch.float32, torch.float64) or u.dim() != 2:
        return False
    if group.measure.dtype != u.dtype or group.measure.device != u.device:
        return False
    if group.model == "corotational":
        # both rotation methods (qr: 3-D; polar: tets, 2-D triangles, membranes)
        return (group.rotation in ROTATION_IDS and group.form == "stress"
                and (group.rotation == "polar" or u.shape[1] == 3))
    return group.model in MODEL_IDS and group.form in ("stress", "tensor")


def contiguous(*tensors):
    return tuple(None if t is None else t.contiguous() for t in tensors)


def wants_grad(tensors) -> bool:
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


class Example:
    """A small mesh for the ops' examples (``OpDef.example``): two tetrahedra sharing a face
    (``dim`` 3) or two triangles sharing an edge (``dim`` 2) with random displacements, and every
    tensor the element ops take, in ``dtype`` on ``device``; index tensors int32.

    Attributes: u, du ``[V, d]``; rest ``[V, d]``; elements ``[N, n]`` and their plan (index,
    force_index ``[N, n]``, num_slots, incidences ``[V]``); m ``[N, n, d]``, vol, lam, mu ``[N]``;
    edges ``[Ed, 2]``, their plan (edge_force_index, edge_slots, edge_incidences) and edge_k
    ``[Ed, d, d]``; tensor_b, tensor_c, tensor_d (the stvk tensor form's).

    ``uniform``: two tetrahedra on the same four nodes instead, so that every node has as many
    elements (and edges) as every other: PartialForce then has no unused slot (whose contents the
    ops leave unspecified, which ``opcheck`` would compare).
    """

    def __init__(self, device, dtype, dim: int = 3, uniform: bool = False):
        from ..mesh.geometry import shape_vectors
        from ..mesh.topology import GatherPlan
        from .reference import tensor_form

        gen = torch.Generator().manual_seed(7)
        if uniform:
            elements = torch.tensor([[0, 1, 2, 3], [0, 2, 3, 1]])
            rest = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=torch.float64)
        elif dim == 3:
            elements = torch.tensor([[0, 1, 2, 3], [1, 2, 3, 4]])
            rest = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], dtype=torch.float64)
        else:
            elements = torch.tensor([[0, 1, 2], [1, 3, 2]])
            rest = torch.tensor([[0.0, 0], [1, 0], [0, 1], [1, 1]], dtype=torch.float64)
        num_nodes, num_elements = rest.shape[0], elements.shape[0]
        m, vol = shape_vectors(rest[elements])
        lam = torch.full((num_elements,), 2.0, dtype=torch.float64)
        mu = torch.full((num_elements,), 1.5, dtype=torch.float64)
        edges, edge_k = tensor_form.assemble_edges(tensor_form.element_stiffness(m, vol, lam, mu), elements,
                                                   num_nodes)
        b, c, d = tensor_form.stvk_tensors(m, vol, lam, mu)
        plan, edge_plan = GatherPlan.build(elements, num_nodes), GatherPlan.build(edges, num_nodes)

        def f(t):
            return t.to(device=device, dtype=dtype).contiguous()

        def i(t):
            return t.to(device=device, dtype=torch.int32).contiguous()

        self.device, self.dtype, self.dim = torch.device(device), dtype, dim
        self.u = f(0.05 * torch.randn(rest.shape, generator=gen, dtype=torch.float64))
        self.du = f(torch.randn(rest.shape, generator=gen, dtype=torch.float64))
        self.rest = f(rest)
        self.elements, self.force_index, self.num_slots = i(elements), i(plan.force_index), plan.num_slots
        self.incidences = i(plan.incidences)
        self.m, self.vol, self.lam, self.mu = f(m), f(vol), f(lam), f(mu)
        self.edges, self.edge_force_index, self.edge_slots = i(edges), i(edge_plan.force_index), edge_plan.num_slots
        self.edge_incidences, self.edge_k = i(edge_plan.incidences), f(edge_k)
        self.tensor_b, self.tensor_c, self.tensor_d = f(b), f(c), f(d)
        self.mass = f(torch.linspace(1.0, 2.0, num_nodes, dtype=torch.float64))
        self.free = f(torch.tensor([0.0] + [1.0] * (num_nodes - 1), dtype=torch.float64))

    @property
    def num_nodes(self) -> int:
        return self.u.shape[0]

    def stress(self, model: str = "hooke"):
        """The trailing stress-op arguments (m, vol, lam, mu, projector, model, rest_elements,
        rotations) for ``model`` (corotational: the rest element nodes, R recomputed per call)."""
        rest = self.rest[self.elements.long()].contiguous() if model == "corotational" else None
        return (self.m, self.vol, self.lam, self.mu, None, MODEL_IDS[model], rest, None)
