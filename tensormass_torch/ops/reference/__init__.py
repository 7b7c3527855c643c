"""Pure tensor-op reference of every kernel: the fallback backend and the tests' oracle."""
from . import gather, stress_form, tensor_form  # noqa: F401
