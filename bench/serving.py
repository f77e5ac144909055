"""The service under load and under crashes, against real ``eva serve`` / ``eva worker`` processes.

    .venv/bin/python -m bench serving latency --service-dir out/demo/service  # 1 and 16 clients
    .venv/bin/python -m bench serving load --service-dir out/demo/service     # 50 clients + uploads
    .venv/bin/python -m bench serving soak                                    # workers SIGKILLed

``--service-dir``: a service data folder holding a finished avatar (``load`` and ``latency`` copy
it to a temporary folder first; without it, ``eva demo --preset tiny`` makes one).

- ``latency``: clients POST ``/avatars/{id}/render`` with a new pose and camera each time, then
  with a new camera only (the view slider), and time the HTTP round trip: p50/p95 at 256² and
  512², 1 and 16 clients (bench/results/service.{json,md}).
- ``load``: for ``--seconds``, 50 render clients and 2 upload clients (upload a video, then
  cancel the queued job) hit a keyed server with its default limits; clients honour
  ``Retry-After``. Reports p50/p95 per kind, every status, errors (any answer but 200/202, or a
  503 without ``Retry-After``), the server's memory, and ``/healthz`` latency from a separate
  process every 100 ms (target: < 50 ms throughout). bench/results/service_load.{json,md}.
- ``soak``: 20 jobs (18 of the signer, 2 of a video without a person) on 2 workers; every few
  seconds a random worker (or a job's own process) is SIGKILLed and a new worker started. A
  monitor scans /proc every 100 ms for two processes running one job. At the end: every job
  succeeded or failed with a reason, none stuck, none ran twice at once, no orphan files.
  bench/results/service_soak.{json,md}. ``soak --hosts``: the same on several "hosts" that share
  no disk: the queue and the job records in a redis-server, avatars and uploads in an S3 bucket
  (moto's server, a dev dependency), the API and every worker (each replacement too) with a data
  dir of its own. bench/results/service_soak_hosts.{json,md}.

Every process is started by ``service.local_stack.LocalStack``, as the demo and the tests start
them. (This file was ``bench/service.py``, a name that hid the ``service`` package from it.)
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import multiprocessing
import os
import random
import secrets
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from bench.machine import run_header, write_result
from jobs.options import MIN_FRAMES
from jobs.runner import JobProcess, job_processes
from service.local_stack import LocalStack, LocalStackError, eva_executable, free_port, launch, stop_process

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
VERDICT = "every job succeeded or failed with a reason, none stuck, none ran twice at once, no orphan files"
CLIP_FRAMES = MIN_FRAMES  # the shortest clip a job takes: half of it is held out to score the avatar
TINY = {
    "preset": "tiny",
    "iterations": "6",
    "image_scale": "0.25",
    "max_frames": str(CLIP_FRAMES),
    "fit_scale": "0.1",
}


# -- shared ---------------------------------------------------------------------------------------


def render_limits() -> str:
    """The render gate's limits as the server started here reads them (the same environment:
    ``EVA_MAX_RENDERS`` and the like, else the defaults)."""
    from service.settings import ServiceSettings

    s = ServiceSettings()
    at_once = "1 render at a time" if s.max_renders == 1 else f"{s.max_renders} renders at once"
    return f"{at_once}, {s.render_queue} waiting at most {s.render_wait_s:.0f} s"


def quantile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    if len(values) == 1:
        return values[0]
    return statistics.quantiles(values, n=100, method="inclusive")[round(q * 100) - 1]


def rss_mb(pid: int, field: str = "VmRSS") -> float:
    status = Path(f"/proc/{pid}/status").read_text()
    return int(status.split(f"{field}:")[1].split()[0]) / 1024


def ensure_service_dir(service_dir: Path | None, work: Path) -> Path:
    """A copy of ``service_dir`` (or a fresh one from ``eva demo --preset tiny``) under ``work``."""
    if service_dir is None:
        subprocess.run(
            [
                eva_executable(),
                "demo",
                "--out",
                str(work / "demo.png"),
                "--workdir",
                str(work / "demo"),
                "--preset",
                "tiny",
            ],
            check=True,
        )
        service_dir = work / "demo" / "service"
    copy = work / "service"
    shutil.copytree(service_dir, copy, ignore=shutil.ignore_patterns("work"))
    return copy


def serve_only(data: Path, logs: Path, key: str | None = None, env: dict | None = None) -> LocalStack:
    """``eva serve`` alone (no worker) on a free port, answering ``/healthz``; logs in ``logs``."""
    stack = LocalStack(data, logs, api_key=key, env=env)
    stack.start_server()
    try:
        stack.wait_healthy()
    except LocalStackError as err:
        stack.close()
        raise SystemExit(str(err)) from err
    return stack


def ready_avatar(base: str, headers: dict) -> dict:
    import httpx

    avatars = [
        a for a in httpx.get(f"{base}/avatars", headers=headers).json()["avatars"] if a["status"] == "ready"
    ]
    if not avatars:
        raise SystemExit("no finished avatar in the service folder")
    return avatars[-1]


def pose_body(k: int, size: int, fmt: str = "png", vary: str = "pose") -> dict:
    """Request ``k``: a new pose and camera (``vary="pose"``), or the one pose seen by a new
    camera (``"camera"``: what turning the page's view slider sends)."""
    angle = 0.05 * (k % 30)  # radians; jawOpen stays within Anny's [0, 1]
    posed = angle if vary == "pose" else 0.0
    return {
        "format": fmt,
        "pose": {
            "joints": {"upperarm01.L": [0.0, 0.0, -0.6 - posed]},
            "expression": {"jawOpen": posed / 1.5},
        },
        "camera": {"yaw": 10.0 * angle},
        "width": size,
        "height": size,
    }


def write_report(name: str, report: dict, lines: list[str], out: Path) -> None:
    write_result(out, name, report, lines, show=True)


def header(title: str, report: dict, note: str | None) -> list[str]:
    lines = [
        f"# {title}",
        "",
        f"- date: {report['date']}",
        f"- command: `{report['command']}`",
        f"- machine: {report['machine']}",
    ]
    if note:
        lines.append(f"- note: {note}")
    return lines


def base_report(args) -> dict:
    return {
        **run_header(),
        "note": args.note,
    }


# -- latency --------------------------------------------------------------------------------------
def measure_latency(
    base: str,
    avatar_id: str,
    size: int,
    clients: int,
    requests_per_client: int,
    fmt: str = "png",
    vary: str = "pose",
) -> dict:
    import httpx

    latencies: list[float] = []
    errors: list[str] = []
    lock = threading.Lock()

    def client(k: int, api: httpx.Client) -> None:
        for i in range(requests_per_client):
            while True:
                t0 = time.perf_counter()
                body = pose_body(k * requests_per_client + i, size, fmt, vary)
                r = api.post(f"/avatars/{avatar_id}/render", json=body)
                if r.status_code != 503:
                    break
                time.sleep(float(r.headers.get("retry-after", "1")))
            with lock:
                if r.status_code == 200:
                    latencies.append(time.perf_counter() - t0)
                else:
                    errors.append(f"{r.status_code} {r.text[:120]}")

    # The clients are made before the clock starts: an httpx.Client loads a TLS context even for
    # http (~20 ms of CPU each), which sixteen of them spent on the service's two cores inside
    # the timed window, and no request's cost.
    apis = [httpx.Client(base_url=base, timeout=120.0) for _ in range(clients)]
    try:
        threads = [threading.Thread(target=client, args=(k, api)) for k, api in enumerate(apis)]
        started = time.perf_counter()
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        wall = time.perf_counter() - started
    finally:
        for api in apis:
            api.close()
    return {
        "size": size,
        "format": fmt,
        "varies": vary,
        "clients": clients,
        "requests": len(latencies),
        "errors": errors[:5],
        "p50_ms": 1e3 * quantile(latencies, 0.5),
        "p95_ms": 1e3 * quantile(latencies, 0.95),
        "throughput_rps": len(latencies) / wall,
    }


def run_latency(args) -> None:
    work = Path(tempfile.mkdtemp(prefix="eva-bench-latency-"))
    data = ensure_service_dir(args.service_dir, work)
    stack = serve_only(data, work / "logs")
    base = stack.base_url
    try:
        avatar = ready_avatar(base, {})
        measure_latency(base, avatar["avatar_id"], 64, 1, 2)  # load the avatar and warm up
        rows = [
            measure_latency(
                base,
                avatar["avatar_id"],
                size,
                clients,
                max(2, args.requests // max(1, clients // 4)),
                fmt,
                vary,
            )
            for vary in args.vary
            for fmt in args.format
            for size in (256, 512)
            for clients in (1, 16)
        ]
    finally:
        stack.close()
        shutil.rmtree(work, ignore_errors=True)
    report = {
        **base_report(args),
        "avatar": {"num_gaussians": avatar.get("num_gaussians"), "preset": avatar.get("preset")},
        "rows": rows,
    }
    lines = header("Service render latency", report, args.note) + [
        f"- avatar: {avatar.get('num_gaussians')} Gaussians ({avatar.get('preset')} preset); round trip over "
        "loopback HTTP incl. pose JSON validation, skinning, rasterization and the image's encoding; 16 "
        f"clients share the render gate ({render_limits()}; clients wait out 503s as Retry-After says)",
        "",
        "Each request changes the pose and the camera (`pose`), or the camera only (`camera`: the "
        "page's view slider).",
        "",
        "| changes | image | format | clients | requests | p50 ms | p95 ms | requests/s |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['varies']} | {r['size']}² | {r['format']} | {r['clients']} | {r['requests']} "
            f"| {r['p50_ms']:.0f} | {r['p95_ms']:.0f} | {r['throughput_rps']:.1f} |"
        )
    write_report(args.name, report, lines, args.out)


# -- load -----------------------------------------------------------------------------------------
def poll_healthz(base: str, seconds: float, every: float, out) -> None:
    """In its own process: GET /healthz every ``every`` s; sends back [(t, seconds or None)]."""
    import httpx

    samples = []
    with httpx.Client(base_url=base, timeout=10.0) as api:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            t0 = time.perf_counter()
            try:
                ok = api.get("/healthz").status_code == 200
            except httpx.TransportError:
                ok = False
            samples.append((time.monotonic(), time.perf_counter() - t0 if ok else None))
            time.sleep(max(0.0, every - (time.perf_counter() - t0)))
    out.send(samples)


async def load_clients(
    base: str, key: str, avatar_id: str, video: bytes, seconds: float, renders: int, uploads: int, size: int
) -> dict:
    import httpx

    headers = {"X-API-Key": key}
    log: dict[str, list] = {"render": [], "upload": [], "cancel": []}
    errors: list[str] = []
    end = time.monotonic() + seconds

    def note(kind: str, response: httpx.Response | None, elapsed: float, problem: str | None = None) -> float:
        """Record an answer; returns how long the client should wait before its next request."""
        status = response.status_code if response is not None else None
        log[kind].append((status, elapsed))
        if response is None:
            errors.append(f"{kind}: {problem}")
            return 1.0
        if status == 503:
            if "retry-after" not in response.headers:
                errors.append(f"{kind}: 503 without Retry-After")
                return 1.0
            return float(response.headers["retry-after"])
        if status not in (200, 202):
            errors.append(f"{kind}: {status} {response.text[:160]}")
        return 0.0

    async def renderer(api: httpx.AsyncClient, k: int) -> None:
        i = 0
        while time.monotonic() < end:
            t0 = time.perf_counter()
            try:
                r = await api.post(f"/avatars/{avatar_id}/render", json=pose_body(k * 1000 + i, size))
                wait = note("render", r, time.perf_counter() - t0)
            except httpx.TransportError as err:
                wait = note("render", None, time.perf_counter() - t0, repr(err))
            i += 1
            await asyncio.sleep(wait)

    async def uploader(api: httpx.AsyncClient) -> None:
        while time.monotonic() < end:
            t0 = time.perf_counter()
            try:
                r = await api.post("/avatars", files={"video": ("signer.mp4", video, "video/mp4")}, data=TINY)
                wait = note("upload", r, time.perf_counter() - t0)
                if r.status_code == 202:
                    t1 = time.perf_counter()
                    c = await api.delete(f"/jobs/{r.json()['job_id']}")
                    note("cancel", c, time.perf_counter() - t1)
            except httpx.TransportError as err:
                wait = note("upload", None, time.perf_counter() - t0, repr(err))
            await asyncio.sleep(wait)

    limits = httpx.Limits(
        max_connections=renders + uploads + 8, max_keepalive_connections=renders + uploads + 8
    )
    async with httpx.AsyncClient(base_url=base, headers=headers, timeout=120.0, limits=limits) as api:
        await asyncio.gather(
            *[renderer(api, k) for k in range(renders)], *[uploader(api) for _ in range(uploads)]
        )
    return {"log": log, "errors": errors}


def summarise(entries: list[tuple[int | None, float]], ok: int) -> dict:
    good = [t for s, t in entries if s == ok]
    statuses: dict[str, int] = {}
    for s, _ in entries:
        statuses[str(s)] = statuses.get(str(s), 0) + 1
    return {
        "requests": len(entries),
        "statuses": statuses,
        "ok": len(good),
        "p50_ms": 1e3 * quantile(good, 0.5),
        "p95_ms": 1e3 * quantile(good, 0.95),
        "p50_all_ms": 1e3 * quantile([t for _, t in entries], 0.5),
        "p95_all_ms": 1e3 * quantile([t for _, t in entries], 0.95),
    }


@dataclasses.dataclass
class LoadRun:
    """What one load run measured (``drive_load``): the clients' log and errors, ``/healthz``
    samples [(t, seconds or None)], the server's RSS in MB over time [(t, MB)], at the start, end
    and its own peak."""

    avatar: dict
    result: dict
    wall_s: float
    health: list
    memory: list
    rss_start: float
    rss_end: float
    rss_peak: float
    alive: bool
    log_tail: str


def drive_load(args) -> LoadRun:
    """Serve a copy of the avatar folder with a key, load the avatar, then run the render and
    upload clients for ``args.seconds`` while another process polls ``/healthz``."""
    import httpx

    work = Path(tempfile.mkdtemp(prefix="eva-bench-load-"))
    data = ensure_service_dir(args.service_dir, work)
    video = (args.video or _signer_video(work)).read_bytes()
    key = secrets.token_hex(16)
    stack = serve_only(data, work / "logs", key=key)
    base, pid = stack.base_url, stack.server.pid
    memory: list[tuple[float, float]] = []
    sampling = threading.Event()

    def sample_memory() -> None:
        while not sampling.wait(0.5):
            memory.append((time.monotonic(), rss_mb(pid)))

    try:
        avatar = ready_avatar(base, stack.headers)
        httpx.post(
            f"{base}/avatars/{avatar['avatar_id']}/render",
            json=pose_body(0, args.size),
            headers=stack.headers,
            timeout=120,
        ).raise_for_status()  # load it: not in the numbers
        rss_start = rss_mb(pid)
        threading.Thread(target=sample_memory, daemon=True).start()
        receive, send = multiprocessing.Pipe(duplex=False)
        poller = multiprocessing.get_context("spawn").Process(
            target=poll_healthz, args=(base, args.seconds, 0.1, send), daemon=True
        )
        poller.start()
        started = time.monotonic()
        clients = load_clients(
            base, key, avatar["avatar_id"], video, args.seconds, args.clients, args.uploads, args.size
        )
        result = asyncio.run(clients)
        wall = time.monotonic() - started
        health = receive.recv()
        poller.join(30)
        sampling.set()
        rss_end, rss_peak = rss_mb(pid), rss_mb(pid, "VmHWM")
        alive = stack.alive()
    finally:
        stack.close()
        log_tail = (stack.logs / "serve.log").read_text(errors="replace")[-2000:]
        shutil.rmtree(work, ignore_errors=True)
    return LoadRun(avatar, result, wall, health, memory, rss_start, rss_end, rss_peak, alive, log_tail)


def load_report(args, run: LoadRun) -> dict:
    answered = [t for _, t in run.health if t is not None]
    result = run.result
    return {
        **base_report(args),
        "avatar": {"num_gaussians": run.avatar.get("num_gaussians"), "preset": run.avatar.get("preset")},
        "clients": {
            "render": args.clients,
            "upload": args.uploads,
            "size": args.size,
            "seconds": args.seconds,
            "wall_s": run.wall_s,
        },
        "render": summarise(result["log"]["render"], 200),
        "upload": summarise(result["log"]["upload"], 202),
        "cancel": summarise(result["log"]["cancel"], 200),
        "errors": result["errors"][:20],
        "error_count": len(result["errors"]),
        "healthz": {
            "samples": len(run.health),
            "failed": len(run.health) - len(answered),
            "p50_ms": 1e3 * quantile(answered, 0.5),
            "p99_ms": 1e3 * quantile(answered, 0.99),
            "max_ms": 1e3 * max(answered, default=float("nan")),
            "over_50ms": sum(t > 0.05 for t in answered),
        },
        "server_memory_mb": {
            "start": run.rss_start,
            "peak_during": max((m for _, m in run.memory), default=run.rss_start),
            "end": run.rss_end,
            "process_peak": run.rss_peak,
            "every_5s": [round(m) for _, m in run.memory[::10]],
        },
        "server_alive_at_end": run.alive,
        "server_log_tail": run.log_tail if result["errors"] else "",
    }


def load_markdown(report: dict) -> list[str]:
    r, u, h, m = report["render"], report["upload"], report["healthz"], report["server_memory_mb"]
    c, avatar, wall = report["clients"], report["avatar"], report["clients"]["wall_s"]
    met = h["failed"] == 0 and h["max_ms"] < 50
    lines = header("Service under load", report, report["note"]) + [
        f"- load: {c['render']} render clients ({c['size']}², a new pose each time) and "
        f"{c['upload']} upload clients (a {CLIP_FRAMES}-frame signer video, then cancel the queued job) for "
        f"{c['seconds']:.0f} s against `eva serve` with an API key and its limits ({render_limits()}, "
        "2 uploads at once); "
        "clients wait out 503s as `Retry-After` says; `/healthz` polled every 100 ms from another process",
        f"- avatar: {avatar['num_gaussians']} Gaussians ({avatar['preset']} preset)",
        "",
        "| requests | count | answered 200/202 | 503 + Retry-After | p50 ms (ok) | p95 ms (ok) "
        "| p50 ms (all) "
        "| p95 ms (all) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in ("render", "upload", "cancel"):
        s = report[name]
        lines.append(
            f"| {name} | {s['requests']} | {s['ok']} | {s['statuses'].get('503', 0)} | {s['p50_ms']:.0f} "
            f"| {s['p95_ms']:.0f} | {s['p50_all_ms']:.0f} | {s['p95_all_ms']:.0f} |"
        )
    return lines + [
        "",
        f"- renders: {r['ok'] / wall:.1f} per second served; statuses {r['statuses']}; "
        f"uploads {u['statuses']}",
        "- errors (any other answer, a 503 without Retry-After, a failed connection): "
        f"{report['error_count']}" + (f": {report['errors'][:5]}" if report["errors"] else ""),
        f"- `/healthz`: {h['samples']} polls, {h['failed']} failed, p50 {h['p50_ms']:.1f} ms, "
        f"p99 {h['p99_ms']:.1f} ms, "
        f"max {h['max_ms']:.1f} ms, {h['over_50ms']} over 50 ms: target < 50 ms throughout "
        f"{'met' if met else 'NOT met'}",
        f"- server memory (RSS): {m['start']:.0f} MB after loading the avatar, at most "
        f"{m['peak_during']:.0f} MB "
        f"during the load (sampled every 0.5 s), {m['end']:.0f} MB at the end; the process's own peak "
        f"{m['process_peak']:.0f} MB; server alive at the end: {report['server_alive_at_end']}; "
        f"every 5 s: {m['every_5s']}",
    ]


def run_load(args) -> None:
    report = load_report(args, drive_load(args))
    write_report("service_load", report, load_markdown(report), args.out)


def _signer_video(work: Path) -> Path:
    import numpy as np

    from eva_engine.body import load_body_model
    from eva_engine.data import write_video
    from eva_engine.demo import signer_video

    video, frames = signer_video(work / "signer", load_body_model("anny"))
    short = work / f"signer{CLIP_FRAMES}.mp4"
    write_video(short, (frames[:CLIP_FRAMES].numpy() * 255 + 0.5).astype(np.uint8), fps=10)
    return short


# -- soak -----------------------------------------------------------------------------------------
def runs_by_job(processes: dict[int, JobProcess]) -> tuple[dict[str, list[int]], list[int]]:
    """Job id -> pids of its independent runs, and the pids of helpers forked by a job's process."""
    runs: dict[str, list[int]] = {}
    helpers = []
    for pid, p in processes.items():
        if p.forked:
            helpers.append(pid)
        else:
            runs.setdefault(p.job_id, []).append(pid)
    return runs, helpers


class SharedBackends:
    """What hosts that share no disk share (``soak --hosts``): a redis-server (the queue and the job
    records) and an S3 endpoint (moto's server) with one bucket, on loopback ports."""

    BUCKET = "eva-soak"

    def __init__(self, work: Path) -> None:
        import boto3

        self.redis_port, self.s3_port = free_port(), free_port()
        subprocess.run(
            ["redis-server", "--port", str(self.redis_port), "--bind", "127.0.0.1", "--save", ""]
            + ["--appendonly", "no", "--dir", str(work), "--daemonize", "yes"],
            check=True,
        )
        moto = [sys.executable, "-m", "moto.server", "-H", "127.0.0.1", "-p", str(self.s3_port)]
        self.s3 = launch(moto, work / "s3.log")
        self.env = {
            "EVA_QUEUE_URL": f"redis://127.0.0.1:{self.redis_port}/0",
            "EVA_RECORDS_URL": f"redis://127.0.0.1:{self.redis_port}/0",
            "EVA_STORAGE_URL": f"s3://{self.BUCKET}/service",
            "EVA_S3_ENDPOINT_URL": f"http://127.0.0.1:{self.s3_port}",
            "AWS_ACCESS_KEY_ID": "soak",
            "AWS_SECRET_ACCESS_KEY": "soak-secret",
            "AWS_DEFAULT_REGION": "us-east-1",
        }
        self.client = boto3.client(
            "s3",
            endpoint_url=self.env["EVA_S3_ENDPOINT_URL"],
            aws_access_key_id="soak",
            aws_secret_access_key="soak-secret",
            region_name="us-east-1",
        )
        deadline = time.time() + 60
        while True:
            try:
                self.client.create_bucket(Bucket=self.BUCKET)
                break
            except Exception:
                if time.time() > deadline:
                    raise
                time.sleep(0.3)

    def sweep_hosts(self, hosts: list[Path], now: float) -> list[str]:
        """What each host's sweep at its next start removes (``jobs.sweep``): folder paths."""
        from jobs import JobsConfig, open_storage, open_store, sweep

        os.environ.update({k: v for k, v in self.env.items() if k.startswith("AWS_")})
        removed = []
        for host in hosts:
            config = JobsConfig(
                data_dir=host,
                records_url=self.env["EVA_RECORDS_URL"],
                storage_url=self.env["EVA_STORAGE_URL"],
                s3_endpoint_url=self.env["EVA_S3_ENDPOINT_URL"],
            )
            done = sweep(config, open_store(config), open_storage(config), now=now)
            removed += [str(p.relative_to(host.parent)) for p in done.folders]
        return removed

    def keys(self, folder: str) -> list[str]:
        pages = self.client.get_paginator("list_objects_v2").paginate(
            Bucket=self.BUCKET, Prefix=f"service/{folder}/"
        )
        return [item["Key"] for page in pages for item in page.get("Contents", [])]

    def close(self) -> None:
        subprocess.run(["redis-cli", "-p", str(self.redis_port), "shutdown", "nosave"], capture_output=True)
        stop_process(self.s3)


class JobProcessMonitor:
    """Scans /proc every 100 ms from a thread (``jobs.runner.job_processes``): two live processes
    running one job at any moment is a violation. ``seen``: job id -> every pid that ran it;
    ``helpers``: pids a job's own process forked (e.g. ``ldconfig``), which are not second runs."""

    def __init__(self, t_start: float) -> None:
        self.t_start = t_start
        self.violations: list[dict] = []
        self.seen: dict[str, set[int]] = {}
        self.helpers: set[int] = set()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._scan, daemon=True)

    def _scan(self) -> None:
        while not self._stop.wait(0.1):
            processes = job_processes()
            runs, helpers = runs_by_job(processes)
            self.helpers.update(helpers)
            for job_id, pids in runs.items():
                self.seen.setdefault(job_id, set()).update(pids)
                if len(pids) > 1:
                    details = {pid: (processes[pid].parent, processes[pid].command) for pid in pids}
                    self.violations.append(
                        {"t": time.monotonic() - self.t_start, "job": job_id, "pids": details}
                    )

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(5)


@dataclasses.dataclass
class SoakRun:
    """What one soak left (``drive_soak``): the job ids and their final records, the kills and
    worker starts (``events``), the monitor, and the folders to inspect (``work``: every host's
    data dir, ``stack.logs``: the processes' logs)."""

    work: Path
    data: Path
    stack: LocalStack
    shared: SharedBackends | None
    jobs: list[str]
    finals: dict[str, dict]
    events: list[dict]
    monitor: JobProcessMonitor
    wall_s: float


def drive_soak(args) -> SoakRun:
    """Queue ``args.jobs`` jobs, start the workers, and SIGKILL a random worker (replaced) or a
    job's own process every few seconds until ``args.kills`` kills; then wait for every job."""
    import httpx

    from eva_engine.synth.hard import nobody_video

    rng = random.Random(args.seed)
    work = Path(tempfile.mkdtemp(prefix="eva-bench-soak-"))
    data = work / "service"
    shared = SharedBackends(work) if args.hosts else None
    signer = args.video or _signer_video(work)
    nobody = nobody_video(work / "nobody.mp4", frames=CLIP_FRAMES)
    stack = serve_only(data, work / "logs", env=shared.env if shared else None)
    events: list[dict] = []
    t_start = time.monotonic()

    def event(name: str, pid: int, **extra) -> None:
        events.append({"t": time.monotonic() - t_start, "event": name, "pid": pid, **extra})

    def start_worker() -> subprocess.Popen:
        # With --hosts each worker, a replacement too, is a new host: a data dir of its own.
        host = work / f"host-{len(stack.workers):02d}" if shared else None
        proc = stack.start_worker("--threads", "1", data_dir=host)
        event("start worker", proc.pid)
        return proc

    monitor = JobProcessMonitor(t_start)
    monitor.start()
    api = httpx.Client(base_url=stack.base_url, timeout=120)
    jobs: list[str] = []
    try:
        for i in range(args.jobs):
            video = nobody if i in (5, 14) else signer
            options = {**TINY, "iterations": "40" if i % 3 == 0 else "6"}
            with open(video, "rb") as f:
                r = api.post("/avatars", files={"video": (video.name, f, "video/mp4")}, data=options)
            r.raise_for_status()
            jobs.append(r.json()["job_id"])
        for _ in range(args.workers):
            start_worker()

        def unfinished() -> list[dict]:
            states = [api.get(f"/jobs/{j}").json() for j in jobs]
            return [s for s in states if s["state"] not in ("succeeded", "failed", "cancelled")]

        kills, deadline = 0, time.monotonic() + args.deadline
        while unfinished() and time.monotonic() < deadline:
            if kills >= args.kills:
                time.sleep(2.0)
                continue
            time.sleep(rng.uniform(args.kill_min, args.kill_max))
            live = [w for w in stack.workers if w.poll() is None]
            procs = {pids[0]: job for job, pids in runs_by_job(job_processes())[0].items()}
            if procs and rng.random() < 0.25:
                pid = rng.choice(sorted(procs))
                os.kill(pid, signal.SIGKILL)
                event("SIGKILL job process", pid, job=procs[pid])
            elif live:
                victim = rng.choice(live)
                victim.kill()
                victim.wait()
                event("SIGKILL worker", victim.pid)
                time.sleep(rng.uniform(0.0, 3.0))
                start_worker()
            kills += 1
        finals = {j: api.get(f"/jobs/{j}").json() for j in jobs}
    finally:
        for w in stack.workers:
            stop_process(w, signal.SIGINT)
        time.sleep(1.0)
        monitor.stop()
        api.close()
        stack.close()
    return SoakRun(work, data, stack, shared, jobs, finals, events, monitor, time.monotonic() - t_start)


def soak_leftovers(run: SoakRun) -> tuple[dict, list[str]]:
    """What the soak left behind that it should not have, and (``--hosts``) what each killed
    host's sweep removes when it comes back."""
    work, shared, finals = run.work, run.shared, run.finals
    hosts = sorted(p for p in work.iterdir() if p.is_dir() and (p / "jobs").is_dir())  # data dirs
    # A killed host keeps the work folder of the job it was running, on its own disk, until it
    # comes back: its worker sweeps at start. Do that for every host (as if 2 min later).
    swept = shared.sweep_hosts(hosts, now=time.time() + 120) if shared else []
    leftovers = {
        "work_folders": sorted(
            str(p.relative_to(work)) for h in hosts for p in (h / "jobs" / "work").iterdir()
        ),
        "partial_or_trash": sorted(
            str(p.relative_to(work))
            for h in hosts
            for p in h.rglob("*")
            if ".partial" in p.name or p.name.startswith((".deleted-", ".fetch-"))
        ),
        "job_processes_alive": {pid: dataclasses.asdict(p) for pid, p in job_processes().items()},
    }
    succeeded = {j for j, s in finals.items() if s["state"] == "succeeded"}
    if shared:
        leftovers["uploads_in_the_bucket"] = shared.keys("work")
        avatars = sorted({k.split("/")[2] for k in shared.keys("avatars") if k.endswith("/.published")})
        shared.close()
    else:
        avatars = sorted(p.name for p in (run.data / "avatars").iterdir())
    leftovers["avatar_folders_without_a_succeeded_job"] = sorted(
        set(avatars) - {finals[j]["avatar_id"] for j in succeeded}
    )
    leftovers["succeeded_jobs_without_avatar"] = sorted(
        j for j in succeeded if finals[j]["avatar_id"] not in avatars
    )
    return leftovers, swept


def soak_report(args, run: SoakRun) -> dict:
    leftovers, swept = soak_leftovers(run)
    finals = run.finals
    attempts_logged: dict[str, int] = {}
    for log in run.stack.logs.glob("worker*.log"):
        for line in log.read_text(errors="replace").splitlines():
            for j in run.jobs:
                if f"job {j}: attempt" in line:
                    attempts_logged[j] = attempts_logged.get(j, 0) + 1
    report = {
        **base_report(args),
        "setup": {
            "jobs": args.jobs,
            "workers": args.workers,
            "kills": args.kills,
            "seed": args.seed,
            "kill_every_s": [args.kill_min, args.kill_max],
            "hosts": bool(args.hosts),
        },
        "wall_s": run.wall_s,
        "jobs": [
            {
                "job_id": j,
                "state": s["state"],
                "attempts": s["attempts"],
                "error": s["error"],
                "processes_seen": len(run.monitor.seen.get(j, ())),
                "attempts_logged": attempts_logged.get(j, 0),
            }
            for j, s in finals.items()
        ],
        "events": run.events,
        "violations_two_processes_one_job": run.monitor.violations,
        "helper_processes_seen": len(run.monitor.helpers),
        "stuck": [j for j, s in finals.items() if s["state"] in ("queued", "running")],
        "failed_without_reason": [j for j, s in finals.items() if s["state"] == "failed" and not s["error"]],
        "leftovers": leftovers,
    }
    if run.shared:
        report["swept_when_hosts_return"] = swept
    return report


def soak_passed(report: dict) -> bool:
    orphans = sum(len(v) for v in report["leftovers"].values())
    problems = (report["violations_two_processes_one_job"], report["stuck"], report["failed_without_reason"])
    return not any(problems) and orphans == 0


def soak_markdown(report: dict) -> list[str]:
    setup, hosts = report["setup"], report["setup"]["hosts"]
    counts: dict[str, int] = {}
    for row in report["jobs"]:
        counts[row["state"]] = counts.get(row["state"], 0) + 1
    kills_done = [e for e in report["events"] if e["event"].startswith("SIGKILL")]
    orphans = sum(len(v) for v in report["leftovers"].values())
    backends = (
        "Redis queue and job records, an S3 bucket (moto's server) for avatars and uploads, the API and "
        "each worker, replacements too, with a data dir of its own"
        if hosts
        else "SQLite queue and records, one data dir"
    )
    title = (
        "Service soak on several hosts: jobs under worker kills"
        if hosts
        else "Service soak: jobs under worker kills"
    )
    kill_min, kill_max = setup["kill_every_s"]
    lines = header(title, report, report["note"]) + [
        f"- setup: {setup['jobs']} jobs ({setup['jobs'] - 2} of a signer video of {CLIP_FRAMES} frames, "
        f"tiny preset, 6 or 40 iterations; 2 of a video without a person), {setup['workers']} `eva worker` "
        f"processes ({backends}; default limits: 2 crashes of a job's own process, 5 workers lost under a "
        "job, 8 GB per job process); "
        f"{len(kills_done)} SIGKILLs every "
        f"{kill_min:.0f}-{kill_max:.0f} s, each of a random worker (replaced 0-3 s later) or, "
        "one time in four, of a random job's own process",
        f"- wall time {report['wall_s'] / 60:.1f} min; job states: {counts}",
        f"- two processes running one job at once (scanned every 100 ms; a process forked by a job's own "
        "process, e.g. `ldconfig` for `find_library`, is not a second run: "
        f"{report['helper_processes_seen']} seen): {len(report['violations_two_processes_one_job'])}",
        f"- stuck (queued or running at the end): {len(report['stuck'])}; failed without a reason: "
        f"{len(report['failed_without_reason'])}",
        "- orphan files (work folders, partial or deleted folders, avatars without a succeeded job, "
        "succeeded "
        f"jobs without an avatar, job processes alive): {orphans}",
        *(
            [
                f"- work folders that killed hosts kept on their own disks, removed by each host's sweep "
                f"when it starts again (run here for every host, as 2 min later): "
                f"{len(report['swept_when_hosts_return'])}"
            ]
            if hosts
            else []
        ),
        f"- result: {VERDICT if soak_passed(report) else 'FAILED (see the JSON)'}",
        "",
        "| job | state | attempts | job processes seen | error |",
        "|---|---|---:|---:|---|",
    ]
    for row in report["jobs"]:
        lines.append(
            f"| {row['job_id'][:8]} | {row['state']} | {row['attempts']} | {row['processes_seen']} "
            f"| {(row['error'] or '').replace('|', '/')[:150]} |"
        )
    return (
        lines
        + ["", "Kills:", ""]
        + [
            f"- {e['t']:.0f} s: {e['event']} {e['pid']}" + (f" (job {e['job'][:8]})" if "job" in e else "")
            for e in kills_done
        ]
    )


def run_soak(args) -> None:
    run = drive_soak(args)
    report = soak_report(args, run)
    write_report(
        "service_soak_hosts" if run.shared else "service_soak", report, soak_markdown(report), args.out
    )
    if soak_passed(report):
        shutil.rmtree(run.work, ignore_errors=True)
    else:
        print(f"kept the soak's folder and logs: {run.work}")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--note", help="Recorded in the result, e.g. what else shared the machine.")
    sub = parser.add_subparsers(dest="command", required=True)
    latency = sub.add_parser("latency", help="render p50/p95 at 1 and 16 clients")
    latency.add_argument("--service-dir", type=Path)
    latency.add_argument("--requests", type=int, default=20, help="requests per client")
    latency.add_argument("--format", nargs="+", default=["png"], choices=["png", "jpeg"], help="formats")
    latency.add_argument("--name", default="service", help="result file stem")
    latency.add_argument(
        "--vary",
        nargs="+",
        default=["pose", "camera"],
        choices=["pose", "camera"],
        help="what each request changes: the pose and the camera, or the camera only",
    )
    load = sub.add_parser("load", help="50 render clients + uploads; errors, memory, /healthz")
    load.add_argument("--service-dir", type=Path)
    load.add_argument(
        "--video",
        type=Path,
        help=f"the video the upload clients send (default: a {CLIP_FRAMES}-frame signer)",
    )
    load.add_argument("--seconds", type=float, default=60.0)
    load.add_argument("--clients", type=int, default=50)
    load.add_argument("--uploads", type=int, default=2)
    load.add_argument("--size", type=int, default=256)
    soak = sub.add_parser("soak", help="jobs under random SIGKILLs of workers")
    soak.add_argument("--video", type=Path, help="the signer video (default: made here)")
    soak.add_argument("--jobs", type=int, default=20)
    soak.add_argument("--workers", type=int, default=2)
    soak.add_argument("--kills", type=int, default=10)
    soak.add_argument("--kill-min", type=float, default=5.0)
    soak.add_argument("--kill-max", type=float, default=25.0)
    soak.add_argument("--deadline", type=float, default=3600.0, help="seconds")
    soak.add_argument("--seed", type=int, default=0)
    soak.add_argument(
        "--hosts", action="store_true", help="hosts that share no disk: Redis records and an S3 bucket"
    )
    args = parser.parse_args(argv)
    {"latency": run_latency, "load": run_load, "soak": run_soak}[args.command](args)


if __name__ == "__main__":
    main()
