"""tensormass_torch: Tensor-Mass soft bodies with an implicit solver, as a PyTorch extension.

    import tensormass_torch as tm
    mesh = tm.beam_mesh(8, 2, 2, size=(1.0, 0.25, 0.25))
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1e3, model="stvk"))
    f = model(mesh.vertices)          # [V, 3] elastic forces
"""
from .errors import MaterialError, MeshError, SceneError, SolverError, TensorMassError

__version__ = "0.1.0"
