"""The body-model interface every backend implements, and the skinning functions around it.

World convention (the whole project): Y up, the subject faces +Z, metres, right-handed, so the
subject's left is +X (like SMPL-X). Backends convert at their boundary.

LBS contract: for ``out = model.forward(params)`` and ``rest = model.canonical(params)``,
``out.vertices == lbs(rest, model.skinning_weights, out.transforms)``; any canonical point (a
Gaussian centre) is posed the same way with weights borrowed from the mesh
(:func:`nearest_vertex_weights`).
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Sequence

import torch

from eva_engine.body.params import BodyParams, BodyPose, params_from_poses, pose_from_params

PART_NAMES = ("body", "hand", "face")
"""Names of the values of ``BodyModel.part_ids``."""
SIDED_PART_NAMES = ("body", "hand_left", "hand_right", "face")
"""Names of the values of ``BodyModel.sided_part_ids``: the parts with the two hands apart."""


@dataclasses.dataclass
class BodyOutput:
    """A posed body in world coordinates.

    vertices: [B, V, 3]; joints: [B, J, 3] (posed joint positions, ``model.joint_names`` order);
    transforms: [B, J, 4, 4] rest-pose (canonical) -> posed rigid transforms for LBS; rest:
    [B, V, 3] ``model.canonical(params)``, computed on the way (a caller that needs both poses
    once).
    """

    vertices: torch.Tensor
    joints: torch.Tensor
    transforms: torch.Tensor
    rest: torch.Tensor


class BodyModel(torch.nn.Module, abc.ABC):
    """A parametric body model behind one interface (see the module docstring for conventions).

    Attributes every backend sets (tensors are buffers, so ``.to(device)`` moves them):
        faces: [F, 3] int64 triangles.
        parents: [J] int64, parent joint index, -1 for the root (index 0).
        skinning_weights: [V, J] float, rows sum to 1.
        part_ids: [V] int64 indices into :data:`PART_NAMES`.
        surface_vertex_mask: [V] bool, vertices of the visible surface (no interior geometry).
        shape_defaults: [S] float, neutral shape values.
        joint_names, expression_names, shape_names, keypoint_names: lists of str.
    """

    name: str
    expression_bounds: tuple[float, float] | None = None
    """Valid range of every expression coefficient (None: unbounded, as SMPL-X's PCA space)."""
    shape_bounds: tuple[float, float] | None = None
    """Valid range of every shape coefficient (None: unbounded)."""
    faces: torch.Tensor
    parents: torch.Tensor
    skinning_weights: torch.Tensor
    part_ids: torch.Tensor
    surface_vertex_mask: torch.Tensor
    shape_defaults: torch.Tensor
    joint_names: list[str]
    expression_names: list[str]
    shape_names: list[str]
    keypoint_names: list[str]

    # -- the model -------------------------------------------------------------------------
    @abc.abstractmethod
    def forward(self, params: BodyParams) -> BodyOutput:
        """Pose the body: ``params`` with batch B -> :class:`BodyOutput` with batch B."""

    def rest_and_transforms(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        """``forward``'s ``rest`` [B, V, 3] and ``transforms`` [B, J, 4, 4] for a caller that
        skins its own points (an avatar's Gaussians). Backends may override it with a path that
        skips posing the mesh."""
        out = self.forward(params)
        return out.rest, out.transforms

    @abc.abstractmethod
    def canonical(self, params: BodyParams) -> torch.Tensor:
        """Rest-pose vertices [B, V, 3] for ``params.shape`` and ``params.expression`` (pose,
        root and translation are ignored): the points ``forward``'s transforms apply to."""

    @abc.abstractmethod
    def keypoints(self, output: BodyOutput) -> torch.Tensor:
        """Keypoints [B, K, 3] in the layout of ``keypoint_names`` (see ``body.keypoints``)."""

    def posed_points(self, params: BodyParams, regressor) -> torch.Tensor:
        """Points [B, N, 3] of a fixed linear map of the posed mesh (``regressor``: a
        ``body.keypoints.KeypointRegressor``, e.g. face-mesh landmarks as barycentric vertex
        combinations) for ``params``. Backends may override it with a path that skips posing the
        full mesh."""
        out = self.forward(params)
        return regressor(out.vertices, out.joints)

    def posed_keypoints(self, params: BodyParams) -> tuple[torch.Tensor, torch.Tensor]:
        """Keypoints [B, K, 3] and posed joints [B, J, 3] for ``params``, the same values as
        ``keypoints(forward(params))``. Fitting calls this hundreds of times on whole clips;
        backends override it with a path that skips posing the full mesh."""
        out = self.forward(params)
        return self.keypoints(out), out.joints

    # -- derived facts ---------------------------------------------------------------------
    @property
    def num_vertices(self) -> int:
        return int(self.skinning_weights.shape[0])

    @property
    def num_joints(self) -> int:
        return len(self.joint_names)

    @property
    def pose_joint_names(self) -> list[str]:
        """Joints with an entry in ``BodyParams.joints``: all but the root (``root_orient``)."""
        return self.joint_names[1:]

    @property
    def dtype(self) -> torch.dtype:
        return self.skinning_weights.dtype

    @property
    def device(self) -> torch.device:
        return self.skinning_weights.device

    @property
    def joint_part_ids(self) -> torch.Tensor:
        """[J] int64 part of each joint (into :data:`PART_NAMES`): the part of the vertices it
        moves most (skinning-weight mass); joints that move no vertex count as body."""
        mass = torch.zeros(self.num_joints, len(PART_NAMES), dtype=self.skinning_weights.dtype)
        mass.index_add_(1, self.part_ids.cpu(), self.skinning_weights.detach().cpu().T)
        ids = mass.argmax(dim=1)
        ids[mass.sum(dim=1) == 0] = PART_NAMES.index("body")
        return ids.to(self.device)

    @property
    def sided_part_ids(self) -> torch.Tensor:
        """[V] int64 indices into :data:`SIDED_PART_NAMES`: ``part_ids`` with each hand vertex
        given its side, the subject's left (+X in the rest pose) or right."""
        with torch.no_grad():
            x = self.canonical(self.default_params(1))[0, :, 0]
        hand = self.part_ids == PART_NAMES.index("hand")
        out = torch.where(self.part_ids == PART_NAMES.index("face"), 3, 0)
        out = torch.where(hand & (x > 0), 1, out)
        return torch.where(hand & (x <= 0), 2, out).to(torch.int64)

    def part_vertex_ids(self, part: str) -> torch.Tensor:
        """Indices [N] of the vertices of one part of :data:`PART_NAMES`."""
        return torch.nonzero(self.part_ids == PART_NAMES.index(part)).squeeze(1)

    # -- parameters ------------------------------------------------------------------------
    def default_params(self, batch_size: int = 1, requires_grad: bool = False) -> BodyParams:
        """Rest pose, zero expression, neutral shape, on the model's device and dtype."""

        def z(*shape):
            return torch.zeros(*shape, dtype=self.dtype, device=self.device)

        params = BodyParams(
            root_orient=z(batch_size, 3),
            transl=z(batch_size, 3),
            joints=z(batch_size, len(self.pose_joint_names), 3),
            expression=z(batch_size, len(self.expression_names)),
            shape=self.shape_defaults.to(self.dtype).expand(batch_size, -1).clone(),
        )
        if requires_grad:
            params = params.map(lambda t: t.requires_grad_(True))
        return params

    def params_from_pose(self, pose: BodyPose | dict | Sequence[BodyPose | dict]) -> BodyParams:
        """One JSON pose (batch 1) or a list of them (batch N) -> :class:`BodyParams`.

        Raises ``pydantic.ValidationError`` for malformed input and ``InvalidPoseError`` (a
        ``ValueError``) listing the valid names when a name is unknown to this model.
        """
        poses = [pose] if isinstance(pose, BodyPose | dict) else list(pose)
        return params_from_poses(
            poses,
            pose_joint_names=self.pose_joint_names,
            expression_names=self.expression_names,
            shape_names=self.shape_names,
            shape_defaults=self.shape_defaults,
            dtype=self.dtype,
            device=self.device,
        )

    def pose_from_params(self, params: BodyParams, index: int = 0, sparse: bool = True) -> BodyPose:
        """Frame ``index`` of ``params`` as JSON (:class:`BodyPose`)."""
        return pose_from_params(
            params,
            index,
            pose_joint_names=self.pose_joint_names,
            expression_names=self.expression_names,
            shape_names=self.shape_names,
            shape_defaults=self.shape_defaults,
            sparse=sparse,
        )

    def extra_repr(self) -> str:
        return (
            f"name={self.name!r}, vertices={self.num_vertices}, joints={self.num_joints}, "
            f"expressions={len(self.expression_names)}, shape={self.shape_names}"
        )


# -- skinning ----------------------------------------------------------------------------------
def lbs(points: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning: posed = sum_j w_j T_j rest.

    points: [B, N, 3] or [N, 3] canonical points; weights: [N, J] or [B, N, J];
    transforms: [B, J, 4, 4]. Returns [B, N, 3].
    """
    b, j = transforms.shape[:2]
    n = points.shape[-2]
    top = transforms[:, :, :3, :]  # [B, J, 3, 4]
    ones = points.new_ones(points.shape[:-1] + (1,))
    homogeneous = torch.cat([points, ones], dim=-1)  # [(B,) N, 4]
    if weights.ndim == 2:
        # One [N, J] @ [J, B*12] product, then a 3x4 @ 4 per point: far cheaper than
        # materialising per-point 4x4 blends with broadcasting.
        blend = (weights @ top.permute(1, 0, 2, 3).reshape(j, b * 12)).view(n, b, 3, 4)
        x = homogeneous.transpose(0, 1) if homogeneous.ndim == 3 else homogeneous[:, None].expand(n, b, 4)
        return (blend @ x.unsqueeze(-1)).squeeze(-1).transpose(0, 1)
    blend = torch.bmm(weights, top.reshape(b, j, 12)).view(b, n, 3, 4)
    x = homogeneous if homogeneous.ndim == 3 else homogeneous.expand(b, n, 4)
    return (blend @ x.unsqueeze(-1)).squeeze(-1)


def nearest_vertex_weights(
    points: torch.Tensor,
    vertices: torch.Tensor,
    weights: torch.Tensor,
    k: int = 4,
    chunk: int = 4096,
) -> torch.Tensor:
    """Skinning weights [N, J] for canonical points, borrowed from the nearest canonical vertices.

    points: [N, 3]; vertices: [V, 3]; weights: [V, J] (rows sum to 1, and so do the results).

    ``k=1`` is EVA's rule (§3.1: the weights of the nearest vertex). It is piecewise constant, so
    a point crossing the boundary between two vertices' regions jumps (centimetres near a bent
    joint). ``k >= 2`` blends the ``k`` nearest vertices with inverse-distance factors
    ``1/d_i - 1/d_(k+1)`` that vanish exactly when a vertex leaves the ``k`` nearest, so the
    weights -- and the skinned point -- vary continuously with the point, and a point on a vertex
    still gets that vertex's weights.
    """
    if k < 1:
        raise ValueError("k must be >= 1")
    if vertices.shape[0] == 1:
        return weights.expand(points.shape[0], -1).clone()
    k = min(k, vertices.shape[0] - 1)
    dist, idx = _knn(points.detach(), vertices.detach(), k + 1, chunk)
    if k == 1:
        return weights[idx[:, 0]]
    out = []
    for d, i in zip(dist.split(chunk), idx.split(chunk), strict=True):  # [chunk, k, J] at a time
        inv = 1.0 / d.clamp_min(1e-12)
        alpha = (inv[:, :k] - inv[:, k:]).clamp_min(0.0)
        # All k+1 distances equal (a measure-zero tie): fall back to a plain average.
        alpha = torch.where(alpha.sum(1, keepdim=True) > 0, alpha, torch.ones_like(alpha))
        alpha = alpha / alpha.sum(1, keepdim=True)
        out.append(torch.einsum("nk,nkj->nj", alpha, weights[i[:, :k]]))
    return torch.cat(out) if out else weights.new_zeros(0, weights.shape[1])


def _knn(
    points: torch.Tensor, vertices: torch.Tensor, k: int, chunk: int = 4096
) -> tuple[torch.Tensor, torch.Tensor]:
    """Exact distances [N, k] and indices [N, k] of the k nearest vertices, ascending.

    On CPU a k-d tree (scipy's, float64) finds them: by brute force, refreshing the Gaussians'
    nearest vertices was an eighth of a short training's time (``docs/speed.md``). Elsewhere
    cdist shortlists candidates ``chunk`` points at a time (its fast matrix-product path loses
    ~1e-4 m near zero, so it only shortlists). Either way the distances returned are recomputed
    exactly in the inputs' dtype and the candidates ordered by them."""
    if points.shape[0] == 0:
        empty = torch.zeros(0, k, dtype=torch.int64, device=points.device)
        return points.new_zeros(0, k), empty
    if points.device.type == "cpu":
        from scipy.spatial import cKDTree

        _, found = cKDTree(vertices.double().numpy()).query(points.double().numpy(), k=k)
        cand = torch.from_numpy(found).reshape(points.shape[0], k).to(torch.int64)
    else:
        shortlist = min(k + 8, vertices.shape[0])
        cand = torch.cat(
            [
                torch.cdist(p, vertices).topk(shortlist, dim=1, largest=False).indices
                for p in points.split(chunk)
            ]
        )
    dist = (vertices[cand] - points[:, None]).norm(dim=-1)
    dist, order = dist.sort(dim=1)
    return dist[:, :k], cand.gather(1, order[:, :k])


def nearest_vertex_index(points: torch.Tensor, vertices: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
    """Index [N] of the nearest vertex (of [V, 3]) to each of ``points`` [N, 3]."""
    return _knn(points.detach(), vertices.detach(), 1, chunk)[1][:, 0]


def part_ids_from_weights(
    weights: torch.Tensor, hand_joints: Sequence[int], face_joints: Sequence[int]
) -> torch.Tensor:
    """Part id per vertex [V] from skinning weights [V, J]: the part holding the largest total
    weight (hand chains -> hand, head/jaw/eyes -> face, everything else -> body)."""
    j = weights.shape[1]
    part_of_joint = torch.zeros(j, dtype=torch.int64)
    part_of_joint[list(hand_joints)] = PART_NAMES.index("hand")
    part_of_joint[list(face_joints)] = PART_NAMES.index("face")
    per_part = torch.zeros(weights.shape[0], len(PART_NAMES), dtype=weights.dtype)
    per_part.index_add_(1, part_of_joint, weights.detach().cpu())
    return per_part.argmax(dim=1)
