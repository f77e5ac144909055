"""Job kinds: the registry names each kind's stages, options and run function, ``JobRun`` runs
whichever kind it is given (a new kind needs no change to it), and the API's job view takes its
ids from the kind."""

from __future__ import annotations

import subprocess
import sys

import pytest
from pydantic import BaseModel

from eva_engine.progress import ProgressEvent
from jobs import JobKind, JobOptions, JobQueue, JobRun, JobsConfig, job_kind, job_kinds
from jobs.animation import ANIMATION, AnimationOptions
from jobs.avatar import AVATAR
from service.schemas import JobInfo

AVATAR_ID = "9f1c2b7e4a5d4c3b8e7f6a5b4c3d2e1f"


class EchoOptions(BaseModel):
    words: str = "hello"


def echo_stages(run: JobRun, job, report) -> None:
    """A kind of two stages that only reports."""
    report(ProgressEvent("think", 1, 2, "thinking"), force=True)
    report.completed("think")
    report(ProgressEvent("say", 1, 1, EchoOptions.model_validate(job.options).words), force=True)
    report.completed("say")


ECHO = JobKind(
    name="echo",
    output_field="echo_id",
    stage_spans={"think": (0.0, 0.6), "say": (0.6, 1.0)},
    options=EchoOptions,
    run=echo_stages,
)


@pytest.fixture
def queue(tmp_path) -> JobQueue:
    return JobQueue(JobsConfig(data_dir=tmp_path / "data"))


def test_the_registry_holds_each_kind_once_with_its_stages():
    assert job_kinds() == {"avatar": AVATAR, "animation": ANIMATION}
    assert AVATAR.stages == ("preprocess", "align", "train", "export")
    assert ANIMATION.stages == ("preprocess", "align", "render", "export")
    assert job_kind("animation") is ANIMATION
    with pytest.raises(ValueError, match="unknown job kind 'nope'"):
        job_kind("nope")
    # A retry resumes after the last completed stage; the last stage repeats (it is idempotent).
    assert [AVATAR.next_stage(s) for s in (None, "align", "export")] == ["preprocess", "train", "export"]


def test_a_kind_s_stages_cover_the_progress_in_order():
    with pytest.raises(ValueError, match="cover"):
        JobKind("x", "x_id", {"a": (0.0, 0.5)}, EchoOptions, echo_stages)
    with pytest.raises(ValueError, match="follow"):
        JobKind("x", "x_id", {"a": (0.0, 0.5), "b": (0.6, 1.0)}, EchoOptions, echo_stages)


def test_a_new_kind_runs_without_changing_job_run(queue):
    store = queue.store
    job = store.create(EchoOptions(words="hi").model_dump(), kind="echo")
    claimed = store.claim(job.id, "w:1:1:1:t")
    seen = []
    update = store.update

    def spy(job_id, **fields):
        if "stage" in fields:
            seen.append((fields["stage"], round(fields["progress"], 3), fields["message"]))
        return update(job_id, **fields)

    store.update = spy
    assert JobRun(queue.config, store, queue.storage, claimed, claimed.worker, ECHO).execute() == "succeeded"
    assert seen == [("think", 0.3, "thinking"), ("say", 1.0, "hi")]  # each stage's share of the progress
    done = store.get(job.id)
    assert done.completed_stage == "say" and done.message == "echo ready"
    # A run given the wrong kind for its record refuses before doing anything.
    other = store.claim(store.create({}, kind="echo").id, "w:1:1:1:t")
    with pytest.raises(ValueError, match="of kind 'echo', not 'avatar'"):
        JobRun(queue.config, store, queue.storage, other, other.worker, AVATAR).execute()


def test_the_api_shows_each_kind_s_ids(queue):
    store = queue.store
    avatar = store.create(JobOptions().model_dump(), output_id=AVATAR_ID)
    info = JobInfo.of(avatar)
    assert (info.kind, info.avatar_id, info.animation_id) == ("avatar", AVATAR_ID, None)
    animation = store.create(AnimationOptions(avatar_id=AVATAR_ID).model_dump(), kind="animation")
    info = JobInfo.of(animation)
    assert (info.kind, info.avatar_id, info.animation_id) == ("animation", AVATAR_ID, animation.output_id)
    assert isinstance(info.options, AnimationOptions)


def test_the_registry_imports_a_kind_only_when_it_is_asked_for():
    """The probe's process and the worker's parent import ``jobs`` and read kinds (a recovered
    job's next stage, its options) but run none: they must not load torch (the probe's memory
    cap), which a kind's stages import when they run, in the job's own process."""
    code = (
        "import sys, jobs, jobs.queue, jobs.worker; print('torch' in sys.modules); "
        "jobs.job_kind('avatar'); print('torch' in sys.modules); "
        "jobs.job_kinds(); print('torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False", "False"]
