"""What a benchmark ran on and how: one result header shared by every bench script."""

from __future__ import annotations

import datetime as dt
import json
import os
import platform
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

# Version of the result files' layout: a header (``run_header``) beside the script's own body.
# 2: the header carries ``schema`` and the command names the harness (``python -m bench``).
SCHEMA_VERSION = 2


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
    ``$EVA_DATA_DIR/...`` when inside the data dir, ``$TMPDIR/...`` in the scratch folder,
    ``../...`` beside the checkout (the reference videos in ``../shared``), else unchanged
    (another machine has neither this checkout's absolute path nor its data dir's)."""
    from eva_engine.paths import data_dir  # torch-free, but first_contact.py runs before install

    path = Path(path).resolve()
    repo = Path(__file__).resolve().parents[1]
    if path.is_relative_to(repo):
        return str(path.relative_to(repo))
    data = data_dir().resolve()
    if path.is_relative_to(data):
        return str(Path("$EVA_DATA_DIR") / path.relative_to(data))
    scratch = Path(tempfile.gettempdir()).resolve()
    beside = repo.parent
    # Beside the checkout before the scratch folder only for a checkout inside it (CI's clone).
    if (
        beside != Path(beside.anchor)
        and path.is_relative_to(beside)
        and (repo.is_relative_to(scratch) or not path.is_relative_to(scratch))
    ):
        return str(Path("..") / path.relative_to(beside))
    if path.is_relative_to(scratch):
        return str(Path("$TMPDIR") / path.relative_to(scratch))
    return str(path)


def portable_argument(arg: str) -> str:
    """A command-line argument with the path it names (``/abs/path`` or ``--opt=/abs/path``)
    made a ``portable_path``; anything else unchanged."""
    if arg.startswith("/"):
        return portable_path(arg)
    option, eq, value = arg.partition("=")
    if eq and option.startswith("-") and value.startswith("/"):
        return f"{option}={portable_path(value)}"
    return arg


def local_path(name: str) -> Path:
    """The path on this machine that a ``portable_path`` names."""
    from eva_engine.paths import data_dir

    for var, base in (("$EVA_DATA_DIR", data_dir), ("$TMPDIR", lambda: Path(tempfile.gettempdir()))):
        if name == var or name.startswith(var + "/"):
            return base() / name[len(var) :].lstrip("/")
    path = Path(name)
    return path if path.is_absolute() else Path(__file__).resolve().parents[1] / path


def portable(doc):
    """``doc`` (JSON-like) with every absolute path, as a ``Path`` or a string, made a
    ``portable_path``: a result file then names data the same way on every machine."""
    if isinstance(doc, dict):
        return {k: portable(v) for k, v in doc.items()}
    if isinstance(doc, list | tuple):
        return [portable(v) for v in doc]
    if isinstance(doc, Path) or (isinstance(doc, str) and doc.startswith("/") and "\n" not in doc):
        return portable_path(doc)
    return doc


def command_line(argv: list[str] | None = None) -> str:
    """The command as typed from the repository: ``python -m bench <name> ...`` through the
    harness, ``python -m bench.<name> ...`` for a module run alone (``argv``: ``sys.argv``); the
    paths in it as ``portable_path`` names them."""
    argv = sys.argv if argv is None else argv
    args = [portable_argument(a) for a in argv[1:]]  # paths as the result files name them
    if argv[0].startswith("python -m bench "):  # set by the harness (``bench.cli``)
        return shlex.join(["python", "-m", "bench", *argv[0].split()[3:], *args])
    script = Path(argv[0])
    if script.name == "__main__.py" and script.parent.name == "bench":
        return shlex.join(["python", "-m", "bench", *args])
    if script.parent.name == "bench":
        return shlex.join(["python", "-m", f"bench.{script.stem}", *args])
    return shlex.join(["python", portable_path(script), *args])


def run_header() -> dict:
    """The head of every result file: the result schema's version, when (UTC), the command as
    typed from the repository, the commit, and the machine (``describe``)."""
    return {
        "schema": SCHEMA_VERSION,
        "date": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "command": command_line(),
        "commit": commit(),
        "machine": describe(),
    }


def resumable(doc: dict, path: Path) -> dict:
    """``doc``, the result file at ``path`` a benchmark is asked to add its missing runs to, if
    this tree's code made its runs (its ``commit``, ``+dirty`` included, is this checkout's); an
    empty document where there is none. Else ``SystemExit``: resumed, the old runs would be
    reported under this commit's header as if this code had made them."""
    if not doc:
        return {}
    made, now = doc.get("commit"), commit()
    if made is None or made != now:
        raise SystemExit(
            f"{path} holds runs made at {made or 'an unrecorded commit'}, and this checkout is "
            f"{now or 'not a git checkout'}: pass another --name or --out, or remove the file"
        )
    return doc


def header_line(doc: dict) -> str:
    """The Markdown line a result file opens with, from a ``run_header`` (or an older result's
    date and command, whose commit was not recorded)."""
    return f"- date: {doc['date']}; command: `{doc['command']}`; commit {doc.get('commit') or 'not recorded'}"


def write_result(out: Path, name: str, doc: dict, markdown: str | list[str], show: bool = False) -> None:
    """The one writer of results: ``<out>/<name>.json`` (``doc``, which opens with a
    ``run_header``; its paths made ``portable``) and ``<out>/<name>.md`` (``markdown``: text or
    lines); ``show`` prints the Markdown too."""
    if not isinstance(doc, dict):
        raise TypeError(f"a result is a JSON object, not {type(doc).__name__}")
    text = markdown if isinstance(markdown, str) else "\n".join(markdown)
    text = text.rstrip("\n") + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.json").write_text(json.dumps(portable(doc), indent=1, default=str) + "\n")
    (out / f"{name}.md").write_text(text)
    if show:
        print(text, end="")
