"""Small in-memory scenes for the avatar, training and evaluation tests (imported by them): a
"teacher" avatar with a known colour pattern, rendered in a few poses by the project's own
rasterizer, wrapped in a ``DatasetLike`` (``splits``, ``meta``, ``params``, ``ds[i]``);
`test_scenes.py` checks that the scene is a fair one."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from eva_engine.align.face_mesh import skin_faces
from eva_engine.avatar import Avatar, AvatarConfig, Camera
from eva_engine.body.params import BodyParams
from eva_engine.data import DatasetMeta, Frame
from eva_engine.geometry import project_points, to_camera
from eva_engine.render import look_at


def front_camera(size: int = 64, distance: float = 2.6, focal: float | None = None) -> Camera:
    """Camera on +Z looking at the origin (OpenCV axes: x right, y down)."""
    f = focal if focal is not None else 0.62 * size * distance / 1.8
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    view = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0]))
    view[2, 3] = distance
    return Camera(K, view, size, size)


def teacher_avatar(body, n: int = 2500, seed: int = 0) -> Avatar:
    """An avatar with opaque Gaussians coloured by part and by height stripes."""
    torch.manual_seed(seed)
    cfg = AvatarConfig(sh_degree=0, init_max_gaussians=n, mlp_width=16, pe_frequencies=2)
    avatar = Avatar.create(body, body.shape_defaults, cfg, seed=seed)
    g = avatar.gaussians
    base = torch.tensor([[0.8, 0.3, 0.2], [0.2, 0.7, 0.3], [0.3, 0.4, 0.9]])[g.part_ids]
    stripes = 0.25 * torch.sin(g.means[:, 1:2].detach() * 40.0)
    rgb = (base + stripes).clamp(0.05, 0.95)
    with torch.no_grad():
        g.splats["sh0"][:] = ((rgb - 0.5) / 0.28209479177387814)[:, None]
        g.splats["opacities"][:] = 3.0
        g.splats["scales"][:] += 0.5
    return avatar


def random_params(body, n: int, seed: int, amplitude: float = 0.4) -> BodyParams:
    """``n`` poses: small random rotations of all joints, larger at shoulders and elbows."""
    g = torch.Generator().manual_seed(seed)
    p = body.default_params(n)
    names = body.pose_joint_names
    scale = torch.full((len(names), 1), 0.05)
    for i, name in enumerate(names):
        if any(k in name for k in ("upperarm", "lowerarm", "shoulder")):
            scale[i] = amplitude
    p.joints = torch.randn(n, len(names), 3, generator=g) * scale
    p.root_orient = torch.randn(n, 3, generator=g) * 0.1
    return p


@dataclass
class SceneDataset:
    """A ``DatasetLike`` held in memory: ``frames[i]`` is frame ``i``; its meta names Anny and a
    white background."""

    frames: list[Frame]
    params: BodyParams
    splits: dict[str, list[int]]
    gt_params: BodyParams | None = None
    meta: DatasetMeta = field(init=False)

    def __post_init__(self) -> None:
        h, w = self.frames[0].image.shape[:2]
        self.meta = DatasetMeta(
            source="synthetic",
            fps=1.0,
            image_size=(h, w),
            num_frames=len(self.frames),
            body_model="anny",
            background=(1.0, 1.0, 1.0),
        )

    def __len__(self) -> int:
        return len(self.frames)

    def __getitem__(self, i: int) -> Frame:
        return self.frames[i]


def region_masks(avatar: Avatar, params: BodyParams, camera: Camera) -> dict[str, torch.Tensor]:
    """{hand_left, hand_right, face: [H, W]} where the Gaussians of that part are what is seen
    (rendered with one-hot colours of ``body.sided_part_ids``)."""
    from eva_engine.render import rasterize

    posed = avatar.pose(params)
    sided = avatar.body.sided_part_ids[avatar.gaussians.vertex_ids]
    onehot = torch.nn.functional.one_hot(sided, 4).float()[:, 1:]  # body is black
    out = rasterize(
        posed.means,
        posed.quats,
        posed.scales,
        posed.opacities,
        onehot,
        camera.viewmat,
        camera.K,
        camera.width,
        camera.height,
    )
    names = ("hand_left", "hand_right", "face")
    return {name: (out.image[..., c] > 0.5).float() for c, name in enumerate(names)}


@torch.no_grad()
def teacher_scene(
    body, n_frames: int = 10, size: int = 64, seed: int = 0, amplitude: float = 0.4
) -> tuple[SceneDataset, Avatar]:
    """Render ``n_frames`` poses of the teacher (``random_params``' amplitude); every third frame
    is a novel-pose test frame."""
    teacher = teacher_avatar(body, seed=seed)
    params = random_params(body, n_frames, seed, amplitude)
    cam = front_camera(size)
    bg = torch.ones(3)
    frames = []
    for i in range(n_frames):
        out = teacher(params[i], cam, bg)
        frames.append(
            Frame(
                index=i,
                image=out.image.clamp(0, 1),
                mask=out.alpha[..., 0].clamp(0, 1),
                regions=region_masks(teacher, params[i], cam),
                K=cam.K,
                viewmat=cam.viewmat,
                time=float(i),
            )
        )
    test = list(range(2, n_frames, 3))
    train = [i for i in range(n_frames) if i not in test]
    ds = SceneDataset(frames, params, {"train": train, "test_pose": test, "test_view": []})
    return ds, teacher


def face_camera(body, size: int) -> Camera:
    """A close-up of the rest-pose face from the front."""
    with torch.no_grad():
        kp = body.keypoints(body(body.default_params(1)))[0]
    names = list(body.keypoint_names)
    centre = 0.5 * (kp[names.index("face_left_iris")] + kp[names.index("face_mouth_left")])
    centre = torch.tensor([0.0, float(centre[1]), float(centre[2])])
    f = size * 0.4 / 0.25  # a 25 cm wide view at 40 cm
    K = torch.tensor([[f, 0.0, size / 2], [0.0, f, size / 2], [0.0, 0.0, 1.0]])
    view = look_at((0.0, float(centre[1]), float(centre[2]) + 0.4), tuple(centre.tolist()))
    return Camera(K, view, size, size)


def project_y(body, camera: Camera, name: str) -> float:
    with torch.no_grad():
        kp = body.keypoints(body(body.default_params(1)))[0, [list(body.keypoint_names).index(name)]]
    return float(project_points(to_camera(kp, camera.viewmat), camera.K)[0, 1])


def dark_eyes_avatar(body, footprint: float, expression_frames: bool = False):
    """The teacher on every surface vertex with dark eyeballs and light skin, its footprints
    exp(-``footprint``) times the teacher's."""
    avatar = teacher_avatar(body, n=body.num_vertices)
    avatar.config = dataclasses.replace(avatar.config, expression_frames=expression_frames)
    g = avatar.gaussians
    faces = body.faces.cpu().numpy()
    skin = torch.zeros(body.num_vertices, dtype=torch.bool)
    skin[torch.from_numpy(faces[skin_faces(faces, body.num_vertices)]).flatten()] = True
    eyeball = ~skin[g.vertex_ids] & (g.part_ids == 2)  # the face's other pieces: eyes (and mouth)
    assert int(eyeball.sum()) > 50
    rgb = torch.where(eyeball[:, None], torch.full((1, 3), 0.02), torch.full((1, 3), 0.9))
    with torch.no_grad():
        g.splats["sh0"][:, 0] = (rgb - 0.5) / 0.28209479177387814
        g.splats["scales"][:] -= footprint
    return avatar


def dark_eye_pixels(avatar, body, blink: float, size: int = 160) -> int:
    """Dark pixels in the rows of the eyes of a frontal close-up with both eyes' blink at ``blink``."""
    cam = face_camera(body, size)
    eye_y = project_y(body, cam, "face_left_iris")
    pose = {"expression": {"eyeBlinkLeft": blink, "eyeBlinkRight": blink}}
    img = avatar.render(body.params_from_pose(pose), cam, torch.ones(3))
    band = img[max(int(eye_y) - 12, 0) : int(eye_y) + 12]
    return int((band.mean(-1) < 0.3).sum())
