"""``eva``, the installed command: the engine's commands (setup, preprocess, train, eval, render,
animate, synth) and the service's: ``serve`` (the REST API), ``worker`` (the job queue's consumer)
and ``demo`` (the whole product end to end).

Imports stay light at module level, as in ``eva_engine.cli``, so ``eva --help`` starts fast.
"""

from service.cli import demo, serve, worker  # noqa: F401
from service.cli.app import app

__all__ = ["app"]
