"""The test suite's wall time: ``make test`` (ruff and pytest as CI runs them), timed.

    python -m bench test_suite [--target test] [--name test_suite]
    python -m bench test_suite --fresh-clone      # writes test_suite_fresh_clone.{json,md}

Runs ``make <target>`` from this checkout (its venv and caches as they are), or with
``--fresh-clone`` in a ``git clone`` of its HEAD in an empty folder, timed from the clone on, so
the install (venv, pip, ``eva setup``) is included as a new user has it; reads pytest's summary
line for the counts and pytest's own time. Writes bench/results/<name>.{json,md}; issue 38's goal
is a fresh clone's ``make test`` in 5 minutes of wall time on 2 cores.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

from bench import machine

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"
TARGET_SECONDS = 5 * 60
OUTCOMES = r"(?:passed|failed|errors?|skipped|deselected|xfailed|xpassed|warnings?)"
SUMMARY = re.compile(rf"^=*\s*(?P<counts>\d+ {OUTCOMES}\b.*?) in (?P<seconds>[\d.]+)s")


def pytest_summary(output: str) -> tuple[dict[str, int], float | None]:
    """({"passed": n, "skipped": m, ...}, pytest's seconds) from the last summary line of
    ``output`` (({}, None) without one)."""
    found = [m for m in map(SUMMARY.match, output.splitlines()) if m]
    if not found:
        return {}, None
    last = found[-1]
    counts = {kind: int(n) for n, kind in re.findall(r"(\d+) (\w+)", last["counts"])}
    return counts, float(last["seconds"])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench test_suite", description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", default="test", help="the make target to time (default: test)")
    parser.add_argument("--name", default=None, help="default: test_suite, test_suite_fresh_clone")
    parser.add_argument(
        "--fresh-clone", action="store_true", help="time a git clone of HEAD and make there, install included"
    )
    args = parser.parse_args(argv)
    args.name = args.name or ("test_suite_fresh_clone" if args.fresh_clone else "test_suite")
    load_before = list(os.getloadavg())
    work = Path(tempfile.mkdtemp(prefix="eva-test-suite-")) if args.fresh_clone else None
    env = None  # the checkout runs as the caller's environment has it
    if work is not None:  # the clone stands alone: no venv, data folder or sources of this checkout
        env = {k: v for k, v in os.environ.items() if k not in ("VENV", "EVA_DATA_DIR", "PYTHONPATH")}
    started = time.perf_counter()
    try:
        cwd = ROOT
        if work is not None:
            cwd = work / "eva"
            subprocess.run(["git", "clone", "-q", str(ROOT), str(cwd)], check=True)
        done = subprocess.run(["make", args.target], cwd=cwd, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - started
    finally:
        if work is not None:
            shutil.rmtree(work, ignore_errors=True)
    output = done.stdout + done.stderr
    counts, pytest_seconds = pytest_summary(output)
    doc = {
        **machine.run_header(),
        "target": f"make {args.target}",
        "fresh_clone": args.fresh_clone,
        "exit_code": done.returncode,
        "wall_seconds": round(wall, 1),
        "pytest_seconds": pytest_seconds,
        "counts": counts,
        "load_average_at_start": [round(x, 2) for x in load_before],
        "target_seconds": TARGET_SECONDS,
        "target_met": done.returncode == 0 and wall <= TARGET_SECONDS,
    }
    slowest = [line for line in output.splitlines() if re.match(r"^\d+\.\d+s (call|setup|teardown) ", line)]
    verdict = "met" if doc["target_met"] else "NOT met"
    lines = [
        "# The test suite's wall time",
        "",
        machine.header_line(doc),
        f"- machine: {doc['machine']}",
        (
            f"- `git clone` of HEAD into an empty folder, then `make {args.target}` there (the install "
            "included: venv, pip, `eva setup`)"
            if args.fresh_clone
            else f"- `make {args.target}` from the checkout (venv and caches present)"
        )
        + f", exit code {done.returncode}; load average at start "
        f"{', '.join(map(str, doc['load_average_at_start']))}",
        f"- wall {wall:.1f} s ({int(wall // 60)} min {wall % 60:.1f} s), ruff included; pytest's own "
        f"time {pytest_seconds} s; {', '.join(f'{n} {k}' for k, n in counts.items()) or 'no pytest summary'}",
        f"- target {TARGET_SECONDS} s of wall time: {verdict}",
        "",
        "The slowest steps (pytest's `--durations`):",
        "",
        *[f"    {line}" for line in slowest[:20]],
    ]
    machine.write_result(RESULTS, args.name, doc, lines, show=True)
    if done.returncode != 0:
        print(output[-4000:])
        raise SystemExit(done.returncode)


if __name__ == "__main__":
    main()
