"""``train_avatar``: fit an :class:`~eva_engine.avatar.Avatar` to a dataset's training frames.

One frame per step (a seeded random order, epoch by epoch), as 3DGS does:
pose (skinning) -> rasterize -> losses -> backward -> Adam steps -> density control. Progress
goes to an optional callback (``eva_engine.progress.ProgressEvent``: stages "setup", "train",
"done"); per-stage wall time is accumulated in ``TrainResult.timings`` (what ``bench/train.py``
reports).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from eva_engine.avatar import Avatar, AvatarFrames, Camera, TrainingRecord
from eva_engine.avatar.coverage import Coverage
from eva_engine.avatar.expression_colours import clamp_offsets
from eva_engine.body import load_body_model
from eva_engine.body.model import PART_NAMES, BodyModel
from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import Dataset, DatasetLike
from eva_engine.data.resampled import ResampledDataset
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.train.config import TrainConfig
from eva_engine.train.face_views import FaceViews
from eva_engine.train.frame_order import epoch_frames, shuffled
from eva_engine.train.losses import AvatarLoss, composite_target
from eva_engine.train.pose_correction import PoseCorrection
from eva_engine.train.regularizers import regularization

logger = logging.getLogger(__name__)

STAGES = ("data", "skinning", "rasterize", "losses", "face_view", "backward", "optimizer", "densify")


class TrainingError(RuntimeError):
    """The data cannot be trained on (no body parameters, no training frames, ...)."""


def _train_event(
    stage: str,
    done: int,
    total: int,
    loss: float | None,
    num_gaussians: int,
    elapsed: float,
    eta: float | None,
) -> ProgressEvent:
    """A training progress report: stage "setup", "train" or "done", iteration ``done`` (1-based)
    of ``total``, the current loss, the Gaussian count, elapsed and remaining seconds."""
    message = f"iteration {done}/{total}, {num_gaussians} Gaussians"
    if loss is not None:
        message += f", loss {loss:.4f}"
    return ProgressEvent(stage, done, total, message, loss, num_gaussians, elapsed, eta)


@dataclass
class TrainResult:
    """avatar: the trained model (eval mode); losses: total loss per iteration;
    train_seconds: wall time of the optimisation loop; timings: seconds per stage (``STAGES``);
    refinements: the strategy's reports (step and counts; the last one, with step = iterations,
    is ``finalize``'s if it changed anything); gaussians_per_part: {"before", "after"} ->
    {part name: count} at the start and the end of training; train_indices: the dataset frames
    trained on; train_params: their body parameters as trained (the fit with the per-frame
    pose correction applied, when it is on); pose_correction: the residuals' mean size per
    group (empty when off)."""

    avatar: Avatar
    losses: list[float]
    train_seconds: float
    timings: dict[str, float]
    refinements: list[dict] = field(default_factory=list)
    gaussians_per_part: dict[str, dict[str, int]] = field(default_factory=dict)
    train_indices: list[int] = field(default_factory=list)
    train_params: BodyParams | None = None
    pose_correction: dict[str, float] = field(default_factory=dict)
    coverage: Coverage | None = None

    def frame_params(self, fitted: BodyParams) -> BodyParams:
        """The dataset's ``fitted`` params (batch F) with the trained frames' rows replaced by
        their params as trained (the pose-corrected ones); the other frames keep their fit."""
        out = fitted.map(lambda t: t.detach().cpu().float().clone())
        if self.train_params is None:
            return out
        rows = torch.tensor(self.train_indices, dtype=torch.int64)
        for k, v in self.train_params.tensors().items():
            getattr(out, k)[rows] = v.detach().cpu().float()
        return out

    def frames(self, dataset: Dataset) -> AvatarFrames:
        """``dataset``'s frames to keep with the avatar, posed as trained (``frame_params``)."""
        if dataset.params is None:
            raise TrainingError("the dataset has no body parameters to keep with the avatar")
        return AvatarFrames.of_dataset(dataset, self.frame_params(dataset.params))

    def record(self, config: TrainConfig, **provenance: Any) -> TrainingRecord:
        """What ``avatar.json`` keeps of this run of ``config``; ``provenance``: the other
        :class:`TrainingRecord` fields (preset, method, metrics, where the data came from)."""
        return TrainingRecord(
            train_config=config.to_dict(),
            iterations=config.iterations,
            train_seconds=self.train_seconds,
            final_loss=self.losses[-1],
            timings=self.timings,
            refinements=self.refinements,
            gaussians_per_part=self.gaussians_per_part,
            pose_correction=self.pose_correction,
            coverage=self.coverage,
            **provenance,
        )


def part_counts(part_ids: Tensor) -> dict[str, int]:
    """{part name: number of Gaussians} for ``part_ids [N]``."""
    return {name: int((part_ids == i).sum()) for i, name in enumerate(PART_NAMES)}


@dataclass
class TrainingFrames:
    """Training frames in memory: images [T, H, W, 3], masks [T, H, W], cameras, params (batch T)."""

    images: Tensor
    masks: Tensor
    cameras: list[Camera]
    params: BodyParams


def load_training_frames(dataset: DatasetLike, indices: list[int]) -> TrainingFrames:
    """Read the frames ``indices`` of ``dataset`` into memory."""
    if dataset.params is None:
        raise TrainingError(
            "the dataset has no body parameters (params.safetensors); fit them first (alignment), "
            "or use a dataset that provides them"
        )
    if not indices:
        raise TrainingError("the dataset has no frames in this split")
    images, masks, cameras = [], [], []
    for i in indices:
        frame = dataset[i]
        img, mask = frame.image.float(), frame.mask.float()
        images.append(img)
        masks.append(mask)
        cameras.append(Camera(frame.K.float(), frame.viewmat.float(), img.shape[1], img.shape[0]))
    params = BodyParams.cat([dataset.params[i] for i in indices])
    return TrainingFrames(torch.stack(images), torch.stack(masks), cameras, params)


def dataset_background(dataset: DatasetLike, config: TrainConfig) -> Tensor:
    """[3] the background renders and targets use: the config's, the dataset's, or white."""
    if config.background is not None:
        return torch.tensor(config.background, dtype=torch.float32)
    bg = dataset.meta.background
    return torch.tensor(bg if bg is not None else (1.0, 1.0, 1.0), dtype=torch.float32)


def resolve_device(name: str) -> torch.device:
    device = torch.device(name)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise TrainingError("CUDA was asked for but is not available; use device='cpu'")
    return device


def make_optimizers(avatar: Avatar, config: TrainConfig) -> dict[str, torch.optim.Optimizer]:
    """One Adam per splat (3DGS's eps 1e-15): the optimizers a density-control strategy edits.
    Fused (one pass over each tensor): 3.5x faster on CPU than the per-op update, equal to rounding."""
    lrs = config.optim.splat_lrs()
    return {
        name: torch.optim.Adam([p], lr=lrs[name], eps=1e-15, fused=True)
        for name, p in avatar.gaussians.splats.items()
    }


def make_extra_optimizers(
    avatar: Avatar, config: TrainConfig, loss: AvatarLoss
) -> list[torch.optim.Optimizer]:
    """Adam for the MLPs (one parameter group per network, the pose refiner's per part, each
    at its rate: ``OptimConfig``), and for the loss's own parameters if it has any."""
    o = config.optim
    out = []
    groups = []
    for name, net in avatar.networks().items():
        if name == "pose_refiner":
            base = o.pose_refine_lr if o.pose_refine_lr is not None else o.mlp_lr
            for part, mlp in net.mlps.items():
                scale = o.pose_refine_part_scale[PART_NAMES.index(part)]
                groups.append({"params": list(mlp.parameters()), "lr": base * scale})
        else:
            lr = (
                o.weight_offsets_lr
                if name == "weight_offsets" and o.weight_offsets_lr is not None
                else o.mlp_lr
            )
            groups.append({"params": list(net.parameters()), "lr": lr})
    groups = [g for g in groups if g["params"]]
    if groups:
        out.append(torch.optim.Adam(groups, lr=o.mlp_lr))
    loss_params = [p for p in loss.parameters() if p.requires_grad]
    if loss_params:
        out.append(torch.optim.Adam(loss_params, lr=config.optim.loss_lr))
    return out


def means_lr(config: TrainConfig, step: int) -> float:
    """Exponential decay of the means' learning rate from init to final over the run, or over
    ``means_lr_steps`` (3DGS)."""
    o = config.optim
    horizon = o.means_lr_steps if o.means_lr_steps is not None else max(config.iterations - 1, 1)
    t = min(step / horizon, 1.0)
    return math.exp((1 - t) * math.log(o.means_lr) + t * math.log(o.means_lr_final)) * o.spatial_scale


def with_pose_noise(
    params: BodyParams, joints: Tensor, sigma: float, generator: torch.Generator
) -> BodyParams:
    """``params`` (batch 1) with Gaussian noise of std ``sigma`` (radians) added to the axis-angles
    of the pose joints in ``joints [P]`` (bool)."""
    noise = torch.randn(params.joints.shape, generator=generator).to(params.joints) * sigma
    noise = noise * joints[None, :, None].to(noise)
    return BodyParams(
        root_orient=params.root_orient,
        transl=params.transl,
        joints=params.joints + noise,
        expression=params.expression,
        shape=params.shape,
    )


class TrainingRun:
    """One training run's state on ``device``: the training frames and their targets, the avatar,
    its loss, optimisers and density-control state, the pose correction, and the seeded random
    generators. ``step(i)`` is one optimisation step (one frame), ``finalize()`` the strategy's
    last pass, ``result(seconds)`` what the run produced. ``train_avatar`` drives it."""

    def __init__(
        self, dataset: DatasetLike, config: TrainConfig, body: BodyModel, device: torch.device
    ) -> None:
        self.config, self.device = config, device
        self.train_ids = list(dataset.splits.get("train", []))
        frames = load_training_frames(ResampledDataset(dataset, config.image_scale), self.train_ids)
        self.frames = frames
        self.background = dataset_background(dataset, config).to(device)
        self.targets = torch.stack(
            [
                composite_target(img, m, self.background.cpu())
                for img, m in zip(frames.images, frames.masks, strict=True)
            ]
        ).to(device)
        self.masks = frames.masks.to(device)
        self.params = frames.params.to(device)
        self.face_views = (
            FaceViews.load(dataset, self.train_ids, device) if config.face_view.weight > 0 else None
        )

        shape = self.params.shape.mean(dim=0)
        # Every random draw of the run comes from generators seeded here (the strategy has its
        # own), never from torch's global state: the initial weights (the avatar's MLPs, then the
        # loss's) and the frame order.
        weights = torch.Generator().manual_seed(config.seed)
        face = None  # the template's expression (AvatarConfig.template_expression)
        if config.avatar.template_expression == "median":
            face = self.params.expression.median(dim=0).values
        avatar = Avatar.create(body.to(device), shape, config.avatar, config.seed, weights, face)
        self.avatar = avatar.to(device)
        self.avatar.set_expression_range(self.params.expression)
        self.avatar.active_sh_degree = 0
        self.loss_fn = AvatarLoss(config.loss, generator=weights).to(device)
        self.optimizers = make_optimizers(self.avatar, config)
        self.extra = make_extra_optimizers(self.avatar, config, self.loss_fn)
        self.correction: PoseCorrection | None = None
        self.correction_opt: torch.optim.Optimizer | None = None
        ground_truth = getattr(dataset.meta, "params_source", None) == "ground_truth"
        if config.pose_correction.enabled and ground_truth:
            logger.info("pose correction off: the dataset's body parameters are ground truth")
        elif config.pose_correction.enabled:
            self.correction = PoseCorrection(
                len(self.train_ids),
                body.joint_part_ids[1:],
                self.params.expression.shape[1],
                config.pose_correction,
            ).to(device)
            self.correction_opt = torch.optim.Adam(self.correction.parameters(), lr=config.pose_correction.lr)
        self.strategy = config.strategy
        self.strategy.check_sanity(self.avatar.gaussians, self.optimizers)
        self.state = self.strategy.initialize_state()
        self.parts_before = part_counts(self.avatar.gaussians.part_ids)

        self.frame_order = torch.Generator().manual_seed(config.seed)
        self.epoch = epoch_frames(
            self.params.expression.cpu(), list(body.expression_names), config.expression_events
        )
        # Draws of the options that perturb a step (their own generator: turning one on leaves the
        # frame order and the initial weights as they were).
        self.perturb = torch.Generator().manual_seed(config.seed + 1)
        self.body_joints = (body.joint_part_ids[1:] == 0).to(device)
        bound = config.avatar.max_scale
        self.max_scale = torch.tensor(bound, device=device) if bound is not None else None
        self.order: list[int] = []
        self.timings = dict.fromkeys(STAGES, 0.0)
        self.losses: list[float] = []
        self.refinements: list[dict] = []

    def _tick(self, stage: str, t0: float) -> float:
        if self.device.type == "cuda":
            torch.cuda.synchronize()
        t1 = time.perf_counter()
        self.timings[stage] += t1 - t0
        return t1

    def step(self, step: int) -> float:
        """Optimisation step ``step`` (0-based) on the next frame of the seeded order; returns its
        loss (the image terms, without the priors). ``TrainingError`` on a non-finite loss,
        before the parameters move."""
        config, avatar, tick = self.config, self.avatar, self._tick
        t = time.perf_counter()
        if not self.order:
            self.order = shuffled(self.epoch, self.frame_order)
        i = self.order.pop()
        if step > 0 and step % config.sh_degree_interval == 0:
            avatar.active_sh_degree = min(avatar.active_sh_degree + 1, avatar.gaussians.sh_degree)
        for g in self.optimizers["means"].param_groups:
            g["lr"] = means_lr(config, step)
        cam = self.frames.cameras[i]
        t = tick("data", t)

        correction = self.correction
        correcting = correction is not None and step >= config.pose_correction.start_iter
        frame_params = correction.apply(self.params[i], i) if correcting else self.params[i]
        if config.pose_noise > 0:
            frame_params = with_pose_noise(frame_params, self.body_joints, config.pose_noise, self.perturb)
        if config.random_background:
            bg = torch.rand(3, generator=self.perturb).to(self.device)
            target, key = composite_target(self.frames.images[i].to(self.device), self.masks[i], bg), None
        else:
            bg, target, key = self.background, self.targets[i], i
        posed = avatar.pose(frame_params)
        t = tick("skinning", t)
        render = avatar.rasterize_posed(posed, cam, bg)
        t = tick("rasterize", t)
        terms = self.loss_fn(render, target, self.masks[i], key=key, step=step)
        total = (terms["total"] + correction.prior(i)) if correcting else terms["total"]
        if config.regularizers.active:
            total = total + regularization(avatar, config.regularizers, posed)
        t = tick("losses", t)
        face = config.face_view
        view = self.face_views.view(i, bg) if self.face_views is not None and step % face.every == 0 else None
        face_render = None
        if view is not None:
            face_cam, face_target, face_mask = view
            face_render = avatar.rasterize_posed(posed, face_cam, bg)
            face_key = ("face", key) if key is not None else None
            face_terms = self.loss_fn(face_render, face_target, face_mask, key=face_key, step=step)
            total = total + face.every * face.weight * face_terms["total"]
            t = tick("face_view", t)
        loss, step_total = float(terms["total"].detach()), float(total.detach())
        if not math.isfinite(step_total):  # non-finite whenever the loss terms are
            # Before backward: the avatar keeps the last finite step's parameters.
            raise TrainingError(f"the loss became {step_total} at iteration {step}; training stopped")
        total.backward()
        t = tick("backward", t)
        for opt in (*self.optimizers.values(), *self.extra, *([self.correction_opt] if correcting else [])):
            opt.step()
            opt.zero_grad(set_to_none=True)
        if self.max_scale is not None:
            avatar.gaussians.clamp_scales(self.max_scale)
        if "sh0_expression" in avatar.gaussians.splats:
            clamp_offsets(avatar.gaussians.splats["sh0_expression"])
        t = tick("optimizer", t)
        if face_render is not None and face.densify:
            self.strategy.observe_view(avatar.gaussians, self.state, step, face_render)
        stats = self.strategy.step_post_backward(avatar.gaussians, self.optimizers, self.state, step, render)
        if stats:
            self.refinements.append({"step": step, **stats})
        tick("densify", t)
        self.losses.append(loss)
        return loss

    def finalize(self) -> None:
        """The strategy's last pass (e.g. a final prune), timed as densification."""
        t = time.perf_counter()
        stats = self.strategy.finalize(self.avatar.gaussians, self.optimizers, self.state)
        if stats:
            self.refinements.append({"step": self.config.iterations, **stats})
            logger.info("after training: %s", stats)
        self._tick("densify", t)

    def result(self, train_seconds: float) -> TrainResult:
        """The run's result, the avatar in eval mode."""
        self.avatar.eval()
        per_part = {"before": self.parts_before, "after": part_counts(self.avatar.gaussians.part_ids)}
        correction = self.correction
        trained = (correction.corrected(self.params) if correction is not None else self.params).to("cpu")
        viewmats = torch.stack([c.viewmat for c in self.frames.cameras])
        coverage = Coverage.of_frames(self.avatar.body, trained, viewmats)
        return TrainResult(
            self.avatar,
            self.losses,
            train_seconds,
            self.timings,
            self.refinements,
            per_part,
            self.train_ids,
            trained,
            correction.magnitudes() if correction is not None else {},
            coverage,
        )


def train_avatar(
    dataset: DatasetLike,
    config: TrainConfig | None = None,
    body: BodyModel | None = None,
    progress: Progress | None = None,
    checkpoint: Callable[[int, Avatar, float], None] | None = None,
    checkpoint_steps: tuple[int, ...] = (),
) -> TrainResult:
    """Train an avatar on ``dataset.splits["train"]``, its frames resampled by
    ``config.image_scale`` (:class:`~eva_engine.data.resampled.ResampledDataset`).

    body: the body model the dataset's parameters are for (default: ``meta.body_model``).
    checkpoint: called as ``checkpoint(step, avatar, seconds)`` after each of
    ``checkpoint_steps`` (1-based iteration counts) with the avatar as it trains (e.g. to
    evaluate it) and the training seconds so far; its own time is not counted as training.
    """
    config = config or TrainConfig()
    device = resolve_device(config.device)
    t_setup = time.perf_counter()
    if progress:
        progress(ProgressEvent("setup", 0, config.iterations, "setting up training", elapsed=0.0))
    if body is None:
        name = dataset.meta.body_model
        if name is None:
            raise TrainingError("the dataset names no body model (meta.body_model)")
        body = load_body_model(name)
    run = TrainingRun(dataset, config, body, device)
    logger.info(
        "setup %.1fs: %d frames, %d Gaussians",
        time.perf_counter() - t_setup,
        len(run.train_ids),
        len(run.avatar.gaussians),
    )

    start = time.perf_counter()
    paused = 0.0  # seconds spent in ``checkpoint``
    for step in range(config.iterations):
        loss = run.step(step)
        done = step + 1
        if checkpoint is not None and done in checkpoint_steps:
            t = time.perf_counter()
            checkpoint(done, run.avatar, t - start - paused)
            run.avatar.train()
            paused += time.perf_counter() - t
        if progress and (done % config.progress_every == 0 or done == config.iterations):
            elapsed = time.perf_counter() - start - paused
            eta = elapsed / done * (config.iterations - done)
            progress(
                _train_event("train", done, config.iterations, loss, len(run.avatar.gaussians), elapsed, eta)
            )

    run.finalize()
    train_seconds = time.perf_counter() - start - paused
    result = run.result(train_seconds)
    if progress:
        n = config.iterations
        progress(_train_event("done", n, n, run.losses[-1], len(run.avatar.gaussians), train_seconds, 0.0))
    return result
