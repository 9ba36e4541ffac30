"""Rigged, animated export: the :class:`Rig` contract, run-directory files, USD (UsdSkel) and glTF."""

from s3o_warp.export.gltf import export_gltf
from s3o_warp.export.rig import Rig, load_rig, save_rig, top_k_error, top_k_weights
from s3o_warp.export.usd import ExportReport, camera_apertures, export_usd

__all__ = [
    "ExportReport",
    "Rig",
    "camera_apertures",
    "export_gltf",
    "export_usd",
    "load_rig",
    "save_rig",
    "top_k_error",
    "top_k_weights",
]
