"""One avatar job, stage by stage, resumable, run inside the job's own process (``jobs.runner``
starts it; an animation job runs the stages of ``jobs.animation`` the same way): video ->
dataset (preprocess + align) -> trained avatar -> published avatar. Every
stage's result lands in the job's work folder by an atomic rename, so a process killed at any
moment leaves either the previous stage's result or the next one, and a retry starts after the
last completed stage.

    work/<job_id>/input.video   the upload (written by the API, whatever its name was)
    work/<job_id>/dataset/      eva_engine.align.preprocess_video (stages preprocess, align)
    work/<job_id>/avatar/       eva_engine.avatar.save_avatar: with its metrics and frames (stage train)
    avatars/<avatar_id>/        the same folder, renamed (stage export)

Every record write is conditional on this attempt still owning the job (``JobStore`` ``owner=``);
when it does not (recovery gave the job to another worker), the stage stops with ``JobLost`` and
this attempt writes nothing more. Partial results carry the attempt's own suffix, so two
attempts never write into one folder.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import re
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from eva_engine.progress import ProgressEvent
from jobs.config import JobsConfig
from jobs.disk import DiskFull, is_disk_full
from jobs.options import JobOptions
from jobs.progress import preprocess_progress
from jobs.storage import Storage, input_file, move_into_place
from jobs.store import STAGES, JobLost, JobRecord, JobStore

logger = logging.getLogger("eva.jobs")

# Share of the whole job each stage stands for in ``progress`` (measured roughly on CPU).
STAGE_SPANS = {"preprocess": (0.0, 0.25), "align": (0.25, 0.5), "train": (0.5, 0.97), "export": (0.97, 1.0)}
METRIC_FRAMES = 8


class JobCancelled(Exception):
    """The job was cancelled while running (raised from a progress callback)."""


class Reporter:
    """Turns engine callbacks into job-record updates (throttled) and stops the stage when the
    job was cancelled (``JobCancelled``) or this attempt no longer owns it (``JobLost``)."""

    def __init__(
        self,
        store: JobStore,
        job: JobRecord,
        worker: str,
        interval: float = 0.5,
        spans: dict[str, tuple[float, float]] | None = None,
    ) -> None:
        self.store, self.job, self.worker, self.interval = store, job, worker, interval
        self.spans = spans or STAGE_SPANS
        self._last = 0.0
        self._stage: str | None = None

    def __call__(self, event: ProgressEvent, force: bool = False) -> None:
        """``event``: a job stage (``spans``) and how far into it (``fraction``), with a message
        and an ETA; reported at most every ``interval`` seconds per stage, unless ``force``."""
        now = time.monotonic()
        stage = event.stage
        if not force and stage == self._stage and now - self._last < self.interval:
            return
        self._stage, self._last = stage, now
        lo, hi = self.spans[stage]
        progress = lo + (hi - lo) * event.fraction
        eta = event.eta if event.eta is not None and math.isfinite(event.eta) else None
        if not self.store.update(
            self.job.id,
            owner=self.worker,
            stage=stage,
            progress=progress,
            eta_s=eta,
            message=event.message,
            heartbeat_at=time.time(),
        ):
            raise JobLost(self.job.id)
        current = self.store.get(self.job.id)
        if current is None or current.cancel_requested:
            raise JobCancelled(self.job.id)

    def completed(self, stage: str) -> None:
        if not self.store.update(self.job.id, owner=self.worker, completed_stage=stage):
            raise JobLost(self.job.id)


@dataclass
class JobRun:
    """One attempt at one job, by ``worker`` (which has claimed it), in the job's process."""

    config: JobsConfig
    store: JobStore
    storage: Storage
    job: JobRecord
    worker: str
    attempt: str = field(default_factory=lambda: uuid.uuid4().hex[:8])
    _models: dict = field(default_factory=dict)

    def add_body_model(self, model) -> None:
        """Use an already loaded body model (keyed by its ``name``)."""
        self._models[model.name] = model

    def body_model(self, name: str):
        if name not in self._models:
            from eva_engine.body import load_body_model

            self._models[name] = load_body_model(name)
        return self._models[name]

    def execute(self) -> str | None:
        """Run the stages of the job's kind (an avatar, or an animation: ``jobs.animation``) and
        end the job with its outcome; returns the final state, or None when this attempt lost
        the job (it then leaves the record and the files alone). Raises ``DiskFull`` (leaving
        the record and the files alone) when the disk is full."""
        job = self.job
        stages, spans = self._stages, STAGE_SPANS
        if job.kind == "animation":
            from jobs.animation import ANIMATION_STAGE_SPANS, animation_stages

            stages, spans = (lambda j, r: animation_stages(self, j, r)), ANIMATION_STAGE_SPANS
        report = Reporter(self.store, job, self.worker, spans=spans)
        stage = job.completed_stage
        try:
            stages(job, report)
        except JobLost:
            logger.warning("job %s: %s no longer owns it; this attempt stops", job.id, self.worker)
            return None
        except JobCancelled:
            state, fields = "cancelled", {"message": "cancelled on request"}
        except Exception as err:  # every failure ends the job with its reason
            if is_disk_full(err):  # but a full disk: the job goes back to the queue, upload and all
                logger.error("job %s: the disk is full; its attempt stops here", job.id, exc_info=True)
                raise DiskFull(job.id) from err
            stage = (self.store.get(job.id) or job).stage or stage
            reason = failure_reason(err, stage, self.config)
            # No server paths in messages.
            reason = re.sub(
                re.escape(str(self.storage.work_dir(job.id))) + r"/[^\s:;,]*", "the uploaded video", reason
            )
            logger.warning(
                "job %s failed in stage %s: %s", job.id, stage, reason, exc_info=not is_input_error(err)
            )
            state, fields = "failed", {"error": reason}
        else:
            state, fields = "succeeded", {"message": f"{job.kind} ready"}
        # Its files go first, so a finished job never has any; a crash in between is retried and
        # finds the published result (or fails again). Only while the job is still ours.
        if self.store.update(job.id, owner=self.worker, message=f"{state}: cleaning up"):
            self.storage.remove_work(job.id)
        if not self.store.finish(job.id, state, owner=self.worker, **fields):
            logger.warning("job %s: lost before it could be marked %s", job.id, state)
            return None
        return state

    def _stages(self, job: JobRecord, report: Reporter) -> None:
        options = JobOptions.model_validate(job.options)
        if self.storage.avatar_exists(job.avatar_id):  # published before the last worker died
            return
        work = self.storage.fetch_upload(job.id)
        dataset_dir, trained_dir = work / "dataset", work / "avatar"
        if not trained_dir.is_dir():
            if not dataset_dir.is_dir():
                self._preprocess(work, dataset_dir, options, report)
            report.completed("align")
            self._train(job, dataset_dir, trained_dir, options, report)
        report.completed("train")
        report(ProgressEvent("export", message="publishing the avatar"), force=True)  # ownership checked here
        try:
            self.storage.publish(trained_dir, job.avatar_id)
        except FileExistsError:  # another attempt published the same job's avatar first
            logger.warning("job %s: avatar %s was already published", job.id, job.avatar_id)
        report.completed("export")

    def _preprocess(self, work: Path, out: Path, options: JobOptions, report: Reporter) -> None:
        from eva_engine.align import preprocess_video
        from jobs.media import check_frame_budget, probe_video

        video = input_file(work)
        if video is None:
            raise FileNotFoundError("the uploaded video is missing from the job's folder")
        report(ProgressEvent("preprocess", message="checking the video"), force=True)
        # Again here, not only at upload: the budget may have changed, and this is what decodes.
        info = probe_video(video, self.config.max_video_side, decode_first=False)
        check_frame_budget(info, options.max_frames, options.max_size, self.config.max_frame_pixels)
        report(ProgressEvent("preprocess", message="decoding the video"), force=True)
        model = self.body_model(options.body_model)

        progress = preprocess_progress(report)

        # Decoded as what the probe approved: its demuxer (never one FFmpeg guesses) and size limit.
        config = dataclasses.replace(
            options.preprocess_config(info.frame_count()),
            demuxer=info.container,
            max_video_side=self.config.max_video_side,
        )
        partial = out.with_name(f"{out.name}.partial-{self.attempt}")
        preprocess_video(video, partial, config, model=model, progress=progress, overwrite=True)
        report(ProgressEvent("align", 1, 1, "dataset ready"), force=True)  # still ours: put it in place
        move_into_place(partial, out)
        video.unlink(missing_ok=True)  # the dataset holds the frames now

    def _train(
        self, job: JobRecord, dataset_dir: Path, out: Path, options: JobOptions, report: Reporter
    ) -> None:

        from eva_engine.avatar import save_avatar
        from eva_engine.data import load_dataset
        from eva_engine.eval import ImageMetrics, quality_report
        from eva_engine.train import train_avatar

        ds = load_dataset(dataset_dir)
        body = self.body_model(ds.meta.body_model or options.body_model)
        config = options.train_config(self.config.max_gaussians, self.config.max_gaussian_std_m)
        report(ProgressEvent("train", message="setting up training"), force=True)

        def progress(event: ProgressEvent) -> None:  # the last 5%: the fit on training frames
            report(event.rescaled("train", 0.0, 0.95))

        result = train_avatar(ds, config, body=body, progress=progress)
        report(ProgressEvent("train", 0.95, 1, "scoring the avatar on unseen frames"), force=True)
        metrics = ImageMetrics()  # LPIPS networks loaded once for both
        quality = quality_report(result.avatar, ds, metrics)
        record = result.record(
            config,
            preset=options.preset,
            method=options.method,
            options=options.model_dump(),
            metrics=_training_metrics(result.avatar, ds, metrics),
            quality=quality.model_dump(),
            avatar_id=job.avatar_id,
            job_id=job.id,
            source_video=job.filename,
            created_at=time.time(),
        )
        partial = out.with_name(f"{out.name}.partial-{self.attempt}")
        # Each training frame's pose (as trained) and camera: a client renders one to compare with the input.
        save_avatar(result.avatar, partial, record, frames=result.frames(ds))
        report(ProgressEvent("train", 1, 1, "avatar trained"), force=True)  # still ours: put it in place
        move_into_place(partial, out)


def _training_metrics(avatar, ds, metrics=None) -> dict:
    """PSNR / SSIM / LPIPS of the avatar on up to METRIC_FRAMES of its training frames."""
    from eva_engine.eval import evaluate_avatar

    train = list(ds.splits.get("train", []))
    if not train:
        return {}
    step = max(1, math.ceil(len(train) / METRIC_FRAMES))
    ds.splits["fit_check"] = train[::step][:METRIC_FRAMES]
    result = evaluate_avatar(avatar, ds, split="fit_check", metrics=metrics)
    full = result.regions.get("full")
    out = {"split": "train", "frames": result.num_frames, "render_fps": result.render_fps}
    if full is not None:
        out.update(psnr=full.psnr, ssim=full.ssim, lpips_vgg=full.lpips_vgg, lpips_alex=full.lpips_alex)
    return out


def is_input_error(err: Exception) -> bool:
    from eva_engine.align import PreprocessError
    from eva_engine.animate import AnimationError, DrivingError
    from eva_engine.avatar import AvatarFileError
    from eva_engine.data import DatasetError, VideoError
    from eva_engine.train import TrainingError
    from jobs.media import VideoRejected

    inputs = (
        VideoError,
        VideoRejected,
        PreprocessError,
        DatasetError,
        TrainingError,
        FileNotFoundError,
        DrivingError,
        AnimationError,
        AvatarFileError,
    )
    return isinstance(err, inputs)


def _address_space_peak_mb() -> float | None:
    try:
        status = Path("/proc/self/status").read_text()
    except OSError:
        return None
    found = re.search(r"VmPeak:\s+(\d+) kB", status)
    return int(found.group(1)) / 1024 if found else None


def is_out_of_memory(err: BaseException, memory_mb: int | None) -> bool:
    """MemoryError, or any library's failure (torch's allocator, oneDNN, OpenCV word it each their
    own way) after this process's address space came within 10% of its limit."""
    if isinstance(err, MemoryError):
        return True
    peak = _address_space_peak_mb()
    return memory_mb is not None and peak is not None and peak > 0.9 * memory_mb


def failure_reason(err: Exception, stage: str | None, config: JobsConfig) -> str:
    """What the job's record says about ``err``: the input's problem as the engine words it, out
    of memory or disk with the limit, or "internal error" without internals (they are logged)."""
    where = f" (stage {stage})" if stage else ""
    if is_out_of_memory(err, config.job_memory_mb):
        limit = f" of {config.job_memory_mb} MB" if config.job_memory_mb else ""
        return (
            f"the job ran out of memory{where}: it needs more than its limit{limit}; "
            "lower max_frames, max_size or iterations"
        )
    if is_disk_full(err):
        return f"the server's disk is full{where}"
    if is_input_error(err):
        return f"{err}{where}"
    return f"internal error{where}: {type(err).__name__} (details in the worker's log)"


__all__ = ["STAGES", "STAGE_SPANS", "JobCancelled", "JobRun", "Reporter", "failure_reason"]
