"""The Makefile's two install levels: ``make demo`` installs what the product needs and no dev
tools; ``make install`` (and so ``make test``) adds them (docs/install.md)."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(shutil.which("make") is None, reason="no make on this machine")


def planned(target: str, venv: Path) -> str:
    """The commands ``make <target>`` would run for a venv that does not exist yet (dry run)."""
    result = subprocess.run(
        ["make", "-n", target, f"VENV={venv}"], cwd=ROOT, capture_output=True, text=True, check=True
    )
    return result.stdout


def test_the_demo_installs_the_product_without_the_dev_tools(tmp_path):
    commands = planned("demo", tmp_path / "venv")
    assert "pip install -q -e .\n" in commands and "eva setup" in commands and "eva demo" in commands
    assert ".[dev]" not in commands


def test_install_and_test_add_the_dev_tools_after_the_runtime(tmp_path):
    for target in ("install", "test"):
        commands = planned(target, tmp_path / "venv")
        runtime, dev = commands.index("pip install -q -e .\n"), commands.index('pip install -q -e ".[dev]"')
        assert runtime < commands.index("eva setup") < dev
