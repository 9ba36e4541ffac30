"""The S3O parametric model (paper 3.1, 3.3): canonical mesh, Gaussian bones, per-frame motion, camera.

Notation (paper Table 4): ``M_c`` canonical mesh (verts X^0, faces, colours); bones B (centre C_b,
orientation V_b, log-scales of the precision Lambda_b, length); per frame t the root transform T_0^t
(object -> camera) and bone transforms T_b^t, each bone rotating about its own centre; intrinsics with
one focal length shared over the video (full-frame pixels) and a principal point per frame in the crop (LASR's),
or one principal point for the whole video in full-frame pixels (``principal_point="shared"``, a real camera's).
Several videos of one object share the mesh, bones and skinning; each frame has its own root and camera, each video
its own focal length (``video_of``), and synchronized videos share the bone motion frame by frame (``motion_of``).

Posed vertices (eq. 3): ``X^t = T_0^t (sum_b W[n,b] T_b^t) X^0`` through the Warp skinning ops.
Rotations are axis-angle vectors (never Euler angles); the root rotation is a learnable axis-angle
delta on top of a fixed per-frame base rotation, so camera hypotheses can be swapped in cleanly.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from s3o_warp.geometry import axis_angle_to_matrix, matrix_to_quat, quat_to_matrix
from s3o_warp.ops import blend_skinning, skinning_weights


@dataclass
class ModelInit:
    """Everything needed to build a model (numpy or torch, float32)."""

    verts: torch.Tensor  # (N, 3) canonical vertices, object frame
    faces: torch.Tensor  # (F, 3) int64
    colors: torch.Tensor  # (N, 3) in [0, 1]
    centers: torch.Tensor  # (B, 3) Gaussian centres C_b
    rotations: torch.Tensor  # (B, 3, 3) orientation V_b (rows = ellipsoid axes)
    log_scales: torch.Tensor  # (B, 3) log of the precision's diagonal Lambda_b
    root_R: torch.Tensor  # (T, 3, 3) initial object -> camera rotation per frame
    root_t: torch.Tensor  # (T, 3) initial object -> camera translation per frame
    focal: float  # focal length in full-frame pixels (shared)
    crop_scale: torch.Tensor  # (T,) crop pixels per full-frame pixel
    crop_size: int  # S, the crop's side in pixels
    crop_to_frame: torch.Tensor  # (T, 3, 3) crop pixel -> full-frame pixel
    principal_point: str = "frame"  # frame: one per frame in the crop (LASR); shared: one in full-frame pixels
    frame_size: tuple | None = None  # (H, W) full frame; principal_point="shared" starts at its centre
    video_of: torch.Tensor | None = None  # (T,) int64 video of each frame (several videos: ``focal`` one per video)
    motion_of: torch.Tensor | None = None  # (T,) int64 row of the bone motion each frame takes (synchronized videos
    # share rows; default: one row per frame)


def root_for_shared_principal_point(root_R: torch.Tensor, root_t: torch.Tensor, crop_to_frame: torch.Tensor,
                                    crop_size: int, focal: float, pp: tuple[float, float]
                                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """Root rotations ``(T, 3, 3)`` and translations ``(T, 3)`` that show the object as a principal point at each
    crop's centre shows it, with one principal point ``pp`` (full-frame pixels) instead.

    A crop with its principal point at its centre is the camera turned to look along the ray through that centre,
    ``d_t = ((c_t - pp) / f, 1)``; the object turned with it, ``R_d R`` and ``R_d t`` (``R_d`` the smallest rotation
    taking the optical axis onto ``d_t``), is seen from the same side, its point on the crop's axis lands on the
    crop's centre, and the rest moves by the rotation's perspective term (about f a u^2 for a ray angle a and an
    object u radians wide). Moving it sideways alone would land as near but turn the side it shows to the camera
    by the ray's angle.
    """
    T = root_t.shape[0]
    c = torch.full((T, 3), (crop_size - 1) / 2, dtype=torch.float64)
    c[:, 2] = 1
    pp_t = (crop_to_frame.double() @ c[..., None])[:, :2, 0]  # each crop's centre, full-frame pixels
    off = (pp_t - torch.tensor(pp, dtype=torch.float64)) / float(focal)
    d = torch.cat([off, torch.ones(T, 1, dtype=torch.float64)], 1)  # the ray through each crop's centre
    d = d / d.norm(dim=1, keepdim=True)
    axis = torch.stack([-d[:, 1], d[:, 0], torch.zeros_like(d[:, 0])], 1)  # z x d
    s = axis.norm(dim=1, keepdim=True)
    aa = axis / s.clamp_min(1e-12) * torch.atan2(s, d[:, 2:3])
    Rd = axis_angle_to_matrix(aa)
    R = Rd @ root_R.double().expand(T, 3, 3)
    t = (Rd @ root_t.double().expand(T, 3)[..., None])[..., 0]
    return R.to(root_R.dtype), t.to(root_t.dtype)


class S3OModel(nn.Module):
    """Learnable canonical shape, skeleton Gaussians, per-frame root/bone motion and intrinsics."""

    def __init__(self, init: ModelInit):
        super().__init__()
        f32 = dict(dtype=torch.float32)
        T = init.root_R.shape[0]
        B = init.centers.shape[0]
        vo = torch.zeros(T, dtype=torch.int64) if init.video_of is None else torch.as_tensor(init.video_of).long()
        mo = torch.arange(T) if init.motion_of is None else torch.as_tensor(init.motion_of).long()
        self.register_buffer("video_of", vo.clone())
        self.register_buffer("motion_of", mo.clone())
        Tm = int(mo.max()) + 1
        self.verts = nn.Parameter(torch.as_tensor(init.verts, **f32).clone())
        c = torch.as_tensor(init.colors, **f32).clamp(1e-3, 1 - 1e-3)
        self.color_logits = nn.Parameter(torch.log(c / (1 - c)))
        self.register_buffer("faces", torch.as_tensor(init.faces, dtype=torch.int64).clone())
        self.bone_centers = nn.Parameter(torch.as_tensor(init.centers, **f32).clone())
        self.bone_quat = nn.Parameter(matrix_to_quat(torch.as_tensor(init.rotations, **f32)).clone())
        self.bone_log_scales = nn.Parameter(torch.as_tensor(init.log_scales, **f32).clone())
        self.register_buffer("root_R0", torch.as_tensor(init.root_R, **f32).clone())
        self.root_aa = nn.Parameter(torch.zeros(T, 3, **f32))
        self.root_t = nn.Parameter(torch.as_tensor(init.root_t, **f32).clone())
        self.bone_aa = nn.Parameter(torch.zeros(Tm, B, 3, **f32))
        self.bone_t = nn.Parameter(torch.zeros(Tm, B, 3, **f32))
        focal = torch.log(torch.as_tensor(init.focal, dtype=torch.float64))  # () one video, (V,) several
        self.log_focal = nn.Parameter(focal.to(torch.float32).clone())
        S = float(init.crop_size)
        if init.principal_point not in ("frame", "shared"):
            raise ValueError(f"principal_point must be 'frame' or 'shared', got {init.principal_point!r}")
        self.pp_shared = init.principal_point == "shared"
        if self.pp_shared:  # (2,) full-frame pixels, from the frame's centre
            H, W = init.frame_size
            self.pp = nn.Parameter(torch.tensor([(W - 1) / 2, (H - 1) / 2], **f32))
        else:  # (T, 2) crop pixels, from each crop's centre
            self.pp = nn.Parameter(torch.full((T, 2), (S - 1) / 2, **f32))
        self.register_buffer("visited", torch.zeros(T, dtype=torch.bool))  # warm-up sweep bookkeeping
        self.register_buffer("crop_scale", torch.as_tensor(init.crop_scale, **f32).clone())
        self.register_buffer("crop_to_frame", torch.as_tensor(init.crop_to_frame, **f32).clone())
        self.crop_size = int(init.crop_size)

    # -- sizes -------------------------------------------------------------------------------------
    @property
    def num_frames(self) -> int:
        return self.root_t.shape[0]

    @property
    def num_bones(self) -> int:
        return self.bone_centers.shape[0]

    @property
    def num_motion_rows(self) -> int:
        """Rows of the bone motion: the frames, or one video's frames when synchronized videos share them."""
        return self.bone_aa.shape[0]

    # -- skeleton ----------------------------------------------------------------------------------
    def precisions(self) -> torch.Tensor:
        """Q_b = V_b^T diag(exp s_b) V_b, ``(B, 3, 3)``."""
        V = quat_to_matrix(self.bone_quat)
        return V.transpose(-1, -2) @ torch.diag_embed(torch.exp(self.bone_log_scales)) @ V

    def skinning(self, detach_verts: bool = True) -> torch.Tensor:
        """Skinning weights W ``(N, B)`` of the canonical vertices (vertices detached, as in LASR)."""
        v = self.verts.detach() if detach_verts else self.verts
        return skinning_weights(v, self.bone_centers, self.precisions())

    def colors(self) -> torch.Tensor:
        return torch.sigmoid(self.color_logits)

    # -- motion ------------------------------------------------------------------------------------
    def root_rt(self, frames: torch.Tensor) -> torch.Tensor:
        """T_0^t as ``(t, 3, 4)`` object -> camera."""
        R = axis_angle_to_matrix(self.root_aa[frames]) @ self.root_R0[frames]
        return torch.cat([R, self.root_t[frames, :, None]], -1)

    def bone_rt(self, frames: torch.Tensor) -> torch.Tensor:
        """T_b^t as ``(t, B, 3, 4)``: rotation about the bone's own centre plus a translation."""
        rows = self.motion_of[frames]
        R = axis_angle_to_matrix(self.bone_aa[rows])
        c = self.bone_centers[None, :, :, None]
        t = c[..., 0] + self.bone_t[rows] - (R @ c)[..., 0]
        return torch.cat([R, t[..., None]], -1)

    def intrinsics_crop(self, frames: torch.Tensor) -> torch.Tensor:
        """K in crop pixels ``(t, 3, 3)``: focal = shared full-frame focal x the frame's crop scale."""
        lf = self.log_focal if self.log_focal.dim() == 0 else self.log_focal[self.video_of[frames]]
        f = torch.exp(lf) * self.crop_scale[frames]
        K = torch.zeros(len(frames), 3, 3, dtype=f.dtype, device=f.device)
        K[:, 0, 0] = f
        K[:, 1, 1] = f
        pp = self.principal_point_crop(frames)
        K[:, 0, 2] = pp[:, 0]
        K[:, 1, 2] = pp[:, 1]
        K[:, 2, 2] = 1
        return K

    def principal_point_crop(self, frames: torch.Tensor) -> torch.Tensor:
        """The principal point in each frame's crop pixels ``(t, 2)`` (a shared one mapped through the crop)."""
        if not self.pp_shared:
            return self.pp[frames]
        # crop_to_frame is a scale 1 / crop_scale and an offset: crop pixel = (frame pixel - offset) x crop_scale
        return (self.pp - self.crop_to_frame[frames, :2, 2]) * self.crop_scale[frames, None]

    def intrinsics_frame(self, frames: torch.Tensor) -> torch.Tensor:
        """K in full-frame pixels ``(t, 3, 3)`` = crop_to_frame @ K_crop."""
        return self.crop_to_frame[frames] @ self.intrinsics_crop(frames)

    def forward(self, frames: torch.Tensor, weights: torch.Tensor | None = None, verts: torch.Tensor | None = None):
        """Posed camera-space vertices ``(t, N, 3)`` of the given frame indices (eq. 3)."""
        W = self.skinning() if weights is None else weights
        v = self.verts if verts is None else verts
        return blend_skinning(v, W, self.bone_rt(frames), self.root_rt(frames))

    def posed_object(self, frames: torch.Tensor, weights: torch.Tensor | None = None) -> torch.Tensor:
        """Articulated vertices in the object frame (before the root), ``(t, N, 3)``."""
        W = self.skinning() if weights is None else weights
        eye = torch.zeros(len(frames), 3, 4, dtype=self.verts.dtype, device=self.verts.device)
        eye[:, :, :3] = torch.eye(3, device=self.verts.device)
        return blend_skinning(self.verts, W, self.bone_rt(frames), eye)
