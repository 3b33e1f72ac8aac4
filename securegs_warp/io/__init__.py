"""Files: Scaffold-GS model folders (point_cloud.ply + MLPs), standard 3DGS PLY export, atomic writes,
and reading TorchScript archives' tensors without executing them."""

from .atomic import atomic_open, atomic_write
from .gs_ply import GS_PLY_PROPERTIES, SH_C0, PlyFormatError, export_3dgs_ply, read_3dgs_ply
from .scaffold import (
    MLP_FILES,
    POINT_CLOUD_FILE,
    UNITE_FILE,
    MlpFileError,
    anchor_ply_properties,
    load_scaffold,
    load_weights,
    save_scaffold,
)
from .torchscript import TorchScriptError, read_torchscript_state_dict

__all__ = [
    "GS_PLY_PROPERTIES",
    "MLP_FILES",
    "POINT_CLOUD_FILE",
    "SH_C0",
    "UNITE_FILE",
    "MlpFileError",
    "PlyFormatError",
    "TorchScriptError",
    "anchor_ply_properties",
    "atomic_open",
    "atomic_write",
    "export_3dgs_ply",
    "load_scaffold",
    "load_weights",
    "read_3dgs_ply",
    "read_torchscript_state_dict",
    "save_scaffold",
]
