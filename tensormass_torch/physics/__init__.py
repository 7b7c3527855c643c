"""The physics layer: materials, element groups and the Tensor-Mass force field.

    materials       Material, the constitutive models, Lame constants
    groups          ElementGroup: the precomputed data of one kind, model and form of elements
    tensor_mass     TensorMass: forces, energy and force differentials of a mesh or a batch
    contact         penalty planes
    constraints     fixed and prescribed node masks
    analytic        beam theory (the accuracy study's references)

It calls the ops and mesh layers.
"""
from .contact import Plane
from .materials import MODELS, Material
from .tensor_mass import TensorMass

__all__ = ["MODELS", "Material", "Plane", "TensorMass"]
