"""What the web page's forms offer, as JSON (``GET /page/options``), built from what the API checks
so the two cannot disagree: the preset and method choices from the engine's registry
(``eva_engine.recipes``), the animation's camera views from ``CAMERA_PRESETS``, each number
field's bounds and default from the form's schema (``AvatarForm``, ``AnimationForm``), and each
field's tooltip from its description there.

The page (``service/static/options.js``) turns a bound into the input's ``min`` / ``max``; an
exclusive bound becomes the first step inside it there, since the step is the page's choice."""

from __future__ import annotations

import types
import typing

from pydantic import BaseModel, Field

from eva_engine.recipes import METHODS, PRESETS
from eva_engine.specs.camera import CAMERA_PRESETS
from jobs.options import JobOptions
from service.animation_schemas import AnimationForm
from service.schemas import AvatarForm


class Choice(BaseModel):
    """One ``<option>``: the value the API takes and what the page shows."""

    value: str
    label: str


class SelectField(BaseModel):
    choices: list[Choice]
    default: str | None = Field(None, description="Selected at first; None: the page's own first option.")


class NumberField(BaseModel):
    """A number field's bounds as the API validates them (None: unbounded on that side)."""

    minimum: float | None = None
    exclusive_minimum: float | None = None
    maximum: float | None = None
    exclusive_maximum: float | None = None
    default: float | None = None


class FormOptions(BaseModel):
    """One form's fields, by the name the API takes."""

    selects: dict[str, SelectField] = Field(default_factory=dict)
    numbers: dict[str, NumberField] = Field(default_factory=dict)
    hints: dict[str, str] = Field(
        default_factory=dict, description="Each field's description in the API's schema, the page's tooltip."
    )


class PageOptions(BaseModel):
    """The page's forms, by the id of their ``<form>`` element."""

    forms: dict[str, FormOptions]


def _is_number(annotation) -> bool:
    """int or float, optionally with None (``int | None``)."""
    if annotation in (int, float):
        return True
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return bool(args) and all(a in (int, float) for a in args)
    return False


_BOUNDS = {"ge": "minimum", "gt": "exclusive_minimum", "le": "maximum", "lt": "exclusive_maximum"}


def number_fields(schema: type[BaseModel]) -> dict[str, NumberField]:
    """Every int or float field of ``schema`` with its pydantic bounds (``Ge``, ``Gt``, ``Le``,
    ``Lt``) and default."""
    out = {}
    for name, field in schema.model_fields.items():
        if not _is_number(field.annotation):
            continue
        bounds = {}
        for constraint in field.metadata:
            for attr, key in _BOUNDS.items():
                if getattr(constraint, attr, None) is not None:
                    bounds[key] = getattr(constraint, attr)
        default = field.default if isinstance(field.default, int | float) else None
        out[name] = NumberField(**bounds, default=default)
    return out


def field_hints(schema: type[BaseModel]) -> dict[str, str]:
    """Every field of ``schema`` that has a description, by name."""
    return {name: field.description for name, field in schema.model_fields.items() if field.description}


def page_options() -> PageOptions:
    presets = [Choice(value=name, label=f"{name} ({p.summary})") for name, p in PRESETS.items()]
    methods = [Choice(value=name, label=f"{name} ({m.summary})") for name, m in METHODS.items()]
    views = {name: name.replace("_", " ") for name in CAMERA_PRESETS} | {"driving": "the driving video's"}
    cameras = [Choice(value=name, label=label) for name, label in views.items()]
    camera_default = AnimationForm.model_fields["camera"].default
    return PageOptions(
        forms={
            "upload-form": FormOptions(
                selects={
                    "preset": SelectField(choices=presets, default=JobOptions().preset),
                    "method": SelectField(choices=methods),
                },
                numbers=number_fields(AvatarForm),
                hints=field_hints(AvatarForm),
            ),
            "animate-form": FormOptions(
                selects={"camera": SelectField(choices=cameras, default=camera_default)},
                numbers=number_fields(AnimationForm),
                hints=field_hints(AnimationForm),
            ),
        }
    )
