"""rtfem: real-time simulation of dynamically deformable finite-element models (shells and solids)."""

from . import meshes
from .errors import MeshError, ModelError, RtfemError, RtfemWarning, SolverError
from .material import Damping, Material
from .mesh import MeshReport, TriMesh
from .tetmesh import TetMesh
from .meshfile import load_mesh, save_mesh
from . import linalg
from .linalg import available_backends
from .modal import ModalBasis, modal_analysis
from .haptics import CallbackDevice, Grasp, HapticLoop, Probe, ScriptedDevice, SharedDevice
from .contact import Tool, ToolContact
from . import contact
from .impedance import ImpedanceDriver, ImpedanceMap, Load
from .model import Model, ShellModel, make_model
from .solidmodel import SolidModel
from .meshing import tetrahedralize
from .selection import select_nodes
from .fullorder import CentralDifferenceSimulator, DirectSimulator, NewmarkSimulator, NonlinearNewmarkSimulator
from .simulate import Driver, ModalSimulator
from .staticdriver import StaticDriver
from .sldm import SLDM
from . import nonlinear
from .reduced import ReducedNonlinearModel, ReducedNonlinearSimulator

__version__ = "0.1.0"

__all__ = [
    "Damping",
    "CallbackDevice",
    "SharedDevice",
    "CentralDifferenceSimulator",
    "DirectSimulator",
    "Driver",
    "ImpedanceDriver",
    "Model",
    "NewmarkSimulator",
    "NonlinearNewmarkSimulator",
    "available_backends",
    "make_model",
    "select_nodes",
    "Grasp",
    "Tool",
    "ToolContact",
    "HapticLoop",
    "Probe",
    "ScriptedDevice",
    "ImpedanceMap",
    "Load",
    "ModalBasis",
    "ModalSimulator",
    "ReducedNonlinearModel",
    "ReducedNonlinearSimulator",
    "modal_analysis",
    "MeshError",
    "MeshReport",
    "Material",
    "ModelError",
    "RtfemError",
    "RtfemWarning",
    "ShellModel",
    "SolidModel",
    "StaticDriver",
    "TetMesh",
    "tetrahedralize",
    "SLDM",
    "SolverError",
    "TriMesh",
    "load_mesh",
    "meshes",
    "save_mesh",
]
