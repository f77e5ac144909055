"""``python -m bench``: one typer app over the benchmarks.

Each benchmark module keeps its own options (``python -m bench <name> --help``); the app is the
one way in, so that every result's header names the same kind of command. ``report`` and
``index`` regenerate what the docs and ``bench/results/README.md`` quote from the results."""

from __future__ import annotations

import ast
import importlib
import sys
from pathlib import Path

import typer

BENCH = Path(__file__).resolve().parent
HARNESS = "python -m bench"
# Modules that are libraries of the benchmarks, not benchmarks.
LIBRARIES = frozenset(
    {"__init__", "__main__", "cli", "machine", "report", "results_index", "stats", "timing"}
)

app = typer.Typer(
    no_args_is_help=True,
    add_completion=False,
    help="The benchmarks; each writes <name>.{json,md} under bench/results/ with one header.",
)


def benchmarks() -> dict[str, str]:
    """Benchmark name (its module) -> the first paragraph of its docstring, read without
    importing it (most import torch)."""
    found = {}
    for path in sorted(BENCH.glob("*.py")):
        if path.stem in LIBRARIES:
            continue
        doc = ast.get_docstring(ast.parse(path.read_text())) or ""
        found[path.stem] = " ".join(doc.strip().split("\n\n")[0].split()) or path.stem
    return found


def _forward(module: str):
    def run(ctx: typer.Context) -> None:
        # The benchmark's parser names itself after argv[0] ("python -m bench <name>" in its usage
        # line) and the result header reads the command from argv (``machine.command_line``).
        sys.argv = [f"{HARNESS} {module}", *ctx.args]
        importlib.import_module(f"bench.{module}").main(list(ctx.args))

    return run


for _name, _summary in benchmarks().items():
    app.command(
        _name,
        help=_summary,
        context_settings={"allow_extra_args": True, "ignore_unknown_options": True},
        add_help_option=False,  # --help goes to the benchmark's own parser
    )(_forward(_name))


@app.command("report")
def report(
    check: bool = typer.Option(False, "--check", help="exit 1 if a doc's generated table is stale"),
) -> None:
    """Rewrite the tables that README.md and docs/*.md include from bench/results/."""
    from bench import report as report_module

    raise typer.Exit(report_module.run(check=check))


@app.command("index")
def index(
    check: bool = typer.Option(False, "--check", help="exit 1 if the committed index is stale"),
) -> None:
    """Rewrite bench/results/README.md, the index of what each result is and which docs quote it."""
    from bench import results_index

    results_index.main(["--check"] if check else [])
