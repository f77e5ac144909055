"""The engine is a library first: it imports without the service stack, and the CLI is wired."""

import subprocess
import sys

from typer.testing import CliRunner

from eva_engine.cli import app

BLOCK_SERVICE_STACK = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"fastapi", "uvicorn", "huey", "redis", "starlette", "service", "jobs"}:
            raise ImportError(f"blocked: {name}")
sys.meta_path.insert(0, Block())
import eva_engine, eva_engine.render, eva_engine.body, eva_engine.data, eva_engine.metrics, eva_engine.cli
import eva_engine.avatar, eva_engine.animate, eva_engine.animate.controls, eva_engine.render.view
print("ok")
"""


def test_engine_imports_without_service_stack():
    out = subprocess.run([sys.executable, "-c", BLOCK_SERVICE_STACK], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_cli_lists_commands():
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ("setup", "demo", "render", "animate"):
        assert command in result.output
