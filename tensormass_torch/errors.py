"""Exceptions raised by tensormass_torch.

Every bad input raises one of these with a message that names the problem; nothing is
modified when they are raised.
"""


class TensorMassError(Exception):
    """Base class of every error this package raises on purpose."""


class MeshError(TensorMassError, ValueError):
    """A mesh is malformed: wrong shapes or dtypes, bad indices, degenerate or inverted elements."""


class InvertedElementsError(MeshError):
    """A mesh has inverted elements (negative measure).

    Attributes:
        ids: the inverted elements' ids, as the message lists them (a short text).
    """

    def __init__(self, message, ids: str = ""):
        super().__init__(message)
        self.ids = ids


class MaterialError(TensorMassError, ValueError):
    """A material parameter is out of range or a model name is unknown."""


class CapacityError(TensorMassError, RuntimeError):
    """A topology change in place does not fit the room reserved for it (spare node rows, a
    node's slots in a gather plan): nothing was changed. A ``Simulator`` answers by building
    itself again with more room."""


class SceneError(TensorMassError, ValueError):
    """A scene (bodies, constraints, options) is inconsistent: mixed devices, every node fixed, ..."""


class SolverError(TensorMassError, RuntimeError):
    """A solve failed (no convergence, breakdown, NaN/inf). The state was left as it was.

    Attributes:
        status: per-object status strings, e.g. ``["converged", "not converged", ...]``.
        report: the solver's report object (iterations, residuals) when one exists.
    """

    def __init__(self, message, status=None, report=None):
        super().__init__(message)
        self.status = status
        self.report = report
