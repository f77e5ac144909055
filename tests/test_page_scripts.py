"""The web page's JavaScript without a browser: Node parses every script in ``service/static``
and runs the quick tests in ``tests/js`` (Node's own test runner). The browser test
(``test_web_page.py``) covers the page as a person uses it."""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NODE = shutil.which("node")
needs_node = pytest.mark.skipif(
    NODE is None, reason="Node.js is not installed (scripts/install-system-deps.sh installs it)"
)


@needs_node
@pytest.mark.parametrize("script", sorted((ROOT / "service" / "static").glob("*.js")), ids=lambda p: p.name)
def test_the_page_scripts_parse(script):
    res = subprocess.run([NODE, "--check", str(script)], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr


@needs_node
def test_the_page_scripts_quick_tests_pass():
    res = subprocess.run(
        [NODE, "--test", str(ROOT / "tests" / "js")], capture_output=True, text=True, timeout=120, cwd=ROOT
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "# fail 0" in res.stdout and "# pass 0" not in res.stdout, res.stdout
