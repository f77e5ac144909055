"""The Gaussian avatar (EVA §3.1): canonical 3D Gaussians on a body model, skinned by LBS with
learned weight offsets and a pose-refinement MLP, rendered by ``eva_engine.render.rasterize``.

    from eva_engine.avatar import Camera, load_avatar
    avatar = load_avatar("data/avatars/alice")
    image = avatar.render(avatar.body.params_from_pose({...}), Camera(K, viewmat, 512, 512))
    still = render_spec(avatar, RenderSpec(pose={...}, camera="left"))   # the API's render JSON
    saved = load_saved_avatar("data/avatars/alice")   # .avatar, .meta (avatar.json), .frames
"""

from eva_engine.avatar.config import AvatarConfig
from eva_engine.avatar.frames import AvatarFrames
from eva_engine.avatar.gaussians import PER_GAUSSIAN_BUFFERS, SPLAT_NAMES, CanonicalGaussians
from eva_engine.avatar.io import (
    FRAMES_NAME,
    AvatarFileError,
    AvatarMeta,
    FramesInfo,
    SavedAvatar,
    TrainingRecord,
    load_avatar,
    load_avatar_frames,
    load_saved_avatar,
    read_avatar_meta,
    read_ply,
    save_avatar,
    write_ply,
)
from eva_engine.avatar.model import Avatar, PosedGaussians, template_vertices
from eva_engine.avatar.networks import (
    LBSWeightOffsets,
    PoseRefiner,
    blend_skinning_weights,
    positional_encoding,
)
from eva_engine.avatar.render_spec import RenderInputError, RenderPose, RenderSpec, render_spec
from eva_engine.avatar.skinning import orthonormalize, quat_multiply, skin_gaussians
from eva_engine.render.camera import Camera

__all__ = [
    "FRAMES_NAME",
    "PER_GAUSSIAN_BUFFERS",
    "SPLAT_NAMES",
    "Avatar",
    "AvatarConfig",
    "AvatarFileError",
    "AvatarFrames",
    "AvatarMeta",
    "Camera",
    "CanonicalGaussians",
    "FramesInfo",
    "LBSWeightOffsets",
    "PoseRefiner",
    "PosedGaussians",
    "RenderInputError",
    "RenderPose",
    "RenderSpec",
    "SavedAvatar",
    "TrainingRecord",
    "blend_skinning_weights",
    "load_avatar",
    "load_avatar_frames",
    "load_saved_avatar",
    "orthonormalize",
    "positional_encoding",
    "quat_multiply",
    "read_avatar_meta",
    "read_ply",
    "render_spec",
    "save_avatar",
    "skin_gaussians",
    "template_vertices",
    "write_ply",
]
