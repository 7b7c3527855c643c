"""tensormass_torch: Tensor-Mass soft bodies with an implicit solver, as a PyTorch extension.

    import tensormass_torch as tm
    mesh = tm.beam_mesh(8, 2, 2, size=(1.0, 0.25, 0.25))
    model = tm.TensorMass(mesh, tm.Material(young=1e5, poisson=0.3, density=1e3, model="stvk"))
    f = model(mesh.vertices)          # [V, 3] elastic forces
"""
from ._backend import backend_info
from .app.viewer import Viewer, view
from .errors import InvertedElementsError, MaterialError, MeshError, SceneError, SolverError, TensorMassError
from .mesh.beams import beam_mesh, beam_tri_mesh
from .mesh.cutting import Blade
from .mesh.io import load_mesh, save_mesh
from .mesh.meshes import Mesh, TetMesh, TriMesh
from .mesh.surface import tetrahedralize
from .physics.body_contact import Contact
from .physics.contact import Plane
from .physics.materials import MODELS, Material
from .physics.tensor_mass import TensorMass
from .physics.tools import Box, Capsule, MeshTool, Sphere, Tool
from .sim.memory import MemoryEstimate, estimate_memory
from .sim.partitioned import PartitionedSimulator
from .sim.rollout import Rollout, rollout
from .sim.scalpel import Scalpel
from .sim.scene_file import load_scene
from .sim.simulator import Body, InvertedElementsWarning, Simulator
from .solver import solve_static

__version__ = "0.1.0"

__all__ = [
    "backend_info", "Plane", "InvertedElementsError", "MaterialError", "MeshError", "SceneError", "SolverError",
    "TensorMassError",
    "load_mesh", "save_mesh", "MODELS", "Material", "Mesh", "TetMesh", "TriMesh", "beam_mesh", "beam_tri_mesh", "Blade",
    "TensorMass", "Body", "Simulator", "Scalpel", "InvertedElementsWarning", "load_scene", "solve_static",
    "tetrahedralize", "Rollout", "rollout", "Tool", "Sphere", "Capsule", "Box", "MeshTool", "Contact", "Viewer",
    "view", "PartitionedSimulator", "estimate_memory", "MemoryEstimate",
]
