"""The engine's commands of ``eva``: setup, preprocess, train, eval, render, animate, synth.

Each module below registers its commands on :data:`app`; imports stay light at module level so
``eva --help`` starts fast (heavy engine modules are imported inside the commands). The installed
``eva`` command is ``service.cli``, which adds the service's commands (serve, worker, demo).
"""

from eva_engine.cli import animate, evaluate, preprocess, render, setup, synth, train  # noqa: F401
from eva_engine.cli.app import app

__all__ = ["app"]
