"""rtfem: real-time simulation of dynamically deformable finite-element models (shells and solids)."""

from .mesh import meshes
from .errors import DeviceError, MeshError, ModelError, RtfemError, RtfemWarning, SolverError
from .fe.material import Damping, Material
from .fe.hyperelastic import MooneyRivlin, NeoHookean, Ogden
from .fe.viscoelastic import Prony
from .fe.fitting import fit_material
from .mesh.repair import MeshReport
from .mesh.surface import TriMesh
from .mesh.tetmesh import TetMesh
from .mesh.files import load_mesh, save_mesh
from .fe import linalg
from .fe.linalg import available_backends
from .reduction.modal import ModalBasis, modal_analysis
from .interaction import devices
from .interaction.devices import CallbackDevice, ScriptedDevice, SharedDevice
from .interaction.haptics import Grasp, Probe
from .interaction.loop import HapticLoop
from .interaction.contact import Tool, ToolContact
from .interaction.scene import Scene
from .interaction.scene_tools import Keyframes
from .interaction import contact
from .drivers.impedance import ImpedanceMap, Load
from .drivers.impedance_driver import ImpedanceDriver
from .fe.protocol import Model
from .fe.shellmodel import ShellModel
from .fe.build import make_model
from .fe.solidmodel import SolidModel
from .mesh.meshing import tetrahedralize
from .mesh.selection import select_nodes
from .drivers.fullorder import CentralDifferenceSimulator, DirectSimulator, NewmarkSimulator
from .drivers.nonlinear_newmark import NonlinearNewmarkSimulator
from .drivers.base import Driver
from .drivers.modal import ModalSimulator
from .drivers.static import StaticDriver
from .reduction.sldm import SLDM
from .fe import nonlinear
from .reduction.reduced import ReducedNonlinearModel
from .drivers.reduced_nonlinear import ReducedNonlinearSimulator

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
    "Scene",
    "Keyframes",
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
    "DeviceError",
    "MeshReport",
    "Material",
    "NeoHookean",
    "Prony",
    "MooneyRivlin",
    "Ogden",
    "fit_material",
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
    "linalg",
    "contact",
    "devices",
    "nonlinear",
    "save_mesh",
]
