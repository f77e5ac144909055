"""Each job in its own process: a worker claims a job, starts ``python -m jobs run JOB_ID`` for it
(``JobRun`` in a child with a memory limit, ``resource.setrlimit``) and watches it, writing the
job's heartbeat meanwhile. A job that runs out of memory or crashes takes down only its own
process: the worker records why and goes on with the next job.

The child dies with its worker (``PR_SET_PDEATHSIG``), so a killed worker never leaves a job
running unsupervised; the worker stops its child when the job was given to another worker
(ownership lost), when a cancel is not honoured within ``CANCEL_GRACE_S``, or after the job's
time limit.

Worker ids are ``host:pidns:pid:start:token``: recovery trusts a same-host pid only in the same
pid namespace (containers) and with the same start time (pids are reused).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from jobs.backends import open_storage, open_store
from jobs.child_env import child_environment
from jobs.config import JobsConfig
from jobs.disk import EXIT_DISK_FULL, DiskFull
from jobs.storage import Storage
from jobs.store import JobRecord, JobStore

logger = logging.getLogger("eva.jobs")

SPEC_ENV = "EVA_JOB_RUNNER_SPEC"
CANCEL_GRACE_S = 30.0


# -- worker ids ---------------------------------------------------------------------------------
def _pid_namespace() -> str:
    try:
        return os.readlink("/proc/self/ns/pid").removeprefix("pid:[").rstrip("]")
    except OSError:
        return ""


def _start_time(pid: int) -> str | None:
    """The process's start time in clock ticks since boot (/proc/<pid>/stat field 22), or None."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None
    return fields[19] if fields[0] != "Z" else None  # a zombie counts as gone


def worker_id() -> str:
    pid = os.getpid()
    return f"{socket.gethostname()}:{_pid_namespace()}:{pid}:{_start_time(pid) or ''}:{uuid.uuid4().hex[:8]}"


@dataclass(frozen=True)
class WorkerId:
    host: str
    pidns: str | None
    pid: int
    start: str | None
    token: str

    @classmethod
    def parse(cls, value: str | None) -> WorkerId | None:
        parts = (value or "").split(":")
        if len(parts) == 5 and parts[2].isdigit():
            return cls(parts[0], parts[1], int(parts[2]), parts[3] or None, parts[4])
        if len(parts) == 3 and parts[1].isdigit():  # older records: host:pid:token
            return cls(parts[0], None, int(parts[1]), None, parts[2])
        return None

    def local(self) -> bool:
        """Whether its pid means something here: same host and pid namespace."""
        same_ns = self.pidns is None or self.pidns == _pid_namespace()
        return self.host == socket.gethostname() and same_ns

    def alive(self) -> bool:
        """Whether that process still runs (only meaningful when ``local``)."""
        started = _start_time(self.pid)
        if started is not None:
            return self.start is None or started == self.start
        try:
            os.kill(self.pid, 0)
        except ProcessLookupError:
            return False
        except PermissionError:
            return True
        return not Path("/proc").is_dir()  # /proc exists but had no entry: gone


# -- the worker's side --------------------------------------------------------------------------
@dataclass
class Crashed:
    """The job's process ended without ending the job (killed, crashed); ``reason`` says how."""

    job: JobRecord
    reason: str


class JobRunner:
    """Claims jobs for one worker and runs each in a child process (see the module docstring)."""

    def __init__(
        self, config: JobsConfig, store: JobStore, storage: Storage, worker: str | None = None
    ) -> None:
        self.config, self.store, self.storage = config, store, storage
        self.worker = worker or worker_id()

    def run(self, job_id: str) -> str | Crashed | None:
        """Claim and run the job. Returns its final state, ``Crashed`` when its process died
        without ending it, or None when it was not ours to run (or was taken from us)."""
        job = self.store.claim(job_id, self.worker)
        if job is None:
            return None
        logger.info("job %s: attempt %d on %s", job.id, job.attempts, self.worker)
        # Without the queue's URL (and its password): the job's process uses the store, not the queue.
        config = self.config.model_copy(update={"queue_url": None}).model_dump(mode="json")
        spec = {"config": config, "worker": self.worker, "parent": os.getpid()}
        try:
            child = subprocess.Popen(
                [sys.executable, "-m", "jobs", "run", job.id],
                env=child_environment(storage=True, **{SPEC_ENV: json.dumps(spec)}),
                stdin=subprocess.DEVNULL,
                start_new_session=True,  # a terminal's Ctrl-C goes to the worker, which decides
            )
        except OSError as err:  # out of processes or memory: the job goes back to the queue
            return Crashed(job, f"the job's process could not start ({err.strerror})")
        ended = self._watch(job, child)
        if ended is not None:
            return ended
        current = self.store.get(job.id)
        if current is None or current.state != "running" or current.worker != self.worker:
            return current.state if current is not None and current.worker == self.worker else None
        return Crashed(current, exit_reason(child.returncode, self.config))

    def _watch(self, job: JobRecord, child: subprocess.Popen) -> str | None:
        """Heartbeat until the child exits; stop it early (and say how the job ended) when the
        job is lost, not cancelled in time, or over its time limit."""
        started = time.monotonic()
        cancel_seen: float | None = None
        while True:
            try:
                child.wait(timeout=self.config.heartbeat_s)
                return None
            except subprocess.TimeoutExpired:
                pass
            try:
                record = self.store.heartbeat(job.id, self.worker)
            except Exception:  # a transient store error must not stop the heartbeat: retried next beat
                logger.warning("job %s: heartbeat failed; retrying", job.id, exc_info=True)
                continue
            if record is None:
                current = self.store.get(job.id)
                if current is not None and current.worker == self.worker and current.finished:
                    child.wait()  # it has just ended the job itself and is exiting
                    return None
                logger.warning(
                    "job %s: taken from %s (it looked dead); stopping its process", job.id, self.worker
                )
                _stop(child)
                return None
            now = time.monotonic()
            if record.cancel_requested:
                cancel_seen = cancel_seen or now
                if now - cancel_seen > CANCEL_GRACE_S:
                    _stop(child)
                    self._end(job, "cancelled", message="cancelled on request (its process was stopped)")
                    return "cancelled"
            if now - started > self.config.job_timeout_s:
                _stop(child)
                limit = _duration(self.config.job_timeout_s)
                self._end(
                    job,
                    "failed",
                    error=f"the job took longer than its limit of {limit} (stage {record.stage})",
                )
                return "failed"

    def _end(self, job: JobRecord, state: str, **fields) -> None:
        if self.store.finish(job.id, state, owner=self.worker, **fields):
            self.storage.remove_work(job.id)


def _duration(seconds: float) -> str:
    return (
        f"{seconds / 3600:.1f} h"
        if seconds >= 7200
        else f"{seconds / 60:.0f} min"
        if seconds >= 120
        else f"{seconds:.0f} s"
    )


def _stop(child: subprocess.Popen, grace: float = 10.0) -> None:
    """SIGTERM, then SIGKILL after ``grace`` seconds (our own child, by its pid)."""
    if child.poll() is not None:
        return
    child.terminate()
    try:
        child.wait(grace)
    except subprocess.TimeoutExpired:
        child.kill()
        child.wait()


def exit_reason(returncode: int, config: JobsConfig) -> str:
    """Why a job's process ended without ending its job, for the job's record."""
    limit = f"{config.job_memory_mb} MB" if config.job_memory_mb else "none"
    if returncode == EXIT_DISK_FULL:
        return "the server's disk was full"
    if returncode < 0:
        sig = signal.Signals(-returncode).name if -returncode in signal.valid_signals() else str(-returncode)
        if -returncode == signal.SIGKILL:
            return f"the job's process was killed (SIGKILL; out of memory? its limit is {limit})"
        return f"the job's process died of {sig} (its memory limit is {limit})"
    return f"the job's process exited with status {returncode} without finishing the job"


# -- the job processes of this machine ----------------------------------------------------------
@dataclass(frozen=True)
class JobProcess:
    """A live process whose command line is a job's (``python -m jobs run JOB_ID``)."""

    job_id: str
    parent: int
    """The parent's pid."""
    command: str
    """The process's name (``/proc/<pid>/comm``)."""
    forked: bool
    """A helper that a process of the same job forked (e.g. ``ctypes.util.find_library`` running
    ``ldconfig``): it shows its parent's command line until it execs."""


def job_processes() -> dict[int, JobProcess]:
    """pid -> the live processes of this machine (from /proc) whose command line is a job's."""
    found: dict[int, tuple[str, int, str]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            args = (entry / "cmdline").read_bytes().split(b"\0")
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            comm = (entry / "comm").read_text().strip()
        except OSError:  # it ended meanwhile
            continue
        for i in range(len(args) - 3):
            if args[i : i + 3] == [b"-m", b"jobs", b"run"] and stat[0] != "Z":
                found[int(entry.name)] = (args[i + 3].decode(), int(stat[1]), comm)
    return {
        pid: JobProcess(job_id, parent, comm, forked=found.get(parent, ("",))[0] == job_id)
        for pid, (job_id, parent, comm) in found.items()
    }


# -- the child's side ---------------------------------------------------------------------------
def _die_with_parent(parent: int) -> None:
    """Linux: SIGKILL this process when the worker that started it dies."""
    try:
        import ctypes

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # it died before prctl took effect
        os._exit(1)


def limit_memory(memory_mb: int | None) -> None:
    """Cap this process's address space: allocations beyond it fail (MemoryError) instead of
    the kernel killing the process, or the machine swapping."""
    if not memory_mb:
        return
    import resource

    limit = memory_mb * 1024 * 1024
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    hard = limit if hard == resource.RLIM_INFINITY else min(hard, limit)
    resource.setrlimit(resource.RLIMIT_AS, (min(limit, hard), hard))


def main(argv: list[str] | None = None) -> int:
    """``python -m jobs run JOB_ID`` with ``EVA_JOB_RUNNER_SPEC`` (set by ``JobRunner``)."""
    argv = sys.argv[1:] if argv is None else argv
    spec = json.loads(os.environ.pop(SPEC_ENV))
    _die_with_parent(spec["parent"])
    config = JobsConfig.model_validate(spec["config"])
    limit_memory(config.job_memory_mb)
    if config.threads:  # the job's process is its own: its torch threads are set once, here
        import torch

        torch.set_num_threads(config.threads)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")
    from jobs.kinds import job_kind
    from jobs.pipeline import JobRun

    store = open_store(config)
    job = store.get(argv[0])
    if job is None or job.state != "running" or job.worker != spec["worker"]:
        return 0  # taken from us before we started
    try:
        JobRun(config, store, open_storage(config), job, spec["worker"], job_kind(job.kind)).execute()
    except DiskFull:  # the worker gives the job back to the queue (exit_reason)
        return EXIT_DISK_FULL
    return 0
