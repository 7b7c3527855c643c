"""Every op registered under ``torch.ops.tensormass`` has its Python side: a declaration
(``ops.library.OpDef``) with a fake kernel, a pure-torch reference and an example, passes
``torch.library.opcheck`` (schema and mutation annotations, fake tensors, autograd registration,
AOT dispatch) on its example, and computes what its reference computes there (every output and
every argument it writes), on the CPU and, where there is one, on CUDA.

A new op without these fails here by name: adding an op is a C++ folder, a family module and
its test file (docs/adding-an-op.md), and this walk covers it with no edit.
"""
from __future__ import annotations

import pytest
import torch

from tensormass_torch.ops import library

pytestmark = pytest.mark.skipif(not library.ensure_registered(), reason="the compiled extension is not available")

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _registered_ops():
    if not library.ensure_registered():
        return []
    return sorted(name.split("::", 1)[1] for name in torch._C._dispatch_get_all_op_names()
                  if name.startswith("tensormass::"))


def test_every_registered_op_is_declared_and_every_declared_op_is_registered():
    registered = set(_registered_ops())
    assert registered, "no op under torch.ops.tensormass"
    assert registered == set(library.REGISTRY), (
        f"registered but not declared: {sorted(registered - set(library.REGISTRY))}; "
        f"declared but not registered: {sorted(set(library.REGISTRY) - registered)}")


@pytest.mark.parametrize("name", _registered_ops())
def test_op_has_a_reference_a_fake_kernel_and_an_example(name):
    d = library.REGISTRY.get(name)
    assert d is not None, f"tensormass::{name} has no OpDef"
    assert callable(d.reference), f"tensormass::{name} has no pure-torch reference"
    assert callable(d.example), f"tensormass::{name} has no example"
    schema = library.op(name)._schema
    returns_nothing = len(schema.returns) == 0
    assert d.fake is not None or returns_nothing, f"tensormass::{name} returns values but has no fake kernel"
    mutable = any(a.alias_info is not None and a.alias_info.is_write for a in schema.arguments)
    assert d.mutates == mutable, f"tensormass::{name}: OpDef.mutates={d.mutates} but the schema says {mutable}"


def _clone(value):
    if isinstance(value, torch.Tensor):
        return value.clone()
    if isinstance(value, list):  # a packed list argument
        return [_clone(v) for v in value]
    return value


def _runs_on(d, device) -> bool:
    return torch.device(device).type in d.devices


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", _registered_ops())
def test_op_passes_opcheck_on_its_example(name, device):
    d = library.REGISTRY[name]
    if not _runs_on(d, device):
        pytest.skip(f"tensormass::{name} has no {device} kernel")
    args, kwargs = d.example(device, torch.float64)
    utils = ("test_schema", "test_autograd_registration", "test_faketensor", "test_aot_dispatch_dynamic")
    torch.library.opcheck(library.op(name), args, kwargs, test_utils=utils)


def _written(d, args, scratch=()):
    """The tensors the op writes (``Tensor(a!)``, ``Tensor(a!)[]``) but its work buffers, as
    (name, accessor): ``accessor(args)`` is the tensor."""
    out = []
    for i, a in enumerate(library.op(d.name)._schema.arguments[:len(args)]):
        if a.alias_info is None or not a.alias_info.is_write or a.name in scratch:
            continue
        if isinstance(args[i], torch.Tensor):
            out.append((a.name, lambda values, i=i: values[i]))
        elif isinstance(args[i], list):
            names = d.members.get(a.name, [f"{a.name}[{j}]" for j in range(len(args[i]))])
            out += [(member, lambda values, i=i, j=j: values[i][j]) for j, member in enumerate(names)
                    if member not in scratch and isinstance(args[i][j], torch.Tensor)]
    return out


def test_list_arguments_name_their_members():
    """Every list argument of every op names its members (``OpDef.members``, which
    ``library.pack`` and the written-tensor comparisons use), and a list's members are unique
    names across the op."""
    for name in _registered_ops():
        d = library.REGISTRY[name]
        lists = {a.name for a in library.op(name)._schema.arguments if isinstance(a.type, torch.ListType)
                 and not isinstance(a.type.getElementType(), torch.IntType)}
        assert lists == set(d.members), f"tensormass::{name}: list arguments {sorted(lists)}, members {sorted(d.members)}"
        names = [m for members in d.members.values() for m in members]
        names += [a.name for a in library.op(name)._schema.arguments if a.name not in d.members]
        assert len(names) == len(set(names)), f"tensormass::{name}: a name used twice: {names}"
        args, kwargs = d.example("cpu", torch.float64)
        for a, value in zip(library.op(name)._schema.arguments, args):
            if a.name in d.members:
                assert len(value) == len(d.members[a.name]), f"tensormass::{name}: the example's {a.name}"


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32], ids=["float64", "float32"])
@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", _registered_ops())
def test_op_computes_its_reference_on_its_example(name, device, dtype):
    d = library.REGISTRY[name]
    args, kwargs = d.example(device, dtype)
    op_args = [_clone(a) for a in args]
    ref_args = [_clone(a) for a in args]
    if not _runs_on(d, device):  # no kernel here (the pipelined solves on the CPU): one error, nothing changed
        with pytest.raises(NotImplementedError):
            library.op(name)(*op_args, **kwargs)
        for member, get in _written(d, args):
            # bit for bit, NaN included: an unwritten buffer may hold anything (torch.empty)
            torch.testing.assert_close(get(op_args), get(args), rtol=0, atol=0, equal_nan=True,
                                       msg=f"{member} written although the op did not run")
        return
    out = library.op(name)(*op_args, **kwargs)
    if d.mutates:
        out = None  # an op that writes its results returns nothing: compare the writes
    with torch.no_grad():
        ref = d.reference(*ref_args, **kwargs)
    if out is None:
        ref = None
    tol = dict(rtol=1e-9, atol=1e-11) if dtype == torch.float64 else dict(rtol=2e-4, atol=1e-5)
    outs = out if isinstance(out, (tuple, list)) else () if out is None else (out,)
    refs = ref if isinstance(ref, (tuple, list)) else () if ref is None else (ref,)
    if d.defined is not None:
        outs, refs = (d.defined(args, outs[0]),), (d.defined(args, refs[0]),)
    for got, want in zip(outs, refs):
        if isinstance(got, torch.Tensor):
            torch.testing.assert_close(got, want, **tol)
        else:
            assert got == want
    for member, get in _written(d, args, d.scratch):
        torch.testing.assert_close(get(op_args), get(ref_args), **tol, msg=lambda m, member=member: f"{member}: {m}")
