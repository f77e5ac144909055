"""The installed ``eva`` application: the engine's commands (``eva_engine.cli``) and the service's,
which register themselves in sibling modules."""

from eva_engine.cli import app as engine_app
from eva_engine.cli.app import new_app

app = new_app()
app.add_typer(engine_app, name=None)  # no name: its commands join these, not a sub-command group
