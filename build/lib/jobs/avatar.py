"""Avatar jobs: a video becomes a drivable avatar, run in the job's own process by ``JobRun``
under the rules of ``jobs.pipeline`` (results in place by atomic renames, a retry resuming after
the last completed stage, every record write conditional on still owning the job):

    work/<job_id>/input.video   the upload (written by the API, whatever its name was)
    work/<job_id>/dataset/      eva_engine.align.preprocess_video (stages preprocess, align)
    work/<job_id>/avatar/       eva_engine.avatar.save_avatar: with its metrics and frames (stage train)
    avatars/<avatar_id>/        the same folder, renamed (stage export)
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path

from eva_engine.progress import ProgressEvent
from jobs.options import JobOptions
from jobs.pipeline import JobKind, JobRun, Reporter
from jobs.progress import preprocess_progress
from jobs.storage import input_file, move_into_place
from jobs.store import JobRecord

logger = logging.getLogger("eva.jobs")

# Share of the whole job each stage stands for in ``progress`` (measured roughly on CPU).
STAGE_SPANS = {"preprocess": (0.0, 0.25), "align": (0.25, 0.5), "train": (0.5, 0.97), "export": (0.97, 1.0)}
METRIC_FRAMES = 8


def avatar_stages(run: JobRun, job: JobRecord, report: Reporter) -> None:
    """Run (or resume) avatar job ``job`` in ``run`` (its storage, limits and body models)."""
    options = JobOptions.model_validate(job.options)
    if run.storage.avatar_exists(job.output_id):  # published before the last worker died
        return
    work = run.storage.fetch_upload(job.id)
    dataset_dir, trained_dir = work / "dataset", work / "avatar"
    if not trained_dir.is_dir():
        if not dataset_dir.is_dir():
            _preprocess(run, work, dataset_dir, options, report)
        report.completed("align")
        _train(run, job, dataset_dir, trained_dir, options, report)
    report.completed("train")
    report(ProgressEvent("export", message="publishing the avatar"), force=True)  # ownership checked here
    try:
        run.storage.publish(trained_dir, job.output_id)
    except FileExistsError:  # another attempt published the same job's avatar first
        logger.warning("job %s: avatar %s was already published", job.id, job.output_id)
    report.completed("export")


def _preprocess(run: JobRun, work: Path, out: Path, options: JobOptions, report: Reporter) -> None:
    from eva_engine.align import preprocess_video
    from jobs.media import check_frame_budget, probe_video

    video = input_file(work)
    if video is None:
        raise FileNotFoundError("the uploaded video is missing from the job's folder")
    report(ProgressEvent("preprocess", message="checking the video"), force=True)
    # Again here, not only at upload: the budget may have changed, and this is what decodes.
    info = probe_video(video, run.config.max_video_side, decode_first=False)
    check_frame_budget(info, options.max_frames, options.max_size, run.config.max_frame_pixels)
    report(ProgressEvent("preprocess", message="decoding the video"), force=True)
    model = run.body_model(options.body_model)

    progress = preprocess_progress(report)

    # Decoded as what the probe approved: its demuxer (never one FFmpeg guesses) and size limit.
    config = dataclasses.replace(
        options.preprocess_config(info.frame_count()),
        demuxer=info.container,
        max_video_side=run.config.max_video_side,
    )
    partial = out.with_name(f"{out.name}.partial-{run.attempt}")
    preprocess_video(video, partial, config, model=model, progress=progress, overwrite=True)
    report(ProgressEvent("align", 1, 1, "dataset ready"), force=True)  # still ours: put it in place
    move_into_place(partial, out)
    video.unlink(missing_ok=True)  # the dataset holds the frames now


def _train(
    run: JobRun, job: JobRecord, dataset_dir: Path, out: Path, options: JobOptions, report: Reporter
) -> None:
    from eva_engine.avatar import save_avatar
    from eva_engine.data import load_dataset
    from eva_engine.eval import ImageMetrics, quality_report
    from eva_engine.train import train_avatar

    ds = load_dataset(dataset_dir)
    body = run.body_model(ds.meta.body_model or options.body_model)
    config = options.train_config(run.config.max_gaussians, run.config.max_gaussian_std_m)
    report(ProgressEvent("train", message="setting up training"), force=True)

    def progress(event: ProgressEvent) -> None:  # the last 5%: the fit on training frames
        report(event.rescaled("train", 0.0, 0.95))

    result = train_avatar(ds, config, body=body, progress=progress)
    report(ProgressEvent("train", 0.95, 1, "scoring the avatar on unseen frames"), force=True)
    metrics = ImageMetrics()  # its AlexNet serves the training-frame metrics too
    quality = quality_report(result.avatar, ds, metrics)
    record = result.record(
        config,
        preset=options.preset,
        method=options.method,
        options=options.model_dump(),
        metrics=_training_metrics(result.avatar, ds, metrics),
        quality=quality.model_dump(),
        avatar_id=job.output_id,
        job_id=job.id,
        source_video=job.filename,
        created_at=time.time(),
    )
    partial = out.with_name(f"{out.name}.partial-{run.attempt}")
    # Each training frame's pose (as trained) and camera: a client renders one to compare with the input.
    save_avatar(result.avatar, partial, record, frames=result.frames(ds))
    report(ProgressEvent("train", 1, 1, "avatar trained"), force=True)  # still ours: put it in place
    move_into_place(partial, out)


def _training_metrics(avatar, ds, metrics=None) -> dict:
    """PSNR / SSIM / LPIPS-Alex of the avatar on up to METRIC_FRAMES of its training frames
    (``metrics``: an ``ImageMetrics`` whose AlexNet is reused). No LPIPS-VGG, the held-out
    report's score: on training frames it cost 5% of a real job (``bench/results/quality_cost.md``)
    for a number that only says how well the avatar fits what it saw, as PSNR and LPIPS-Alex do."""
    from eva_engine.eval import ImageMetrics, evaluate_avatar

    metrics = ImageMetrics(lpips_alex=metrics.lpips_alex if metrics is not None else None, vgg=False)
    train = list(ds.splits.get("train", []))
    if not train:
        return {}
    step = max(1, math.ceil(len(train) / METRIC_FRAMES))
    ds.splits["fit_check"] = train[::step][:METRIC_FRAMES]
    result = evaluate_avatar(avatar, ds, split="fit_check", metrics=metrics)
    full = result.regions.get("full")
    out = {"split": "train", "frames": result.num_frames, "render_fps": result.render_fps}
    if full is not None:
        out.update(psnr=full.psnr, ssim=full.ssim, lpips_alex=full.lpips_alex)
    return out


AVATAR = JobKind(
    name="avatar", output_field="avatar_id", stage_spans=STAGE_SPANS, options=JobOptions, run=avatar_stages
)
