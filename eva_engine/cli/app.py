"""The ``eva`` Typer application object; commands register themselves in sibling modules."""

import typer

app = typer.Typer(
    name="eva",
    help="Expressive Gaussian human avatars from monocular RGB video (EVA).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)
