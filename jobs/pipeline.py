"""One avatar job, stage by stage, resumable: video -> dataset (preprocess + align) -> trained
avatar -> published avatar. Every stage's result lands in the job's work folder by an atomic
rename, so a worker killed at any moment leaves either the previous stage's result or the next
one, and a retry starts after the last completed stage.

    work/<job_id>/input.<ext>   the upload (written by the API)
    work/<job_id>/dataset/      eva_engine.align.preprocess_video (stages preprocess, align)
    work/<job_id>/avatar/       eva_engine.avatar.save_avatar + metrics + frames (stage train)
    avatars/<avatar_id>/        the same folder, renamed (stage export)
"""

from __future__ import annotations

import logging
import math
import os
import re
import shutil
import socket
import threading
import time
import uuid
from dataclasses import dataclass, field
from pathlib import Path

from jobs.config import JobsConfig
from jobs.options import JobOptions
from jobs.storage import Storage
from jobs.store import STAGES, JobRecord, JobStore

logger = logging.getLogger("eva.jobs")

# Share of the whole job each stage stands for in ``progress`` (measured roughly on CPU).
STAGE_SPANS = {"preprocess": (0.0, 0.25), "align": (0.25, 0.5), "train": (0.5, 0.97), "export": (0.97, 1.0)}
METRIC_FRAMES = 8


class JobCancelled(Exception):
    """The job was cancelled while running (raised from a progress callback)."""


def worker_id() -> str:
    """``host:pid:token``: the token tells a restarted worker that reuses a pid (pid 1 in a
    container) from the dead one."""
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def input_file(work: Path) -> Path | None:
    found = sorted(p for p in work.glob("input.*") if p.is_file()) if work.is_dir() else []
    return found[0] if found else None


class Reporter:
    """Turns engine callbacks into job-record updates (throttled), heartbeats and cancellation."""

    def __init__(self, store: JobStore, job: JobRecord, worker: str, interval: float = 0.5,
                 spans: dict[str, tuple[float, float]] | None = None) -> None:  # fmt: skip
        self.store, self.job, self.worker, self.interval = store, job, worker, interval
        self.spans = spans or STAGE_SPANS
        self._last = 0.0
        self._stage: str | None = None

    def __call__(self, stage: str, fraction: float, eta: float | None = None, message: str | None = None,
                 force: bool = False) -> None:  # fmt: skip
        now = time.monotonic()
        if not force and stage == self._stage and now - self._last < self.interval:
            return
        self._stage, self._last = stage, now
        lo, hi = self.spans[stage]
        progress = lo + (hi - lo) * min(max(fraction, 0.0), 1.0)
        eta = eta if eta is not None and math.isfinite(eta) else None
        self.store.update(self.job.id, where_state=("running",), stage=stage, progress=progress, eta_s=eta,
                          message=message, heartbeat_at=time.time())  # fmt: skip
        current = self.store.get(self.job.id)
        if current is None or current.cancel_requested or current.state != "running":
            raise JobCancelled(self.job.id)

    def completed(self, stage: str) -> None:
        self.store.update(self.job.id, where_state=("running",), completed_stage=stage)


class Heartbeat:
    """A thread that marks the job alive while a long engine call gives no callbacks."""

    def __init__(self, store: JobStore, job_id: str, worker: str, every: float) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(
            target=self._run, args=(store, job_id, worker, every), daemon=True, name=f"heartbeat-{job_id[:8]}"
        )

    def _run(self, store: JobStore, job_id: str, worker: str, every: float) -> None:
        while not self._stop.wait(every):
            store.heartbeat(job_id, worker)

    def __enter__(self) -> Heartbeat:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()


@dataclass
class Pipeline:
    """What a worker process needs to run jobs; body models are loaded once and kept."""

    config: JobsConfig
    store: JobStore
    storage: Storage
    worker: str = field(default_factory=worker_id)
    _models: dict = field(default_factory=dict)
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def add_body_model(self, model) -> None:
        """Use an already loaded body model (keyed by its ``name``)."""
        with self._lock:
            self._models[model.name] = model

    def body_model(self, name: str):
        with self._lock:
            if name not in self._models:
                from eva_engine.body import load_body_model

                self._models[name] = load_body_model(name)
            return self._models[name]

    # -- the job ------------------------------------------------------------------------------
    def run(self, job_id: str) -> str | None:
        """Claim and run the job; returns its final state (None if it was not ours to run)."""
        job = self.store.claim(job_id, self.worker)
        if job is None:
            return None
        logger.info("job %s: attempt %d on %s", job.id, job.attempts, self.worker)
        stages, spans = self._stages, STAGE_SPANS
        if job.kind == "animation":
            from jobs.animation import ANIMATION_STAGE_SPANS, animation_stages

            stages, spans = (lambda j, r: animation_stages(self, j, r)), ANIMATION_STAGE_SPANS
        report = Reporter(self.store, job, self.worker, spans=spans)
        stage = job.completed_stage
        try:
            with Heartbeat(self.store, job.id, self.worker, self.config.heartbeat_s):
                stages(job, report)
        except JobCancelled:
            self.store.finish(job.id, "cancelled", message="cancelled on request")
            state = "cancelled"
        except Exception as err:  # every failure ends the job with its reason
            stage = (self.store.get(job.id) or job).stage or stage
            reason = re.sub(re.escape(str(self.storage.work_dir(job.id))) + r"/\S*", "the uploaded video",
                            _reason(err, stage))  # no server paths in messages  # fmt: skip
            self.store.finish(job.id, "failed", error=reason)
            logger.warning("job %s failed in stage %s", job.id, stage, exc_info=not _is_input_error(err))
            state = "failed"
        else:
            self.store.finish(job.id, "succeeded", message=f"{job.kind} ready")
            state = "succeeded"
        current = self.store.get(job.id)
        if current is None or current.finished:
            self.storage.remove_work(job.id)
        return state

    def _stages(self, job: JobRecord, report: Reporter) -> None:
        options = JobOptions.model_validate(job.options)
        work = self.storage.work_dir(job.id)
        dataset_dir, trained_dir = work / "dataset", work / "avatar"
        if self.storage.avatar_exists(job.avatar_id):  # published before the last worker died
            return
        if not trained_dir.is_dir():
            if not dataset_dir.is_dir():
                self._preprocess(work, dataset_dir, options, report)
            report.completed("align")
            self._train(job, dataset_dir, trained_dir, options, report)
        report.completed("train")
        report("export", 0.0, message="publishing the avatar", force=True)
        self.storage.publish(trained_dir, job.avatar_id)
        report.completed("export")

    def _preprocess(self, work: Path, out: Path, options: JobOptions, report: Reporter) -> None:
        from eva_engine.align import PreprocessConfig, preprocess_video

        video = input_file(work)
        if video is None:
            raise FileNotFoundError("the uploaded video is missing from the job's folder")
        report("preprocess", 0.0, message="decoding the video", force=True)
        model = self.body_model(options.body_model)

        def progress(stage: str, done: int, total: int) -> None:
            frac = done / max(total, 1)
            if stage == "decode":
                report("preprocess", 0.1, message=f"decoded {done} frames")
            elif stage == "detect":
                report("preprocess", 0.1 + 0.9 * frac, message=f"detecting the person: frame {done}/{total}")
            elif stage == "align":
                report("align", 0.7 * frac, message="fitting the body model", force=True)
            elif stage == "regions":
                report("align", 0.8, message="rendering hand and face regions", force=True)
            else:
                report("align", 0.8 + 0.2 * frac, message=f"writing frame {done}/{total}")

        config = PreprocessConfig(max_frames=options.max_frames, max_size=options.max_size,
                                  fitting=options.fit_config())  # fmt: skip
        preprocess_video(video, out, config, model=model, progress=progress, overwrite=True)
        video.unlink(missing_ok=True)  # the dataset holds the frames now

    def _train(self, job: JobRecord, dataset_dir: Path, out: Path, options: JobOptions,
               report: Reporter) -> None:  # fmt: skip
        from eva_engine.avatar import save_avatar
        from eva_engine.avatar.frames import save_avatar_frames
        from eva_engine.data import load_dataset
        from eva_engine.train import preset, train_avatar, with_method

        ds = load_dataset(dataset_dir)
        body = self.body_model(ds.meta.body_model or options.body_model)
        overrides: dict = {"threads": self.config.threads}
        if options.iterations is not None:
            overrides["iterations"] = options.iterations
        if options.image_scale is not None:
            overrides["image_scale"] = options.image_scale
        config = preset(options.preset, **overrides)
        if options.method is not None:
            config = with_method(config, options.method)
        report("train", 0.0, message="setting up training", force=True)

        def progress(p) -> None:
            msg = f"iteration {p.iteration}/{p.total}, {p.num_gaussians} Gaussians"
            if math.isfinite(p.loss):
                msg += f", loss {p.loss:.4f}"
            report("train", 0.95 * p.iteration / max(p.total, 1), eta=p.eta, message=msg)

        result = train_avatar(ds, config, body=body, progress=progress)
        report("train", 0.95, message="measuring the fit on training frames", force=True)
        metrics = _training_metrics(result.avatar, ds)
        info = {
            "avatar_id": job.avatar_id,
            "job_id": job.id,
            "source_video": job.filename,
            "preset": options.preset,
            "options": options.model_dump(),
            "train_config": config.to_dict(),
            "train_seconds": result.train_seconds,
            "iterations": config.iterations,
            "final_loss": result.losses[-1],
            "timings": result.timings,
            "gaussians_per_part": result.gaussians_per_part,
            "metrics": metrics,
            "created_at": time.time(),
        }
        partial = out.with_name(out.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        partial.mkdir(parents=True)
        # Each training frame's pose and camera, so a client can render it to compare with the input.
        info["frames"] = save_avatar_frames(partial, ds)
        save_avatar(result.avatar, partial, info)
        os.replace(partial, out)


def _training_metrics(avatar, ds) -> dict:
    """PSNR / SSIM / LPIPS of the avatar on up to METRIC_FRAMES of its training frames."""
    from eva_engine.eval import evaluate_avatar

    train = list(ds.splits.get("train", []))
    if not train:
        return {}
    step = max(1, math.ceil(len(train) / METRIC_FRAMES))
    ds.splits["fit_check"] = train[::step][:METRIC_FRAMES]
    result = evaluate_avatar(avatar, ds, split="fit_check")
    full = result.regions.get("full")
    out = {"split": "train", "frames": result.num_frames, "render_fps": result.render_fps}
    if full is not None:
        out.update(psnr=full.psnr, ssim=full.ssim, lpips_vgg=full.lpips_vgg, lpips_alex=full.lpips_alex)
    return out


def _is_input_error(err: Exception) -> bool:
    from eva_engine.align import PreprocessError
    from eva_engine.animate import AnimationError, DrivingError
    from eva_engine.avatar import AvatarFileError
    from eva_engine.data import DatasetError, VideoError
    from eva_engine.train import TrainingError

    inputs = (VideoError, PreprocessError, DatasetError, TrainingError, FileNotFoundError, DrivingError,
              AnimationError, AvatarFileError)  # fmt: skip
    return isinstance(err, inputs)


def _reason(err: Exception, stage: str | None) -> str:
    where = f" (stage {stage})" if stage else ""
    if _is_input_error(err):
        return f"{err}{where}"
    return f"internal error{where}: {type(err).__name__}: {err}"


__all__ = ["STAGES", "STAGE_SPANS", "JobCancelled", "Pipeline", "Reporter", "worker_id"]
