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
from eva_engine.body.model import PART_NAMES, BodyModel
from eva_engine.body.params import BodyParams
from eva_engine.data.dataset import Dataset, DatasetLike
from eva_engine.data.resampled import ResampledDataset
from eva_engine.progress import Progress, ProgressEvent
from eva_engine.train.config import TrainConfig
from eva_engine.train.losses import AvatarLoss, composite_target
from eva_engine.train.pose_correction import PoseCorrection
from eva_engine.train.regularizers import regularization

logger = logging.getLogger(__name__)

STAGES = ("data", "skinning", "rasterize", "losses", "backward", "optimizer", "densify")


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
        from eva_engine.body import load_body_model

        name = dataset.meta.body_model
        if name is None:
            raise TrainingError("the dataset names no body model (meta.body_model)")
        body = load_body_model(name)
    train_ids = list(dataset.splits.get("train", []))
    frames = load_training_frames(ResampledDataset(dataset, config.image_scale), train_ids)
    background = dataset_background(dataset, config).to(device)
    targets = torch.stack(
        [
            composite_target(img, m, background.cpu())
            for img, m in zip(frames.images, frames.masks, strict=True)
        ]
    ).to(device)
    masks = frames.masks.to(device)
    params = frames.params.to(device)

    shape = params.shape.mean(dim=0)
    # Every random draw of the run comes from generators seeded here (the strategy has its own),
    # never from torch's global state: the initial weights (the avatar's MLPs, then the loss's)
    # and the frame order.
    weights = torch.Generator().manual_seed(config.seed)
    avatar = Avatar.create(body.to(device), shape, config.avatar, seed=config.seed, generator=weights)
    avatar = avatar.to(device)
    avatar.active_sh_degree = 0
    loss_fn = AvatarLoss(config.loss, generator=weights).to(device)
    optimizers = make_optimizers(avatar, config)
    extra = make_extra_optimizers(avatar, config, loss_fn)
    correction, correction_opt = None, None
    ground_truth = getattr(dataset.meta, "params_source", None) == "ground_truth"
    if config.pose_correction.enabled and ground_truth:
        logger.info("pose correction off: the dataset's body parameters are ground truth")
    elif config.pose_correction.enabled:
        correction = PoseCorrection(
            len(train_ids), body.joint_part_ids[1:], params.expression.shape[1], config.pose_correction
        ).to(device)
        correction_opt = torch.optim.Adam(correction.parameters(), lr=config.pose_correction.lr)
    strategy = config.strategy
    strategy.check_sanity(avatar.gaussians, optimizers)
    state = strategy.initialize_state()
    parts_before = part_counts(avatar.gaussians.part_ids)
    logger.info(
        "setup %.1fs: %d frames, %d Gaussians",
        time.perf_counter() - t_setup,
        len(train_ids),
        len(avatar.gaussians),
    )

    frame_order = torch.Generator().manual_seed(config.seed)
    # Draws of the options that perturb a step (their own generator: turning one on leaves the
    # frame order and the initial weights as they were).
    perturb = torch.Generator().manual_seed(config.seed + 1)
    body_joints = (body.joint_part_ids[1:] == 0).to(device)
    max_scale = (
        torch.tensor(config.avatar.max_scale, device=device) if config.avatar.max_scale is not None else None
    )
    order: list[int] = []
    timings = dict.fromkeys(STAGES, 0.0)
    losses: list[float] = []
    refinements: list[dict] = []
    start = time.perf_counter()
    paused = 0.0  # seconds spent in ``checkpoint``

    def tick(stage: str, t0: float) -> float:
        if device.type == "cuda":
            torch.cuda.synchronize()
        t1 = time.perf_counter()
        timings[stage] += t1 - t0
        return t1

    for step in range(config.iterations):
        t = time.perf_counter()
        if not order:
            order = torch.randperm(len(train_ids), generator=frame_order).tolist()
        i = order.pop()
        if step > 0 and step % config.sh_degree_interval == 0:
            avatar.active_sh_degree = min(avatar.active_sh_degree + 1, avatar.gaussians.sh_degree)
        for g in optimizers["means"].param_groups:
            g["lr"] = means_lr(config, step)
        cam = frames.cameras[i]
        t = tick("data", t)

        correcting = correction is not None and step >= config.pose_correction.start_iter
        frame_params = correction.apply(params[i], i) if correcting else params[i]
        if config.pose_noise > 0:
            frame_params = with_pose_noise(frame_params, body_joints, config.pose_noise, perturb)
        if config.random_background:
            bg = torch.rand(3, generator=perturb).to(device)
            target, key = composite_target(frames.images[i].to(device), masks[i], bg), None
        else:
            bg, target, key = background, targets[i], i
        posed = avatar.pose(frame_params)
        t = tick("skinning", t)
        render = avatar.rasterize_posed(posed, cam, bg)
        t = tick("rasterize", t)
        terms = loss_fn(render, target, masks[i], key=key, step=step)
        total = (terms["total"] + correction.prior(i)) if correcting else terms["total"]
        if config.regularizers.active:
            total = total + regularization(avatar, config.regularizers, posed)
        t = tick("losses", t)
        loss, step_total = float(terms["total"].detach()), float(total.detach())
        if not math.isfinite(step_total):  # non-finite whenever the loss terms are
            # Before backward: the avatar keeps the last finite step's parameters.
            raise TrainingError(f"the loss became {step_total} at iteration {step}; training stopped")
        total.backward()
        t = tick("backward", t)
        for opt in (*optimizers.values(), *extra, *([correction_opt] if correcting else [])):
            opt.step()
            opt.zero_grad(set_to_none=True)
        if max_scale is not None:
            avatar.gaussians.clamp_scales(max_scale)
        t = tick("optimizer", t)
        stats = strategy.step_post_backward(avatar.gaussians, optimizers, state, step, render)
        if stats:
            refinements.append({"step": step, **stats})
        tick("densify", t)

        losses.append(loss)
        done = step + 1
        if checkpoint is not None and done in checkpoint_steps:
            t = time.perf_counter()
            checkpoint(done, avatar, t - start - paused)
            avatar.train()
            paused += time.perf_counter() - t
        if progress and (done % config.progress_every == 0 or done == config.iterations):
            elapsed = time.perf_counter() - start - paused
            eta = elapsed / done * (config.iterations - done)
            event = _train_event("train", done, config.iterations, loss, len(avatar.gaussians), elapsed, eta)
            progress(event)

    t = time.perf_counter()
    stats = strategy.finalize(avatar.gaussians, optimizers, state)
    if stats:
        refinements.append({"step": config.iterations, **stats})
        logger.info("after training: %s", stats)
    tick("densify", t)
    train_seconds = time.perf_counter() - start - paused
    avatar.eval()
    if progress:
        n = config.iterations
        progress(_train_event("done", n, n, losses[-1], len(avatar.gaussians), train_seconds, 0.0))
    per_part = {"before": parts_before, "after": part_counts(avatar.gaussians.part_ids)}
    trained = (correction.corrected(params) if correction is not None else params).to("cpu")
    viewmats = torch.stack([c.viewmat for c in frames.cameras])
    coverage = Coverage.of_frames(avatar.body, trained, viewmats)
    return TrainResult(
        avatar,
        losses,
        train_seconds,
        timings,
        refinements,
        per_part,
        train_ids,
        trained,
        correction.magnitudes() if correction is not None else {},
        coverage,
    )
