"""The engine is a library first: it imports without the service stack; the ``eva`` command holds
the engine's commands and the service's."""

import subprocess
import sys

import click
import typer
from typer.testing import CliRunner

from eva_engine.cli import app as engine_app
from service.cli import app

BLOCK_SERVICE_STACK = """
import sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {"fastapi", "uvicorn", "huey", "redis", "starlette", "service", "jobs"}:
            raise ImportError(f"blocked: {name}")
sys.meta_path.insert(0, Block())
import eva_engine, eva_engine.render, eva_engine.body, eva_engine.data, eva_engine.metrics, eva_engine.cli
import eva_engine.avatar, eva_engine.animate, eva_engine.animate.controls, eva_engine.render.view
import eva_engine.specs.camera, eva_engine.specs.animation
print("ok")
"""


def test_engine_imports_without_service_stack():
    out = subprocess.run([sys.executable, "-c", BLOCK_SERVICE_STACK], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


ENGINE_COMMANDS = ("animate", "eval", "preprocess", "render", "setup", "synth", "train")
SERVICE_COMMANDS = ("demo", "serve", "worker")


def _commands(application) -> list[str]:
    group = typer.main.get_command(application)
    return group.list_commands(click.Context(group))


def test_cli_lists_commands():
    assert _commands(app) == sorted(ENGINE_COMMANDS + SERVICE_COMMANDS)
    assert _commands(engine_app) == sorted(ENGINE_COMMANDS)
    result = CliRunner().invoke(app, ["--help"])
    assert result.exit_code == 0
    for command in ENGINE_COMMANDS + SERVICE_COMMANDS:
        assert f"│ {command} " in result.output


def test_cli_starts_without_fastapi_or_torch():
    code = "import sys, service.cli; print(sorted({'fastapi', 'torch', 'huey'} & set(sys.modules)))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
