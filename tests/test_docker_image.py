"""The container image, checked without a Docker engine (none runs here or in CI): what the build
context holds (``.dockerignore``, matched with Docker's rules), that the image runs as an
unprivileged user from a multi-stage build without dev extras, that every role has a health check
it can pass, that compose caps memory and will not start an open API; and the health check."""

from __future__ import annotations

import re
import time
from pathlib import Path

import pytest
import yaml

from service import healthcheck

ROOT = Path(__file__).resolve().parents[1]


def _pattern_regex(pattern: str) -> re.Pattern:
    """Docker's pattern syntax (Go's filepath.Match plus ``**``): ``*`` and ``?`` stay within one
    path element, ``**`` spans any number of them."""
    out, i = "", 0
    while i < len(pattern):
        if pattern.startswith("**/", i):
            out, i = out + "(?:.*/)?", i + 3
        elif pattern.startswith("**", i):
            out, i = out + ".*", i + 2
        elif pattern[i] == "*":
            out, i = out + "[^/]*", i + 1
        elif pattern[i] == "?":
            out, i = out + "[^/]", i + 1
        else:
            out, i = out + re.escape(pattern[i]), i + 1
    return re.compile(out)


def dockerignore_rules(path: Path = ROOT / ".dockerignore") -> list[tuple[bool, re.Pattern]]:
    rules = []
    for line in path.read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        keep = line.startswith("!")
        pattern = line.lstrip("!").strip().strip("/")
        rules.append((keep, _pattern_regex(pattern)))
    return rules


def in_context(relpath: str, rules) -> bool:
    """Whether Docker sends ``relpath`` to the build: the last rule that matches the path or one
    of its parent folders decides."""
    parts = relpath.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    included = True
    for keep, regex in rules:
        if any(regex.fullmatch(p) for p in prefixes):
            included = keep
    return included


def test_the_build_context_holds_no_data_venv_or_history():
    rules = dockerignore_rules()
    excluded = [
        ".git/HEAD",
        ".venv/.installed",
        ".venv/bin/python",
        "data/service/jobs/jobs.db",
        "data/service/avatars/0123/avatar.ply",
        "data/cache/anny/x.safetensors",
        "out/demo.png",
        "out/demo/service/jobs/work/x/input.mp4",
        "tests/test_service_api.py",
        "bench/results/service.md",
        "eva_engine/__pycache__/paths.cpython-311.pyc",
        "service/__pycache__/app.cpython-311.pyc",
        ".env",
        "docs/evaluation.md",
        "scripts/install-system-deps.sh",
    ]
    for path in excluded:
        assert not in_context(path, rules), path
    # The source tree as a checkout or an unpacked release has it (no git needed).
    needed = [
        p.relative_to(ROOT).as_posix()
        for top in ("eva_engine", "service", "jobs")
        for p in (ROOT / top).rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    ]
    needed += ["pyproject.toml", "Makefile", "README.md"]
    assert len(needed) > 50
    for path in needed:
        assert in_context(path, rules), path


def stages(dockerfile: str) -> list[list[str]]:
    """Instructions per stage (continuation lines joined)."""
    text = re.sub(r"\\\n", " ", dockerfile)
    out: list[list[str]] = []
    for line in text.splitlines():
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        if line.upper().startswith("FROM "):
            out.append([])
        out[-1].append(line)
    return out


def test_the_image_runs_unprivileged_from_a_multi_stage_build():
    dockerfile = (ROOT / "docker" / "Dockerfile").read_text()
    build, final = stages(dockerfile)[0], stages(dockerfile)[-1]
    assert len(stages(dockerfile)) >= 2 and build[0].endswith(" AS build")
    users = [line.split()[1] for line in final if line.upper().startswith("USER ")]
    assert users and users[-1] not in ("root", "0") and not users[-1].startswith("0:"), users
    run = " ".join(line for line in final if "useradd" in line)
    created = re.search(r"useradd .*--uid (\d+).* (\w+)$", run)
    assert created and int(created.group(1)) >= 1000 and created.group(2) == users[-1]
    assert any(line.startswith("COPY --from=build") for line in final)
    assert not any("make install" in line or "[dev]" in line for line in build + final)
    # Every source the build stage copies is in the build context.
    rules = dockerignore_rules()
    for line in build:
        if line.startswith("COPY ") and "--from" not in line:
            for src in line.split()[1:-1]:
                assert in_context(src, rules), src
    health = next(line for line in final if line.startswith("HEALTHCHECK"))
    assert "service.healthcheck" in health  # role-aware: a worker is not sent to /healthz
    env = " ".join(line for line in final if line.startswith("ENV "))
    assert "EVA_HOST=0.0.0.0" in env and f"{healthcheck.HEALTH_FILE_ENV}=" in env


def test_compose_caps_memory_and_needs_a_key():
    compose = yaml.safe_load((ROOT / "docker" / "docker-compose.yml").read_text())
    for name, service in compose["services"].items():
        assert service.get("mem_limit"), name
        assert service.get("healthcheck", {}).get("disable") is not True, name
    api, worker = compose["services"]["api"], compose["services"]["worker"]
    assert re.match(r"\$\{EVA_API_KEY:\?", api["environment"]["EVA_API_KEY"])
    assert all(p.startswith("127.0.0.1:") for p in api["ports"])
    # Redis asks for a password (huey's messages are pickles): every client's URL carries it.
    redis = compose["services"]["redis"]
    assert "--requirepass" in " ".join(redis["command"]) and redis["environment"]["REDISCLI_AUTH"]
    with_password = r"redis://:\$\{EVA_REDIS_PASSWORD:\?[^}]+\}@redis:"
    assert all(re.match(with_password, s["environment"]["EVA_QUEUE_URL"]) for s in (api, worker))
    job_mb = int(re.search(r":-(\d+)", worker["environment"]["EVA_JOB_MEMORY_MB"]).group(1))
    assert job_mb * 2**20 < int(worker["mem_limit"].rstrip("g")) * 2**30  # a job fails before the container


def test_compose_for_several_hosts_shares_only_redis_and_a_bucket():
    hosts = yaml.safe_load((ROOT / "docker" / "docker-compose.hosts.yml").read_text())["services"]
    remote = yaml.safe_load((ROOT / "docker" / "docker-compose.worker-host.yml").read_text())["services"]
    records_user = r"redis://records:\$\{EVA_RECORDS_PASSWORD:\?[^}]+\}@"
    for env in (hosts["api"]["environment"], hosts["worker"]["environment"], remote["worker"]["environment"]):
        assert re.match(records_user, env["EVA_RECORDS_URL"]), env
        assert re.match(r"redis://:\$\{EVA_REDIS_PASSWORD:\?", env["EVA_QUEUE_URL"]), env
        assert env["EVA_STORAGE_URL"].startswith("${EVA_STORAGE_URL:")
        assert re.match(r"\$\{AWS_SECRET_ACCESS_KEY:\?", env["AWS_SECRET_ACCESS_KEY"])
    # The records' Redis user reaches only the records' keys (a job's process holds its password).
    command = " ".join(hosts["redis"]["command"])
    assert '--user records on ">$$EVA_RECORDS_PASSWORD" "~eva:records:*" -@all' in command
    assert all(p.startswith("${EVA_REDIS_BIND:?") for p in hosts["redis"]["ports"])  # no default address
    # The bucket this host can run for itself only comes with its profile; every service is capped.
    assert hosts["minio"]["profiles"] == ["minio"] and hosts["bucket"]["profiles"] == ["minio"]
    assert all(hosts[name].get("mem_limit") for name in ("minio", "bucket")) and remote["worker"]["mem_limit"]
    assert remote["worker"]["volumes"] == ["eva-work:/data/service"]  # its own volume, nothing shared


def test_the_health_check_knows_the_worker_role(tmp_path):
    cmdline = tmp_path / "cmdline"
    cmdline.write_bytes(b"/app/.venv/bin/python\0/app/.venv/bin/eva\0worker\0--workers\0001\0")
    assert healthcheck.container_role(cmdline) == "worker"
    cmdline.write_bytes(b"/app/.venv/bin/python\0/app/.venv/bin/eva\0serve\0")
    assert healthcheck.container_role(cmdline) == "api"
    alive = tmp_path / "alive"
    assert "no health file" in healthcheck.check_worker(alive)
    alive.touch()
    assert healthcheck.check_worker(alive) is None
    old = time.time() - 10 * healthcheck.MAX_AGE_S
    import os

    os.utime(alive, (old, old))
    assert "ago" in healthcheck.check_worker(alive)


def test_a_worker_health_check_without_its_file_says_why(monkeypatch, capsys):
    monkeypatch.delenv(healthcheck.HEALTH_FILE_ENV, raising=False)
    assert healthcheck.main(["--role", "worker"]) == 1
    assert f"{healthcheck.HEALTH_FILE_ENV} is not set" in capsys.readouterr().err


def test_the_api_health_check_reads_the_port_where_the_settings_do(monkeypatch):
    from service.settings import ServiceSettings

    asked = []
    monkeypatch.setattr(healthcheck, "check_api", asked.append)
    monkeypatch.setenv("EVA_PORT", "8123")
    assert healthcheck.main(["--role", "api"]) == 0  # check_api's stand-in reports no problem
    assert asked == [8123] == [ServiceSettings.from_env().port]
    monkeypatch.delenv("EVA_PORT")
    assert healthcheck.main(["--role", "api"]) == 0
    assert asked[-1] == 8000 == ServiceSettings.from_env().port


@pytest.mark.slow
def test_a_worker_keeps_its_health_file_fresh(tmp_path, monkeypatch):
    from helpers.service import EVA, start_process, stop, wait_for

    alive = tmp_path / "alive"
    worker = start_process(
        [EVA, "worker", "--data-dir", str(tmp_path / "data"), "--health-file", str(alive)],
        tmp_path / "worker.log",
    )
    try:
        wait_for(alive.exists, 60, "the health file")
        monkeypatch.delenv(healthcheck.HEALTH_FILE_ENV, raising=False)
        assert healthcheck.main(["--role", "worker"]) == 1  # no variable: no file to check
        monkeypatch.setenv(healthcheck.HEALTH_FILE_ENV, str(alive))
        assert healthcheck.main(["--role", "worker"]) == 0
    finally:
        stop(worker)
    assert not alive.exists()  # removed on a clean stop
