"""``docs/configuration.md`` from the settings models: every environment variable of
``JobsConfig`` (the queue and the workers) and ``ServiceSettings`` (the API), with its type,
default and bounds. ``python -m service.config_docs > docs/configuration.md`` writes it; a test
checks that the committed file matches."""

from __future__ import annotations

import inspect
import re
import types
import typing

import annotated_types
from pydantic import BaseModel
from pydantic.fields import FieldInfo

from jobs.config import ENV_PREFIX, JobsConfig
from service.settings import ServiceSettings, env_name

BOUNDS = {
    annotated_types.Ge: ("ge", ">="),
    annotated_types.Gt: ("gt", ">"),
    annotated_types.Le: ("le", "<="),
    annotated_types.Lt: ("lt", "<"),
}


def type_name(annotation) -> str:
    """A field's type as a reader would write it: ``int | None``, ``tuple[str, ...]``."""
    if typing.get_origin(annotation) is typing.Annotated:
        return type_name(typing.get_args(annotation)[0])
    if isinstance(annotation, types.UnionType) or typing.get_origin(annotation) is typing.Union:
        return " | ".join(type_name(a) for a in typing.get_args(annotation))
    if annotation is type(None):
        return "None"
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is not None:
        inner = ", ".join("..." if a is Ellipsis else type_name(a) for a in args)
        return f"{origin.__name__}[{inner}]"
    return getattr(annotation, "__name__", str(annotation))


def default_text(field: FieldInfo) -> str:
    if field.default_factory is not None:
        factory = field.default_factory
        return f"`{factory.__module__}.{factory.__qualname__}()`"
    if isinstance(field.default, BaseModel):
        return "its fields' defaults"
    return "none" if field.default is None else f"`{field.default!r}`"


def bounds_text(field: FieldInfo) -> str:
    parts = []
    for m in field.metadata:
        for kind, (attribute, op) in BOUNDS.items():
            if isinstance(m, kind):
                parts.append(f"{op} {getattr(m, attribute)}")
    return ", ".join(parts)


def rows(model: type[BaseModel], prefix: str = ENV_PREFIX, owner: str = "") -> list[str]:
    out = []
    for name, field in model.model_fields.items():
        if isinstance(field.annotation, type) and issubclass(field.annotation, JobsConfig):
            continue  # its own table
        if isinstance(field.annotation, type) and issubclass(field.annotation, BaseModel):
            out += rows(field.annotation, f"{prefix}{name.upper()}__", f"{owner}{name}.")
            continue
        kind = type_name(field.annotation).replace("|", "\\|")  # a pipe ends a table cell
        cells = (f"`{env_name(name, field, prefix)}`", f"`{owner}{name}`", f"`{kind}`")
        out.append("| " + " | ".join((*cells, default_text(field), bounds_text(field))) + " |")
    return out


def section(model: type[BaseModel]) -> str:
    doc = inspect.cleandoc(model.__doc__ or "")
    doc = re.sub(r"(?<!\n)\n(?!\n)", " ", doc)  # one line per paragraph
    table = ["| variable | field | type | default | bounds |", "|---|---|---|---|---|", *rows(model)]
    return f"## `{model.__module__}.{model.__name__}`\n\n{doc}\n\n" + "\n".join(table) + "\n"


def configuration_markdown() -> str:
    head = (
        "# Configuration\n\n"
        "Generated from the settings models by `python -m service.config_docs > docs/configuration.md`"
        " (a test checks it matches them). `eva serve` and `eva worker` read these variables when they"
        " start; their command-line options win over them. Empty values are ignored.\n"
    )
    return head + "\n" + section(JobsConfig) + "\n" + section(ServiceSettings)


if __name__ == "__main__":
    print(configuration_markdown(), end="")
