"""``eva``: the single command-line entry point.

Each module below registers its commands on :data:`app`; imports stay light at module level so
``eva --help`` starts fast (heavy engine modules are imported inside the commands).
"""

from eva_engine.cli import animate, demo, evaluate, preprocess, render, serve, setup, synth, train, worker  # noqa: F401
from eva_engine.cli.app import app

__all__ = ["app"]
