"""The ``eva`` Typer application of the engine's commands; they register themselves in sibling
modules. The installed ``eva`` command (``service.cli``) is a second application made the same way
(``new_app``) that holds these commands and the service's."""

import click
import typer
from typer.core import TyperGroup

HELP = "Expressive Gaussian human avatars from monocular RGB video (EVA)."


class CommandsByName(TyperGroup):
    """Lists the commands by name, whichever application registered them."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self.commands)


def new_app() -> typer.Typer:
    """An ``eva`` application without commands: its name, help and settings."""
    return typer.Typer(
        name="eva",
        help=HELP,
        cls=CommandsByName,
        no_args_is_help=True,
        add_completion=False,
        pretty_exceptions_show_locals=False,
    )


app = new_app()
