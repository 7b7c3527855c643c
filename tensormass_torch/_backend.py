"""Backend selection: the compiled extension ``tensormass_torch._C`` or the pure-torch reference.

Ops ask :func:`use_extension` for the device of their inputs; when it says no they run the
reference (pure tensor ops), which runs wherever PyTorch runs. The extension is optional:
importing the package never imports it, and a missing or broken build only means the torch
path is used (a broken build — present but failing to import, e.g. "undefined symbol" after
building against another torch — also emits a warning once, since that is never intended).

``TENSORMASS_BACKEND`` (read at every call, so it can be changed at run time):

* ``auto`` (default, also when unset or empty): the extension where it is available, torch
  elsewhere;
* ``torch``: always the pure-torch path; ``_C`` is not even imported;
* ``extension``: the extension is required on CPU and CUDA tensors: ops raise
  :class:`BackendError` instead of falling back.
"""
import importlib
import os
import threading
import warnings

import torch

from .errors import TensorMassError

ENV_VAR = "TENSORMASS_BACKEND"
MODES = ("auto", "torch", "extension")
FORCED_REASON = "forced by %s=torch" % ENV_VAR

__all__ = ["BackendError", "backend_mode", "load_extension", "use_extension", "backend_info",
           "reset_cache"]


class BackendError(TensorMassError, ValueError):
    """``TENSORMASS_BACKEND`` has a bad value, or it requires an extension that is unavailable."""


_lock = threading.Lock()
_loaded = False      # whether the import of _C was attempted
_module = None       # the extension module, or None
_has_cuda = False    # whether _C was built with CUDA
_load_error = ""     # why _C is not available ("" when it is)


def backend_mode():
    """The mode asked for by ``TENSORMASS_BACKEND``: "auto", "torch" or "extension"."""
    raw = os.environ.get(ENV_VAR, "")
    mode = raw.strip().lower() or "auto"
    if mode not in MODES:
        raise BackendError(
            "%s=%r is not valid: use one of %s (unset means auto)"
            % (ENV_VAR, raw, ", ".join(MODES))
        )
    return mode


def _import_extension():
    """Try to import _C once; set the module-level cache."""
    global _loaded, _module, _has_cuda, _load_error
    with _lock:
        if _loaded:
            return
        try:
            _C = importlib.import_module(__package__ + "._C")  # also registers the custom ops
        except ModuleNotFoundError as exc:
            if exc.name == __package__ + "._C":
                _load_error = "extension not built (%s)" % exc
            else:
                _load_error = "extension failed to import: %s: %s" % (type(exc).__name__, exc)
        except Exception as exc:  # ImportError (undefined symbol), OSError, errors of static init
            _load_error = "extension failed to import: %s: %s" % (type(exc).__name__, exc)
        else:
            _module = _C
            has_cuda = getattr(_C, "has_cuda", None)
            try:
                _has_cuda = bool(has_cuda()) if callable(has_cuda) else False
            except Exception:  # a broken has_cuda() must not break the CPU path
                _has_cuda = False
        if _module is None and not _load_error.startswith("extension not built"):
            warnings.warn(
                "tensormass_torch: the compiled extension is present but could not be imported; "
                "using the pure-torch path. Reinstall with 'pip install --no-build-isolation -e .' "
                "against the torch in use. (%s)" % _load_error,
                RuntimeWarning,
                stacklevel=3,
            )
        _loaded = True


def load_extension():
    """The extension module ``tensormass_torch._C``, or None (not built, failed, or forced off).

    The import is attempted once per process (see :func:`reset_cache`); the reason of a failure
    is kept and shown by :func:`backend_info`.
    """
    if backend_mode() == "torch":
        return None
    if not _loaded:
        _import_extension()
    return _module


def reset_cache():
    """Forget the result of the import attempt (for tests). An already imported ``_C`` stays in
    ``sys.modules``, so a second attempt gives the same module."""
    global _loaded, _module, _has_cuda, _load_error
    with _lock:
        _loaded, _module, _has_cuda, _load_error = False, None, False, ""


def _device_type(device):
    if isinstance(device, torch.device):
        return device.type
    if isinstance(device, str):
        return torch.device(device).type
    raise TypeError("expected a torch.device or a device string, got %r" % (device,))


def use_extension(device):
    """Whether ops on tensors of ``device`` should call ``_C`` (else the pure-torch reference).

    True when the extension is loaded, not forced off by ``TENSORMASS_BACKEND=torch``, and built
    for that device type (for CUDA, ``_C.has_cuda()`` is true). Device types the extension never
    handles (meta, mps, ...) always give False. With ``TENSORMASS_BACKEND=extension``, a CPU or
    CUDA device the extension cannot serve raises :class:`BackendError`.
    """
    kind = _device_type(device)
    mode = backend_mode()
    if mode == "torch" or kind not in ("cpu", "cuda"):
        return False
    module = load_extension()
    ok = module is not None and (kind == "cpu" or _has_cuda)
    if not ok and mode == "extension":
        raise BackendError(
            "%s=extension but the extension cannot run on %s tensors: %s"
            % (ENV_VAR, kind, _load_error or "it was built without CUDA")
        )
    return ok


def backend_info():
    """Which backend runs on each device type, and why.

    Returns a dict::

        {"cpu": "extension" | "torch",
         "cuda": "extension" | "torch" | "unavailable",   # unavailable: torch sees no CUDA device
         "reason": str,          # why the extension is (not) used
         "torch": torch.__version__,
         "cuda_device": name of the current CUDA device, or None,
         "forced": bool,         # TENSORMASS_BACKEND is set to torch or extension
         "mode": "auto" | "torch" | "extension"}

    Raises :class:`BackendError` when ``TENSORMASS_BACKEND`` has a bad value.
    """
    mode = backend_mode()
    cuda_available = torch.cuda.is_available()
    cuda_device = torch.cuda.get_device_name(torch.cuda.current_device()) if cuda_available else None
    module = load_extension()
    if mode == "torch":
        cpu, cuda, reason = "torch", "torch", FORCED_REASON
    elif module is None:
        cpu, cuda, reason = "torch", "torch", _load_error
    else:
        cpu = "extension"
        cuda = "extension" if _has_cuda else "torch"
        reason = "extension loaded (%s)" % (
            "built with CUDA" if _has_cuda
            else "built without CUDA: CUDA tensors use the torch path")
    if not cuda_available:
        cuda = "unavailable"
    return {
        "cpu": cpu,
        "cuda": cuda,
        "reason": reason,
        "torch": torch.__version__,
        "cuda_device": cuda_device,
        "forced": mode != "auto",
        "mode": mode,
    }
