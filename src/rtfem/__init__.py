"""rtfem: real-time simulation of dynamically deformable finite-element models (shells and solids).

The public names (``rt.X``) are imported when first used (PEP 562): ``import rtfem`` itself loads
the error classes only, so a script, the command line and a worker start without the viewer, the
contact solver, the devices or numba's kernels until they are asked for (issue 54: 0.72 s before).
"""

from importlib import import_module

from .errors import DeviceError, MeshError, ModelError, RtfemError, RtfemWarning, SolverError
from .lazy import submodules

_submodule = submodules(__name__)

__version__ = "0.1.0"

# name -> (module, attribute in it; None: the module itself)
_LAZY = {
    "meshes": (".mesh.meshes", None),
    "Damping": (".fe.material", 'Damping'),
    "Material": (".fe.material", 'Material'),
    "MooneyRivlin": (".fe.hyperelastic", 'MooneyRivlin'),
    "NeoHookean": (".fe.hyperelastic", 'NeoHookean'),
    "Ogden": (".fe.hyperelastic", 'Ogden'),
    "Prony": (".fe.viscoelastic", 'Prony'),
    "fit_material": (".fe.fitting", 'fit_material'),
    "tissue": (".fe.tissues", 'tissue'),
    "materials": (".fe.materials", None),
    "TissueSet": (".fe.tissues", 'TissueSet'),
    "MeshReport": (".mesh.repair", 'MeshReport'),
    "TriMesh": (".mesh.surface", 'TriMesh'),
    "TetMesh": (".mesh.tetmesh", 'TetMesh'),
    "load_mesh": (".mesh.files", 'load_mesh'),
    "save_mesh": (".mesh.files", 'save_mesh'),
    "linalg": (".fe.linalg", None),
    "available_backends": (".fe.linalg", 'available_backends'),
    "ModalBasis": (".reduction.modal", 'ModalBasis'),
    "modal_analysis": (".reduction.modal", 'modal_analysis'),
    "devices": (".interaction.devices", None),
    "CallbackDevice": (".interaction.devices", 'CallbackDevice'),
    "ScriptedDevice": (".interaction.devices", 'ScriptedDevice'),
    "SharedDevice": (".interaction.devices", 'SharedDevice'),
    "Grasp": (".interaction.haptics", 'Grasp'),
    "Probe": (".interaction.haptics", 'Probe'),
    "MultiRateProbe": (".interaction.multirate", 'MultiRateProbe'),
    "error_estimate": (".reduction.indicator", 'error_estimate'),
    "MultiRateGrasp": (".interaction.multirate", 'MultiRateGrasp'),
    "Scalpel": (".interaction.scalpel", 'Scalpel'),
    "HapticLoop": (".interaction.loop", 'HapticLoop'),
    "Tool": (".interaction.contact", 'Tool'),
    "ToolContact": (".interaction.contact", 'ToolContact'),
    "Scene": (".interaction.scene", 'Scene'),
    "Keyframes": (".interaction.scene_tools", 'Keyframes'),
    "contact": (".interaction.contact", None),
    "ImpedanceMap": (".drivers.impedance", 'ImpedanceMap'),
    "Load": (".drivers.impedance", 'Load'),
    "ImpedanceDriver": (".drivers.impedance_driver", 'ImpedanceDriver'),
    "Model": (".fe.protocol", 'Model'),
    "ShellModel": (".fe.shellmodel", 'ShellModel'),
    "make_model": (".fe.build", 'make_model'),
    "SolidModel": (".fe.solidmodel", 'SolidModel'),
    "tetrahedralize": (".mesh.meshing", 'tetrahedralize'),
    "cut": (".fe.cut", 'cut'),
    "select_nodes": (".mesh.selection", 'select_nodes'),
    "CentralDifferenceSimulator": (".drivers.fullorder", 'CentralDifferenceSimulator'),
    "DirectSimulator": (".drivers.fullorder", 'DirectSimulator'),
    "NewmarkSimulator": (".drivers.fullorder", 'NewmarkSimulator'),
    "NonlinearNewmarkSimulator": (".drivers.nonlinear_newmark", 'NonlinearNewmarkSimulator'),
    "Driver": (".drivers.base", 'Driver'),
    "ModalSimulator": (".drivers.modal", 'ModalSimulator'),
    "StaticDriver": (".drivers.static", 'StaticDriver'),
    "SLDM": (".reduction.sldm", 'SLDM'),
    "nonlinear": (".fe.nonlinear", None),
    "ReducedNonlinearModel": (".reduction.reduced", 'ReducedNonlinearModel'),
    "ReducedNonlinearSimulator": (".drivers.reduced_nonlinear", 'ReducedNonlinearSimulator'),
    "precompute": (".reduction.precompute", 'precompute'),
    "cache": (".cache", None),
}


def __getattr__(name: str):
    if name not in _LAZY:
        return _submodule(name)  # rt.mesh, rt.io, ...: the subpackages on first use
    module, attr = _LAZY[name]
    value = import_module(module, __name__)
    if attr is not None:
        value = getattr(value, attr)
    globals()[name] = value  # once: later lookups are plain attribute reads
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))

__all__ = [
    "Damping",
    "CallbackDevice",
    "SharedDevice",
    "CentralDifferenceSimulator",
    "cut",
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
    "MultiRateProbe",
    "error_estimate",
    "MultiRateGrasp",
    "Scalpel",
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
    "tissue",
    "TissueSet",
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
    "precompute",
    "cache",
]
