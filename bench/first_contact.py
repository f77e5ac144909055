"""First contact: a fresh clone's ``make demo``, timed phase by phase.

    python3 -m bench.first_contact          # clones this repository's HEAD into a temp folder

Runs with the system Python (the clone makes its own venv). ``make`` echoes each command as it
starts, so the install's steps are timed from the echoed lines: system packages, the venv, the
pip installs, ``eva setup`` (the Anny cache, the face correspondence, the compiled kernels); the
demo prints its own phases (``time per phase: ...``). Writes bench/results/first_contact.{json,md}.
Packages come from wherever pip finds them on this machine (its index and cache), as for a user.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench import machine

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
TARGET_SECONDS = 3 * 60
"""Issue 38's goal for a fresh clone's ``make demo``, system packages included (8 min before it)."""
# An install step starts at the first echoed line that matches its pattern.
STEPS = (
    ("system packages", re.compile(r"^bash scripts/install-system-deps\.sh")),
    ("venv", re.compile(r"-m venv ")),
    ("pip install", re.compile(r"/pip install -q --upgrade pip")),
    ("eva setup", re.compile(r"/eva setup$")),
    ("demo", re.compile(r"/eva demo ")),
)
DEMO_PHASES = re.compile(r"time per phase: (.*)$")


def run_make(clone: Path, log: Path) -> tuple[list[tuple[float, str]], int]:
    """``make demo`` in ``clone``: every output line with its time since the start, exit code."""
    started = time.perf_counter()
    lines: list[tuple[float, str]] = []
    env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "EVA_DATA_DIR", "PYTHONPATH")}
    env["COLUMNS"] = "400"  # rich would wrap the demo's "time per phase" line at 80 columns
    with log.open("w") as out:
        proc = subprocess.Popen(
            ["make", "demo"], cwd=clone, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
        )
        assert proc.stdout is not None
        for line in proc.stdout:
            t = time.perf_counter() - started
            lines.append((t, line.rstrip("\n")))
            out.write(f"[{t:7.1f} s] {line}")
            out.flush()
        code = proc.wait()
    lines.append((time.perf_counter() - started, ""))
    return lines, code


def step_times(lines: list[tuple[float, str]]) -> dict[str, float]:
    """Seconds per install step and for the demo, from the echoed command lines."""
    starts: list[tuple[str, float]] = []
    for name, pattern in STEPS:
        hit = next((t for t, line in lines if pattern.search(line)), None)
        if hit is not None:
            starts.append((name, hit))
    ends = [t for _, t in starts[1:]] + [lines[-1][0]]
    return {name: round(end - start, 1) for (name, start), end in zip(starts, ends, strict=True)}


def demo_phases(lines: list[tuple[float, str]]) -> dict[str, float]:
    for _, line in lines:
        match = DEMO_PHASES.search(line)
        if match:
            parts = (p.strip().rsplit(" ", 2) for p in match.group(1).split("·"))
            return {name: float(sec) for name, sec, _unit in parts}
    return {}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repo", type=Path, default=ROOT, help="the repository to clone (its HEAD)")
    parser.add_argument("--keep", action="store_true", help="keep the clone")
    parser.add_argument("--name", default="first_contact")
    args = parser.parse_args(argv)

    commit = machine.commit(args.repo)
    work = Path(tempfile.mkdtemp(prefix="eva-first-contact-"))
    clone = work / "eva"
    load_before = os.getloadavg()
    try:
        subprocess.run(["git", "clone", "-q", str(args.repo), str(clone)], check=True)
        lines, code = run_make(clone, work / "make-demo.log")
        shutil.copy(work / "make-demo.log", RESULTS / f"{args.name}.log")
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    total = lines[-1][0]
    steps = step_times(lines)
    install = round(sum(v for k, v in steps.items() if k != "demo"), 1)
    doc = {
        **machine.run_header(),
        "commit": commit,  # the cloned repository's, which --repo may make another than this
        "machine": f"{machine.cpu_name()}, {os.cpu_count()} logical CPUs, Python {platform.python_version()}",
        "load_average_at_start": [round(x, 2) for x in load_before],
        "exit_code": code,
        "total_seconds": round(total, 1),
        "install_seconds": install,
        "steps_seconds": steps,
        "demo_phases_seconds": demo_phases(lines),
        "target_seconds": TARGET_SECONDS,
        "target_met": code == 0 and total <= TARGET_SECONDS,
    }
    (RESULTS / f"{args.name}.json").write_text(json.dumps(doc, indent=1) + "\n")
    rows = "\n".join(f"| {k} | {v:.0f} |" for k, v in steps.items())
    phases = " · ".join(f"{k} {v:.0f} s" for k, v in doc["demo_phases_seconds"].items()) or "n/a"
    verdict = "met" if doc["target_met"] else "NOT met"
    (RESULTS / f"{args.name}.md").write_text(
        f"""# First contact: a fresh clone's `make demo`

- date: {doc["date"]}; command: `{doc["command"]}`; commit {commit}
- machine: {doc["machine"]}; load average at start {", ".join(map(str, doc["load_average_at_start"]))}
- `git clone` into an empty folder, then `make demo` (exit code {code}); the full log with a
  timestamp per line: [{args.name}.log]({args.name}.log)
- total {total:.0f} s (install {install:.0f} s, demo {steps.get("demo", float("nan")):.0f} s);
  target {TARGET_SECONDS} s: {verdict}

| step | seconds |
|---|---:|
{rows}

Demo phases (its own clock): {phases}.
"""
    )
    print((RESULTS / f"{args.name}.md").read_text())
    if code != 0:
        sys.exit(f"make demo failed (exit {code}); see bench/results/{args.name}.log")


if __name__ == "__main__":
    main()
