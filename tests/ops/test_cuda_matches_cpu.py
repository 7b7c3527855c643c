"""The CUDA ops: CUDA = CPU extension = pure torch, determinism, autograd, opcheck, streams, graphs.

Skipped unless torch sees a CUDA device and the extension was built with CUDA
(``scripts/gpu_check.sh`` runs them on the GPU machine). ``TENSORMASS_GPU_TEST_DEVICE=cpu`` runs
them with "cpu" in place of "cuda" (a dry run of the tests' own logic on a machine without a
GPU; the stream and graph tests are then skipped).

    1. every op on CUDA = the pure-torch reference (float64 on the CPU) = the CPU extension, for
       every model, element kind (tet, tri 2-D, tri 3-D membrane), form, dtype, index dtype
    2. bitwise identical from run to run (and on another stream), on a beam of ~10k tetrahedra
    3. the model (ops.dispatch) on CUDA = TENSORMASS_BACKEND=torch on CUDA
    4. gradcheck (float64) and opcheck on CUDA
    5. launches go to the current stream: a CUDA graph of dforce replays to the eager result
"""
from __future__ import annotations

import importlib
import os

import numpy as np
import pytest
import torch
from conftest import CASES, DTYPES, MODELS, reference

DEVICE = os.environ.get("TENSORMASS_GPU_TEST_DEVICE", "cuda")


def _cuda_extension():
    if DEVICE == "cuda" and not torch.cuda.is_available():
        return None
    try:
        C = importlib.import_module("tensormass_torch._C")
    except ImportError:
        return None
    if DEVICE == "cuda" and not C.has_cuda():
        return None
    from tensormass_torch.ops import library, native

    return native if library.available() else None


native = _cuda_extension()
pytestmark = pytest.mark.skipif(native is None, reason="needs a CUDA device and the extension built with CUDA")
needs_cuda = pytest.mark.skipif(DEVICE != "cuda", reason="dry run on the CPU: no streams or graphs")

if native is not None:  # the helpers of the CPU tests
    from test_element_ops import displacements, make_group, op_calls, plan_indices, rel, tol, used_slots

T = torch.ops.tensormass


def to(args, device=None, dtype=None):
    out = []
    for a in args:
        if isinstance(a, torch.Tensor):
            a = a.to(device=device) if device is not None else a
            if dtype is not None and a.is_floating_point():
                a = a.to(dtype)
            a = a.contiguous()
        out.append(a)
    return out


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_cuda_ops_match_cpu_and_reference(kind, model, form, dtype, rng):
    _, group, scene = make_group(rng, kind, model, form, torch.float64)
    u, du = displacements(rng, scene, torch.float64)
    n = group.elements.shape[0]
    lam = torch.tensor(rng.uniform(0.5, 2.0, n))
    mu = torch.tensor(rng.uniform(0.5, 2.0, n))
    for index_dtype in (torch.int64, torch.int32):
        for name, args in op_calls(group, u, du, index_dtype, lam, mu):
            ref_args = [a.long() if isinstance(a, torch.Tensor) and not a.is_floating_point() else a for a in args]
            ref = reference(name)(*ref_args)  # float64, CPU: the oracle
            cpu_args = to(args, dtype=dtype)
            gpu_args = to(cpu_args, device=DEVICE)
            cpu = used_slots(name, cpu_args, getattr(T, name)(*cpu_args))
            gpu = used_slots(name, gpu_args, getattr(T, name)(*gpu_args))
            assert gpu.device.type == DEVICE and gpu.dtype == dtype and gpu.shape == ref.shape, name
            assert rel(gpu.cpu(), ref) < tol(dtype, group), (name, index_dtype, rel(gpu.cpu(), ref))
            assert rel(gpu.cpu(), cpu) < tol(dtype, group), (name, index_dtype, rel(gpu.cpu(), cpu))


@pytest.mark.parametrize("form", ("stress", "tensor"))
@pytest.mark.parametrize("model", MODELS)
def test_cuda_bitwise_deterministic(model, form, rng):
    _, group, scene = make_group(rng, "tet", model, form, torch.float32, cells=(20, 10, 8))  # 9,600 tets
    u, du = displacements(rng, scene, torch.float32)
    calls = [(name, to(args, device=DEVICE)) for name, args in op_calls(group, u, du, torch.int32)
             if "_partial_" not in name]
    first = [getattr(T, name)(*args) for name, args in calls]
    for _ in range(3):
        again = [getattr(T, name)(*args) for name, args in calls]
        for name_args, a, b in zip(calls, first, again):
            assert torch.equal(a, b), name_args[0]
    if DEVICE != "cuda":
        return
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        other = [getattr(T, name)(*args) for name, args in calls]
    torch.cuda.current_stream().wait_stream(side)
    for a, b in zip(first, other):
        assert torch.equal(a, b)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,model,form", CASES)
def test_cuda_model_matches_torch_backend(kind, model, form, dtype, rng, monkeypatch):
    tm, group, scene = make_group(rng, kind, model, form, dtype)
    tm = tm.to(DEVICE)
    u, du = displacements(rng, scene, dtype)
    x = (scene.rest.to(dtype) + u).to(DEVICE)
    dx = du.to(DEVICE)

    def run():
        return tm(x), tm.dforce(x, dx)

    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext = run()
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    ref = run()
    for a, b in zip(ext, ref):
        assert a.device.type == DEVICE and rel(a, b) < tol(dtype, group)


@pytest.mark.parametrize("kind,model,form", CASES)
def test_cuda_gradcheck(kind, model, form, rng):
    cells = (1, 1, 1) if kind == "tet" else (1, 2)
    _, group, scene = make_group(rng, kind, model, form, cells=cells)
    u, du = displacements(rng, scene, torch.float64)
    for name, args in op_calls(group, 0.3 * u, 0.3 * du):
        if "_partial_" in name or "_element_" in name:
            continue  # their backward is the reference's (tested on the CPU)
        args = to(args, device=DEVICE)
        diff = [i for i, a in enumerate(args) if isinstance(a, torch.Tensor) and a.is_floating_point()
                and (a.shape == args[0].shape or a.dim() == 1)]  # u, du, lam, mu, node terms
        inputs = [args[i].detach().clone().requires_grad_(True) for i in diff]

        def fn(*xs, name=name, args=args, diff=diff):
            full = list(args)
            for i, x in zip(diff, xs):
                full[i] = x
            return getattr(T, name)(*full)

        assert torch.autograd.gradcheck(fn, inputs, eps=1e-6, atol=1e-7, rtol=1e-5), name


def test_cuda_opcheck():
    rng = np.random.default_rng(3)
    for kind, model, form in (("tet", "stvk", "stress"), ("tri3d", "hooke", "stress"), ("tet", "hooke", "tensor"),
                              ("tri2d", "stvk", "tensor")):
        _, group, scene = make_group(rng, kind, model, form, cells=(1, 1, 1) if kind == "tet" else (1, 2))
        u, du = displacements(rng, scene, torch.float64)
        for name, args in op_calls(group, 0.3 * u, du):
            args = [a.detach().clone().requires_grad_(True) if isinstance(a, torch.Tensor) and a.is_floating_point()
                    else a for a in to(args, device=DEVICE)]
            utils = ("test_schema", "test_autograd_registration", "test_faketensor", "test_aot_dispatch_dynamic")
            if "_partial_" in name:
                utils = utils[:3]  # unused slots are uninitialised
            torch.library.opcheck(getattr(T, name).default, tuple(args), test_utils=utils)


@needs_cuda
@pytest.mark.parametrize("model", MODELS)
def test_cuda_graph_capture_of_dforce(model, rng):
    """The ops launch on the current stream and never synchronise: a CUDA graph of model.dforce
    (the product inside CG) replays to the eager result, bitwise."""
    tm, _, scene = make_group(rng, "tet", model, "stress", torch.float32, cells=(6, 4, 4))
    tm = tm.to("cuda")
    u, du = displacements(rng, scene, torch.float32)
    x = (scene.rest.float() + u).cuda()
    dx = du.cuda()
    eager = tm.dforce(x, dx)
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(2):  # warm-up (caches of the dispatch layer) on the capture stream
            tm.dforce(x, dx)
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = tm.dforce(x, dx)
    graph.replay()
    torch.cuda.synchronize()
    assert torch.equal(out, eager)
    dx.mul_(2.0)
    graph.replay()
    torch.cuda.synchronize()
    assert torch.allclose(out, 2.0 * eager, rtol=1e-5, atol=1e-6 * float(eager.abs().max()))


# ------------------------------------------------------------------ corotational (issue 4)
#
# The rotations op (qr, polar) and the stress ops reading the rotations of the linearisation, on
# the device = the float64 reference on the CPU = the CPU extension; bitwise reproducible; opcheck.

COROT_CASES = [("tet", "qr"), ("tri3d", "qr"), ("tet", "polar"), ("tri3d", "polar"), ("tri2d", "polar")]
COROT_IDS = [f"{k}-{r}" for k, r in COROT_CASES]


def corotational_calls(group, u, du, rotations, index_dtype):
    """[(op name, args)]: the rotations op and the six stress ops with the rotations given."""
    from test_corotational_ops import METHOD

    idx, fi, inc = plan_indices(group, index_dtype)
    ns = group.plan.num_slots
    lam, mu = group.lame()
    s = (group.shape_vectors, group.measure, lam.contiguous(), mu.contiguous(), group.projector, 2, None, rotations)
    rest = getattr(group, "rest_elements", None)
    return [
        ("corotational_rotations", (u, idx, group.shape_vectors, group.projector, rest, METHOD[group.rotation])),
        ("stress_element_forces", (u, idx) + s),
        ("stress_element_dforces", (u, du, idx) + s),
        ("stress_partial_forces", (u, idx, fi, ns) + s),
        ("stress_partial_dforces", (u, du, idx, fi, ns) + s),
        ("stress_forces", (u, idx, fi, ns, inc) + s),
        ("stress_dforces", (u, du, idx, fi, ns, inc) + s),
    ]


@pytest.mark.parametrize("dtype", DTYPES, ids=["f64", "f32"])
@pytest.mark.parametrize("kind,rot", COROT_CASES, ids=COROT_IDS)
def test_cuda_corotational_matches_cpu_and_reference(kind, rot, dtype, rng):
    from test_corotational_ops import deformations, reference_rotations
    from test_corotational_ops import make_group as make_corotational

    _, group, scene = make_corotational(rng, kind, torch.float64, rot)
    u = (deformations(rng, scene)[1] - scene.rest).contiguous()
    du = torch.tensor(rng.standard_normal(u.shape))
    rotations = reference_rotations(group, u)
    for index_dtype in (torch.int64, torch.int32):
        for name, args in corotational_calls(group, u, du, rotations, index_dtype):
            ref_args = [a.long() if isinstance(a, torch.Tensor) and not a.is_floating_point() else a for a in args]
            ref = reference(name)(*ref_args)
            cpu_args = to(args, dtype=dtype)
            gpu_args = to(cpu_args, device=DEVICE)
            cpu = used_slots(name, cpu_args, getattr(T, name)(*cpu_args))
            gpu = used_slots(name, gpu_args, getattr(T, name)(*gpu_args))
            assert gpu.device.type == DEVICE and gpu.dtype == dtype and gpu.shape == ref.shape, name
            assert rel(gpu.cpu(), ref) < tol(dtype), (name, index_dtype, rel(gpu.cpu(), ref))
            assert rel(gpu.cpu(), cpu) < tol(dtype), (name, index_dtype, rel(gpu.cpu(), cpu))


@pytest.mark.parametrize("rot", ["qr", "polar"])
def test_cuda_corotational_bitwise_deterministic_and_model_matches_torch(rot, rng, monkeypatch):
    from test_corotational_ops import make_group as make_corotational

    tm, group, scene = make_corotational(rng, "tet", torch.float32, rot, cells=(20, 10, 8))  # 9,600 tets
    u, du = displacements(rng, scene, torch.float32)
    r = T.corotational_rotations(*to(corotational_calls(group, u, du, None, torch.int32)[0][1], device=DEVICE))
    calls = [(name, to(args, device=DEVICE)) for name, args in corotational_calls(group, u, du, r, torch.int32)
             if "_partial_" not in name]
    first = [getattr(T, name)(*args) for name, args in calls]
    for _ in range(2):
        for (name, args), a in zip(calls, first):
            assert torch.equal(getattr(T, name)(*args), a), name
    tm = tm.to(DEVICE)
    x = (scene.rest.float() + u).to(DEVICE)
    dx = du.to(DEVICE)
    monkeypatch.setenv("TENSORMASS_BACKEND", "extension")
    ext = (tm(x), tm.dforce(x, dx))
    monkeypatch.setenv("TENSORMASS_BACKEND", "torch")
    ref = (tm(x), tm.dforce(x, dx))
    for a, b in zip(ext, ref):
        assert a.device.type == DEVICE and rel(a, b) < tol(torch.float32)


def test_cuda_corotational_opcheck():
    from test_corotational_ops import deformations
    from test_corotational_ops import make_group as make_corotational

    rng = np.random.default_rng(4)
    for kind, rot in (("tet", "polar"), ("tri3d", "qr")):
        _, group, scene = make_corotational(rng, kind, rot=rot, cells=(1, 1, 1) if kind == "tet" else (1, 2))
        u = (0.5 * (deformations(rng, scene)[0] - scene.rest)).contiguous()
        r = T.corotational_rotations(*corotational_calls(group, u, u, None, torch.int64)[0][1])
        for name, args in corotational_calls(group, u, u.clone(), r, torch.int64):
            if "_partial_" in name or name == "stress_forces":
                continue
            args = [a.detach().clone().requires_grad_(True) if isinstance(a, torch.Tensor) and a.is_floating_point()
                    else a for a in to(args, device=DEVICE)]
            torch.library.opcheck(getattr(T, name).default, tuple(args),
                                  test_utils=("test_schema", "test_autograd_registration", "test_faketensor"))
