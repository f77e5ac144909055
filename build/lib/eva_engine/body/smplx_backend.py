"""SMPL-X for users who bring their own (licensed) model files, through the ``smplx`` package.

The file is the user's ``SMPLX_{GENDER}.npz`` (or ``.pkl``), found at ``model_path`` (a file or
a folder) or, when that is not given, in ``$EVA_SMPLX_DIR``. ``smplx.SMPLX`` loads it (its own
loading code, so any file it accepts works); the forward pass reuses its buffers with the shared
kinematics of :mod:`eva_engine.body.kinematics` so that ``transforms`` come out explicitly.

SMPL-X is already in the world convention (Y up, facing +Z, metres): no conversion. Hands are
full axis-angle (no PCA) with a flat mean, so zero parameters are the rest pose. The jaw and eyes
are joints (``jaw``, ``left_eye_smplhf``, ``right_eye_smplhf``); expression is the file's
expression basis (``expr_0`` ...), shape its betas (``beta_0`` ..., neutral 0).

Pose-corrective blendshapes (``posedirs``) are off by default (``pose_correctives=False``): the
avatar skins Gaussians with ``transforms`` only, and with correctives the mesh would no longer be
``lbs(canonical, weights, transforms)``. Turn them on for mesh-only uses (fitting); ``forward``
then matches ``smplx.SMPLX`` exactly.

Parts from the skinning weights: the part (hand: wrists and finger chains; face: head, jaw, eyes;
body: the rest) with the largest total weight. Keypoints: SMPL-X joints for shoulders, elbows,
hips, knees, ankles and hand joints (thumb1/2/3 -> CMC/MCP/IP, finger1/2/3 -> MCP/PIP/DIP);
smplx's standard vertex ids for nose, ears, heels, big toes and fingertips; the file's 51 face
landmarks (iBUG-68 points 17-67) for eye corners, lids (mean of the two lid points), nose tip,
mouth corners and inner lip centres; its frontal dynamic contour for the chin (iBUG 8); the eye
vertices for irises.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import torch

from eva_engine.body.keypoints import KEYPOINT_NAMES, KeypointRegressor
from eva_engine.body.kinematics import KinematicTree, axis_angle_to_matrix
from eva_engine.body.model import BodyModel, BodyOutput, lbs, part_ids_from_weights
from eva_engine.body.params import BodyParams

SMPLX_DIR_ENV = "EVA_SMPLX_DIR"
NUM_KINEMATIC_JOINTS = 55
SMPLX_REAL_VERTEX_COUNT = 10475


@dataclasses.dataclass(frozen=True)
class SmplxConfig:
    """Options of the SMPL-X backend (``load_body_model("smplx", **fields)``)."""

    model_path: Path | str | None = None
    """``SMPLX_*.npz``/``.pkl`` file or the folder holding it; default ``$EVA_SMPLX_DIR``."""
    gender: str = "neutral"
    num_betas: int = 10
    num_expression_coeffs: int = 10
    pose_correctives: bool = False


def resolve_model_file(config: SmplxConfig) -> Path:
    """The SMPL-X file to load, or a ``FileNotFoundError`` naming the settings to fix."""
    where = config.model_path or os.environ.get(SMPLX_DIR_ENV)
    if not where:
        raise FileNotFoundError(
            "SMPL-X needs the licensed model files, which are not shipped: download them from "
            f"https://smpl-x.is.tue.mpg.de and set the `model_path` option or ${SMPLX_DIR_ENV} "
            "to the folder holding SMPLX_NEUTRAL.npz (or to the file itself)"
        )
    path = Path(where).expanduser()
    if path.is_dir():
        for ext in ("npz", "pkl"):
            candidate = path / f"SMPLX_{config.gender.upper()}.{ext}"
            if candidate.is_file():
                return candidate
        source = "model_path" if config.model_path else f"${SMPLX_DIR_ENV}"
        raise FileNotFoundError(
            f"no SMPLX_{config.gender.upper()}.npz or .pkl in {path} (from {source}); "
            "put the SMPL-X model files there or point the setting at the file"
        )
    if not path.is_file():
        source = "model_path" if config.model_path else f"${SMPLX_DIR_ENV}"
        raise FileNotFoundError(f"SMPL-X model file {path} (from {source}) does not exist")
    return path


class SmplxBody(BodyModel):
    """SMPL-X behind :class:`BodyModel` (see the module docstring)."""

    name = "smplx"

    def __init__(self, config: SmplxConfig | None = None) -> None:
        super().__init__()
        import smplx
        from smplx.joint_names import JOINT_NAMES

        self.config = config or SmplxConfig()
        path = resolve_model_file(self.config)
        self.smplx = smplx.SMPLX(
            str(path),
            ext=path.suffix.lstrip("."),
            gender=self.config.gender,
            num_betas=self.config.num_betas,
            num_expression_coeffs=self.config.num_expression_coeffs,
            use_pca=False,
            flat_hand_mean=True,
            use_face_contour=True,
            dtype=torch.float32,
        )
        self.smplx.requires_grad_(False)
        s = self.smplx
        if s.J_regressor.shape[0] != NUM_KINEMATIC_JOINTS:
            raise ValueError(f"{path} has {s.J_regressor.shape[0]} joints, expected SMPL-X's 55")
        self.joint_names = list(JOINT_NAMES[:NUM_KINEMATIC_JOINTS])
        self.shape_names = [f"beta_{i}" for i in range(s.num_betas)]
        self.expression_names = [f"expr_{i}" for i in range(s.num_expression_coeffs)]
        self.register_buffer("shape_defaults", torch.zeros(s.num_betas), persistent=False)
        self.register_buffer("parents", s.parents.clone(), persistent=False)
        self.register_buffer("faces", s.faces_tensor.clone(), persistent=False)
        weights = s.lbs_weights / s.lbs_weights.sum(dim=1, keepdim=True)
        self.register_buffer("skinning_weights", weights.float(), persistent=False)
        self.tree = KinematicTree(s.parents.tolist())

        j = {n: i for i, n in enumerate(self.joint_names)}
        hand = [
            i
            for n, i in j.items()
            if "wrist" in n or n[:-1].endswith(("index", "middle", "pinky", "ring", "thumb"))
        ]
        face = [j["head"], j["jaw"], j["left_eye_smplhf"], j["right_eye_smplhf"]]
        self.register_buffer("part_ids", part_ids_from_weights(weights, hand, face), persistent=False)
        # SMPL-X has no interior geometry besides the eyeballs, which are visible: keep all.
        self.register_buffer(
            "surface_vertex_mask", torch.ones(weights.shape[0], dtype=torch.bool), persistent=False
        )
        self.keypoint_names = list(KEYPOINT_NAMES)
        # The keypoints use smplx's vertex ids of the real 10,475-vertex topology.
        self.keypoint_regressor = (
            self._build_keypoints() if self.num_vertices == SMPLX_REAL_VERTEX_COUNT else None
        )

    # -- BodyModel ---------------------------------------------------------------------------
    def _shaped(self, params: BodyParams) -> torch.Tensor:
        s = self.smplx
        coeffs = torch.cat([params.shape, params.expression], dim=1).to(self.dtype)
        dirs = torch.cat([s.shapedirs, s.expr_dirs], dim=-1)  # [V, 3, S + E]
        return s.v_template[None] + torch.einsum("bl,vdl->bvd", coeffs, dirs)

    def canonical(self, params: BodyParams) -> torch.Tensor:
        return self._shaped(params)

    def forward(self, params: BodyParams) -> BodyOutput:
        shaped, rotations, transforms, joints = self._skeleton(params)
        rest = shaped
        if self.config.pose_correctives:
            eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
            feature = (rotations[:, 1:] - eye).flatten(1)  # [B, (J - 1) * 9]
            rest = rest + (feature @ self.smplx.posedirs).view_as(rest)
        vertices = lbs(rest, self.skinning_weights, transforms)
        return BodyOutput(vertices=vertices, joints=joints, transforms=transforms, rest=shaped)

    def rest_and_transforms(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        shaped, _, transforms, _ = self._skeleton(params)
        return shaped, transforms

    def _skeleton(self, params: BodyParams) -> tuple[torch.Tensor, ...]:
        """Shaped rest vertices [B, V, 3], joint rotations [B, J, 3, 3], LBS transforms
        [B, J, 4, 4] and posed joints [B, J, 3] (no mesh posed)."""
        shaped = self._shaped(params)  # [B, V, 3]
        heads = torch.einsum("jv,bvd->bjd", self.smplx.J_regressor, shaped)
        rotvecs = torch.cat([params.root_orient[:, None], params.joints], dim=1).to(self.dtype)
        rotations = axis_angle_to_matrix(rotvecs)  # [B, J, 3, 3]
        transforms, joints = self.tree.forward_kinematics(rotations, heads, params.transl.to(self.dtype))
        return shaped, rotations, transforms, joints

    def keypoints(self, output: BodyOutput) -> torch.Tensor:
        if self.keypoint_regressor is None:
            raise ValueError(
                f"this SMPL-X file has {self.num_vertices} vertices, not {SMPLX_REAL_VERTEX_COUNT}: "
                "the keypoint layout's vertex ids do not apply to it"
            )
        return self.keypoint_regressor(output.vertices, output.joints)

    def smplx_inputs(self, params: BodyParams) -> dict[str, torch.Tensor]:
        """Keyword arguments for ``self.smplx(...)`` (smplx's own forward) equivalent to
        ``params`` (used to check this backend against the package)."""
        p = params.joints.to(self.dtype)
        j = {n: i for i, n in enumerate(self.pose_joint_names)}

        def take(names: list[str]) -> torch.Tensor:
            return p[:, [j[n] for n in names]].flatten(1)

        body = self.joint_names[1:22]
        return dict(
            betas=params.shape.to(self.dtype),
            expression=params.expression.to(self.dtype),
            global_orient=params.root_orient.to(self.dtype),
            transl=params.transl.to(self.dtype),
            body_pose=take(body),
            jaw_pose=take(["jaw"]),
            leye_pose=take(["left_eye_smplhf"]),
            reye_pose=take(["right_eye_smplhf"]),
            left_hand_pose=take(self.joint_names[25:40]),
            right_hand_pose=take(self.joint_names[40:55]),
        )

    # -- construction helpers ------------------------------------------------------------------
    def _build_keypoints(self) -> KeypointRegressor:
        from smplx.vertex_ids import vertex_ids

        s = self.smplx
        ids = vertex_ids["smplx"]
        j = {n: i for i, n in enumerate(self.joint_names)}
        faces = s.faces_tensor

        def surface_point(face: int, bary: torch.Tensor) -> dict[int, float]:
            out: dict[int, float] = {}
            for v, w in zip(faces[face].tolist(), bary.tolist(), strict=True):
                out[v] = out.get(v, 0.0) + float(w)
            return out

        def landmark(ibug: int) -> dict[int, float]:
            k = ibug - 17
            return surface_point(int(s.lmk_faces_idx[k]), s.lmk_bary_coords[k])

        def mean(*terms: dict[int, float]) -> dict[int, float]:
            out: dict[int, float] = {}
            for t in terms:
                for v, w in t.items():
                    out[v] = out.get(v, 0.0) + w / len(terms)
            return out

        vt: dict[str, dict[int, float]] = {
            "face_right_eye_outer": landmark(36),
            "face_right_eye_inner": landmark(39),
            "face_left_eye_inner": landmark(42),
            "face_left_eye_outer": landmark(45),
            "face_right_eye_upper_lid": mean(landmark(37), landmark(38)),
            "face_right_eye_lower_lid": mean(landmark(40), landmark(41)),
            "face_left_eye_upper_lid": mean(landmark(43), landmark(44)),
            "face_left_eye_lower_lid": mean(landmark(46), landmark(47)),
            "face_right_iris": {ids["reye"]: 1.0},
            "face_left_iris": {ids["leye"]: 1.0},
            "face_nose_tip": landmark(30),
            "face_mouth_right": landmark(48),
            "face_mouth_left": landmark(54),
            "face_upper_lip_inner": landmark(62),
            "face_lower_lip_inner": landmark(66),
            # Frontal (zero head yaw) entry of the dynamic contour; contour point 8 is the chin.
            "face_chin": surface_point(int(s.dynamic_lmk_faces_idx[0, 8]), s.dynamic_lmk_bary_coords[0, 8]),
            "nose": {ids["nose"]: 1.0},
            "left_ear": {ids["lear"]: 1.0},
            "right_ear": {ids["rear"]: 1.0},
            "left_heel": {ids["LHeel"]: 1.0},
            "right_heel": {ids["RHeel"]: 1.0},
            "left_foot_index": {ids["LBigToe"]: 1.0},
            "right_foot_index": {ids["RBigToe"]: 1.0},
        }
        jt: dict[str, dict[int, float]] = {}
        for side, c in (("left", "l"), ("right", "r")):
            vt[f"{side}_eye_inner"] = vt[f"face_{side}_eye_inner"]
            vt[f"{side}_eye"] = vt[f"face_{side}_iris"]
            vt[f"{side}_eye_outer"] = vt[f"face_{side}_eye_outer"]
            vt[f"mouth_{side}"] = vt[f"face_mouth_{side}"]
            for name in ("shoulder", "elbow", "hip", "knee", "ankle", "wrist"):
                jt[f"{side}_{name}"] = {j[f"{side}_{name}"]: 1.0}
            h = f"{side}_hand_"
            jt[h + "wrist"] = {j[f"{side}_wrist"]: 1.0}
            for ours, theirs in (
                ("thumb", "thumb"),
                ("index_finger", "index"),
                ("middle_finger", "middle"),
                ("ring_finger", "ring"),
                ("pinky", "pinky"),
            ):
                names = ("cmc", "mcp", "ip") if ours == "thumb" else ("mcp", "pip", "dip")
                for k, n in enumerate(names, start=1):
                    jt[h + f"{ours}_{n}"] = {j[f"{side}_{theirs}{k}"]: 1.0}
                vt[h + f"{ours}_tip"] = {ids[f"{c}{theirs}"]: 1.0}
            jt[f"{side}_pinky"] = jt[h + "pinky_mcp"]
            jt[f"{side}_index"] = jt[h + "index_finger_mcp"]
            jt[f"{side}_thumb"] = jt[h + "thumb_mcp"]
        return KeypointRegressor(KEYPOINT_NAMES, vt, jt, num_joints=len(self.joint_names))
