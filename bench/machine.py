"""What a benchmark ran on and how: one result header shared by every bench script."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import shlex
import subprocess
import sys
from pathlib import Path


def cpu_name() -> str:
    """The CPU model from /proc/cpuinfo (Linux), else what ``platform`` knows."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown"


def describe() -> str:
    """One line: CPU, cores, torch and its threads, Python, load average (timings are noisy
    when other work shares the machine)."""
    load = ", ".join(f"{x:.1f}" for x in os.getloadavg())
    try:
        import torch  # here, not at the top: first_contact.py runs before torch is installed
    except ImportError:
        runtime = "no torch"
    else:
        runtime = f"torch {torch.__version__} with {torch.get_num_threads()} threads"
    return (
        f"{cpu_name()}, {os.cpu_count()} logical CPUs, {runtime}, Python {platform.python_version()}, "
        f"load average {load}"
    )


def commit(root: Path = Path(__file__).resolve().parents[1]) -> str | None:
    """The commit of the checkout at ``root`` (``+dirty`` with uncommitted changes), None
    outside git."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=root, capture_output=True, text=True
        ).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None
    return head + ("+dirty" if dirty else "")


def portable_path(path: str | Path) -> str:
    """``path`` as a result file should name it: relative to the repository when inside it, as
    ``$EVA_DATA_DIR/...`` when inside the data dir, else unchanged (another machine has neither
    this checkout's absolute path nor its data dir's)."""
    from eva_engine.paths import data_dir  # torch-free, but first_contact.py runs before install

    path = Path(path).resolve()
    repo = Path(__file__).resolve().parents[1]
    if path.is_relative_to(repo):
        return str(path.relative_to(repo))
    data = data_dir().resolve()
    if path.is_relative_to(data):
        return str(Path("$EVA_DATA_DIR") / path.relative_to(data))
    return str(path)


def run_header() -> dict:
    """The head of every result file: when (UTC), the command as typed from the repository
    (``python bench/<script>.py ...``), the commit, and the machine (``describe``)."""
    script = Path(sys.argv[0])
    if script.is_absolute() or script.parent.name == "bench":
        script = Path("bench") / script.name
    return {
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": shlex.join(["python", str(script), *sys.argv[1:]]),
        "commit": commit(),
        "machine": describe(),
    }


def header_line(doc: dict) -> str:
    """The Markdown line a result file opens with, from a ``run_header`` (or an older result's
    date and command, whose commit was not recorded)."""
    return f"- date: {doc['date']}; command: `{doc['command']}`; commit {doc.get('commit') or 'not recorded'}"


def write_result(out: Path, name: str, doc: dict, lines: list[str]) -> None:
    """``<out>/<name>.json`` (``doc``) and ``<out>/<name>.md`` (``lines``), printed too."""
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(doc, indent=1))
    (out / f"{name}.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
