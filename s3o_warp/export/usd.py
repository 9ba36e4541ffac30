"""Rigged, animated USD export (UsdSkel) of a :class:`~s3o_warp.export.rig.Rig`.

Stage layout (Y up, ``metersPerUnit`` a setting, one time code per video frame, frame k at time
code k, ``timeCodesPerSecond`` = the video's fps)::

    /World                      Xform (default prim, kind component)
    /World/Character            SkelRoot (extent: posed vertices, per frame)
    /World/Character/Skel       Skeleton: joints "root", "root/bone_00", "root/bone_00/bone_03", ...
    /World/Character/Skel/Anim  SkelAnimation: local translations, rotations, scales per frame
    /World/Character/Mesh       Mesh bound with UsdSkel.BindingAPI (K influences per vertex),
                                displayColor, normals, extent
    /World/Camera               Camera reproducing each input frame (intrinsics and pose)

Everything is authored in the WORLD frame (``rig.world_from_object`` applied) with identity
transforms on the prims above the camera, so UsdSkel's skinned points are world points.
The ``baked`` variant writes ``/World/Mesh`` with time-sampled points (the exact full-weight posed
vertices) and no UsdSkel schema, for tools without UsdSkel.
"""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt
from tqdm import tqdm

from s3o_warp.data.io import atomic_path
from s3o_warp.errors import InputError
from s3o_warp.export.rig import (
    Rig,
    decompose_rigid,
    dense_weights,
    max_distance,
    top_k_weights,
    vertex_normals,
)

logger = logging.getLogger(__name__)

USD_EXTENSIONS = (".usd", ".usda", ".usdc")
#: Horizontal aperture of the exported camera (USD aperture units, i.e. mm: a 36 mm film back).
HORIZONTAL_APERTURE = 36.0


@dataclass
class ExportReport:
    """What an export wrote and how closely the file reproduces the fit.

    Attributes:
        path: the file written.
        influences: joints per vertex stored in the file (after clipping to the bone count).
        topk_error: largest vertex distance (scene units) over all frames between the full-weight
            posed vertices and the ones skinned with the stored top-K renormalised weights.
        topk_error_rel: ``topk_error`` divided by the canonical bounding-box diagonal.
        camera_px_error: largest reprojection error (pixels) that the file's camera model itself
            causes (0 for USD; for glTF, what folding each frame's principal point offset and focal
            into the camera's pose leaves).
    """

    path: Path
    influences: int
    topk_error: float
    topk_error_rel: float
    camera_px_error: float = 0.0


def _m4(m: np.ndarray):
    return Gf.Matrix4d(*np.asarray(m, dtype=np.float64).T.flatten().tolist())


def _m4_array(ms: np.ndarray):
    return Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(np.swapaxes(ms, -1, -2), dtype=np.float64))


def camera_apertures(K: np.ndarray, image_size: tuple[int, int], horizontal_aperture: float = HORIZONTAL_APERTURE) -> dict:
    """USD camera attributes that reproduce OpenCV intrinsics on the full frame.

    Args:
        K: (3, 3) OpenCV intrinsics (fx, fy, cx, cy in pixels; pixel (c, r) centred at (c, r)).
        image_size: (H, W) in pixels.
        horizontal_aperture: film-back width (USD aperture units) to use.

    Returns:
        dict with focalLength, horizontalAperture, verticalAperture, horizontalApertureOffset,
        verticalApertureOffset (all in the same units: f = hAp fx / W, vAp = H f / fy,
        hOff = (W/2 - 0.5 - cx) hAp / W, vOff = (cy + 0.5 - H/2) vAp / H).
    """
    h, w = image_size
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    hap = float(horizontal_aperture)
    f = hap * fx / w
    vap = h * f / fy
    return {
        "focalLength": float(f),
        "horizontalAperture": hap,
        "verticalAperture": float(vap),
        "horizontalApertureOffset": float((w / 2 - 0.5 - cx) * hap / w),
        "verticalApertureOffset": float((cy + 0.5 - h / 2) * vap / h),
    }


def _extent(points: np.ndarray):
    return Vt.Vec3fArray.FromNumpy(np.stack([points.min(0), points.max(0)]).astype(np.float32))


def _define_mesh(stage, path: str, rig: Rig, points: np.ndarray):
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(rig.faces), 3, dtype=np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(rig.faces.reshape(-1).astype(np.int32)))
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points.astype(np.float32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(vertex_normals(points, rig.faces)))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateExtentAttr(_extent(points))
    mesh.CreateDisplayColorPrimvar(UsdGeom.Tokens.vertex).Set(Vt.Vec3fArray.FromNumpy(rig.colors.astype(np.float32)))
    return mesh


def _define_camera(stage, path: str, rig: Rig, depth_range: tuple[float, float]):
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateProjectionAttr(UsdGeom.Tokens.perspective)
    near, far = depth_range
    cam.CreateClippingRangeAttr(Gf.Vec2f(float(max(near * 0.1, 1e-4)), float(far * 10.0)))
    attrs = {
        "focalLength": cam.CreateFocalLengthAttr(),
        "horizontalAperture": cam.CreateHorizontalApertureAttr(),
        "verticalAperture": cam.CreateVerticalApertureAttr(),
        "horizontalApertureOffset": cam.CreateHorizontalApertureOffsetAttr(),
        "verticalApertureOffset": cam.CreateVerticalApertureOffsetAttr(),
    }
    xf = cam.AddTransformOp()
    c2w = rig.camera_to_world()
    for t in range(rig.num_frames):
        for key, value in camera_apertures(rig.K[t], rig.image_size).items():
            attrs[key].Set(value, t)
        xf.Set(_m4(c2w[t]), t)
    return cam


def _write_layer(layer, tmp: Path) -> None:
    """Write a root layer to ``tmp`` (the format follows the extension)."""
    if not layer.Export(str(tmp)):
        raise OSError(f"USD could not write the temporary file {tmp}")


def export_usd(
    rig: Rig,
    path: str | os.PathLike,
    influences: int = 4,
    baked: bool = False,
    meters_per_unit: float = 1.0,
) -> ExportReport:
    """Write ``rig`` as a rigged, animated USD stage (``.usda`` text, ``.usdc``/``.usd`` binary).

    The file is written atomically (:mod:`s3o_warp.data.io`), so an existing good file is never replaced by a
    half-written one.

    Args:
        rig: the reconstruction to export.
        path: output file; the extension picks the format.
        influences: joints per vertex (``primvars:skel:jointIndices`` elementSize); the top
            ``influences`` weights of each vertex are kept and renormalised. Clipped to B.
        baked: write the skinning baked into time-sampled points instead of UsdSkel.
        meters_per_unit: the stage's ``metersPerUnit`` (the fit's scale is only known up to a
            factor; 1 means one scene unit is one metre).

    Returns:
        An :class:`ExportReport` (top-K approximation error of the stored weights).

    Raises:
        InputError: bad extension, influences < 1, or a missing output folder.
    """
    path = Path(path)
    if path.suffix.lower() not in USD_EXTENSIONS:
        raise InputError(f"{path}: a USD export needs the extension .usda, .usdc or .usd")
    if int(influences) < 1:
        raise InputError(f"influences: must be at least 1 (joints per vertex), got {influences}")
    k = min(int(influences), rig.num_bones)
    t_count = rig.num_frames

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
    stage.SetTimeCodesPerSecond(rig.fps)
    stage.SetFramesPerSecond(rig.fps)
    stage.SetStartTimeCode(0)
    stage.SetEndTimeCode(t_count - 1)
    layer = stage.GetRootLayer()
    layer.customLayerData = {"s3o:frameNames": Vt.StringArray(rig.frame_names), "s3o:imageSize": Vt.IntArray(list(rig.image_size))}
    world = UsdGeom.Xform.Define(stage, "/World")
    stage.SetDefaultPrim(world.GetPrim())
    Usd.ModelAPI(world.GetPrim()).SetKind("component")

    posed = rig.posed_world_frames()
    cam_from_world = rig.root @ np.linalg.inv(rig.world_from_object)
    z = np.einsum("tnj,tj->tn", posed, cam_from_world[:, 2, :3]) + cam_from_world[:, 2, 3:]
    depth = (float(z.min()), float(z.max()))
    rest = rig.verts.astype(np.float64) @ rig.world_from_object[:3, :3].T + rig.world_from_object[:3, 3]

    if baked:
        mesh = _define_mesh(stage, "/World/Mesh", rig, rest)
        pts_attr, nrm_attr, ext_attr = mesh.GetPointsAttr(), mesh.GetNormalsAttr(), mesh.GetExtentAttr()
        for t in tqdm(range(t_count), desc="USD baked frames", leave=False, disable=None):
            p = posed[t].astype(np.float32)
            pts_attr.Set(Vt.Vec3fArray.FromNumpy(p), t)
            nrm_attr.Set(Vt.Vec3fArray.FromNumpy(vertex_normals(posed[t], rig.faces)), t)
            ext_attr.Set(_extent(p), t)
        err = (0.0, 0.0)
        k = rig.num_bones
    else:
        skel_root = UsdSkel.Root.Define(stage, "/World/Character")
        skel = UsdSkel.Skeleton.Define(stage, "/World/Character/Skel")
        order = rig.topological_order()  # joint j (after "root") is bone order[j]
        paths = rig.joint_paths()
        joints = ["root"] + [paths[b] for b in order]
        joint_of_bone = np.empty(rig.num_bones, dtype=np.int64)
        joint_of_bone[order] = np.arange(1, rig.num_bones + 1)
        skel.CreateJointsAttr(Vt.TokenArray(joints))
        skel.CreateJointNamesAttr(Vt.TokenArray([j.rsplit("/", 1)[-1] for j in joints]))
        bind_world = rig.bind_world()
        skel.CreateBindTransformsAttr(_m4_array(np.concatenate([np.eye(4)[None], bind_world[order]])))
        rest_local = rig.local_transforms(bind_world)
        skel.CreateRestTransformsAttr(_m4_array(np.concatenate([np.eye(4)[None], rest_local[order]])))

        anim = UsdSkel.Animation.Define(stage, "/World/Character/Skel/Anim")
        anim.CreateJointsAttr(Vt.TokenArray(joints))
        local = np.stack([rig.local_transforms(rig.bone_world(t))[order] for t in range(t_count)])
        local = np.concatenate([np.broadcast_to(np.eye(4), (t_count, 1, 4, 4)), local], 1)
        trans, quat = decompose_rigid(local)
        tr_attr, rot_attr, sc_attr = anim.CreateTranslationsAttr(), anim.CreateRotationsAttr(), anim.CreateScalesAttr()
        ones = Vt.Vec3hArray.FromNumpy(np.ones((len(joints), 3), dtype=np.float16))
        for t in tqdm(range(t_count), desc="USD frames", leave=False, disable=None):
            tr_attr.Set(Vt.Vec3fArray.FromNumpy(trans[t].astype(np.float32)), t)
            rot_attr.Set(Vt.QuatfArray.FromNumpy(quat[t].astype(np.float32)), t)
            sc_attr.Set(ones, t)
        UsdSkel.BindingAPI.Apply(skel.GetPrim()).CreateAnimationSourceRel().SetTargets([anim.GetPath()])

        mesh = _define_mesh(stage, "/World/Character/Mesh", rig, rest)
        binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
        binding.CreateSkeletonRel().SetTargets([skel.GetPath()])
        idx, val = top_k_weights(rig.weights, k)
        binding.CreateJointIndicesPrimvar(False, k).Set(Vt.IntArray.FromNumpy(joint_of_bone[idx].reshape(-1).astype(np.int32)))
        binding.CreateJointWeightsPrimvar(False, k).Set(Vt.FloatArray.FromNumpy(val.reshape(-1).astype(np.float32)))
        binding.CreateGeomBindTransformAttr(_m4(np.eye(4)))
        ext = skel_root.CreateExtentAttr()
        posed_k = rig.posed_world_frames(dense_weights(idx, val, rig.num_bones))
        for t in range(t_count):
            ext.Set(_extent(posed_k[t]), t)
        err = max_distance(rig, posed, posed_k)

    _define_camera(stage, "/World/Camera", rig, depth)
    with atomic_path(path) as tmp:
        _write_layer(layer, tmp)
    logger.info(
        "wrote %s (%s, %d frames, %d bones, %d influences, top-K error %.3g = %.2g of the bbox diagonal)",
        path, "baked points" if baked else "UsdSkel", t_count, rig.num_bones, k, err[0], err[1],
    )
    return ExportReport(path=path, influences=k, topk_error=err[0], topk_error_rel=err[1])
