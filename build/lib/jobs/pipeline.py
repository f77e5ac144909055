"""One attempt at one job, stage by stage, resumable, run inside the job's own process
(``jobs.runner`` starts it): ``JobRun`` runs the stages of the job's kind (an avatar from a
video, ``jobs.avatar``, or an animation, ``jobs.animation``) and ends the job with their outcome.
A kind (``JobKind``) names its stages with their share of the progress, its options and the
function that runs them; ``jobs.kinds`` registers the kinds. Every stage's result lands in the
job's work folder by an atomic rename, so a process killed at any moment leaves either the
previous stage's result or the next one, and a retry starts after the last completed stage.

Every record write is conditional on this attempt still owning the job (``JobStore`` ``owner=``);
when it does not (recovery gave the job to another worker), the stage stops with ``JobLost`` and
this attempt writes nothing more. Partial results carry the attempt's own suffix, so two
attempts never write into one folder.
"""

from __future__ import annotations

import logging
import math
import re
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import BaseModel

from eva_engine.progress import ProgressEvent
from jobs.config import JobsConfig
from jobs.disk import DiskFull, is_disk_full
from jobs.storage import Storage
from jobs.store import JobLost, JobRecord, JobStore

logger = logging.getLogger("eva.jobs")


@dataclass(frozen=True)
class JobKind:
    """One kind of job.

    name: the record's ``kind``; output_field: the API's name for its output id (``avatar_id``,
    ``animation_id``); stage_spans: stage -> (start, end) of its share of ``progress``, in order,
    covering 0..1; options: the model of the record's ``options``; input_fields: the options'
    fields that name other outputs (an animation's ``avatar_id``); run: ``run(job_run, job,
    report)`` runs (or resumes) the stages, raising on failure."""

    name: str
    output_field: str
    stage_spans: Mapping[str, tuple[float, float]]
    options: type[BaseModel]
    run: Callable[[JobRun, JobRecord, Reporter], None]
    input_fields: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        spans = list(self.stage_spans.values())
        if not spans or spans[0][0] != 0.0 or spans[-1][1] != 1.0:
            raise ValueError(f"job kind {self.name!r}: its stages must cover progress 0..1")
        if any(a[1] != b[0] for a, b in zip(spans, spans[1:], strict=False)):
            raise ValueError(f"job kind {self.name!r}: its stages' spans must follow each other")

    @property
    def stages(self) -> tuple[str, ...]:
        return tuple(self.stage_spans)

    def next_stage(self, completed: str | None) -> str:
        """The stage a retry starts at, after ``completed`` (None: the first)."""
        if completed is None:
            return self.stages[0]
        index = self.stages.index(completed)
        return self.stages[min(index + 1, len(self.stages) - 1)]

    def ids(self, job: JobRecord, options: BaseModel) -> dict[str, str]:
        """The ids a client sees for ``job``: its output's, and the inputs its ``options`` (the
        record's, validated by ``self.options``) name."""
        inputs = {name: getattr(options, name) for name in self.input_fields}
        return {**inputs, self.output_field: job.output_id}


class JobCancelled(Exception):
    """The job was cancelled while running (raised from a progress callback)."""


class Reporter:
    """Turns engine callbacks into job-record updates (throttled) and stops the stage when the
    job was cancelled (``JobCancelled``) or this attempt no longer owns it (``JobLost``).
    spans: stage -> its share of the job's progress (``JobKind.stage_spans``)."""

    def __init__(
        self,
        store: JobStore,
        job: JobRecord,
        worker: str,
        spans: Mapping[str, tuple[float, float]],
        interval: float = 0.5,
    ) -> None:
        self.store, self.job, self.worker, self.interval = store, job, worker, interval
        self.spans = spans
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
    """One attempt at one job of ``kind`` (``jobs.kinds.job_kind(job.kind)``), by ``worker`` (which
    has claimed it), in the job's process."""

    config: JobsConfig
    store: JobStore
    storage: Storage
    job: JobRecord
    worker: str
    kind: JobKind
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
        """Run the stages of the job's kind and end the job with its outcome; returns the final
        state, or None when this attempt lost the job (it then leaves the record and the files
        alone). Raises ``DiskFull`` (leaving the record and the files alone) when the disk is
        full."""
        job = self.job
        if job.kind != self.kind.name:
            raise ValueError(f"job {job.id} is of kind {job.kind!r}, not {self.kind.name!r}")
        report = Reporter(self.store, job, self.worker, self.kind.stage_spans)
        stage = job.completed_stage
        try:
            self.kind.run(self, job, report)
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


__all__ = ["JobCancelled", "JobKind", "JobRun", "Reporter", "failure_reason"]
