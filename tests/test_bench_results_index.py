"""bench/results/README.md is generated (``bench/results_index.py``): it must match the results
and the docs as committed, so a new result file or a doc that starts quoting one is listed."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_results_index_is_current():
    run = subprocess.run(
        [sys.executable, str(ROOT / "bench" / "results_index.py"), "--check"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 0, run.stderr or run.stdout
