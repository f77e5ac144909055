"""The web page at ``/``: plain HTML, JavaScript and CSS from ``service/static`` (no build step, no
CDN: the service runs offline). The page holds no secret, so it is served without the API key; it
asks for the key when the API answers 401 and sends it with every call.

What the forms offer is written into the page here, from what the API checks, so the two cannot
disagree: the preset and method choices from the engine's registry (``eva_engine.recipes``), the
animation's camera views from ``CAMERA_PRESETS``, and each number field's bounds and default from
the field of the same name of the form's schema (``AvatarForm``, ``AnimationForm``)."""

from __future__ import annotations

import re
from html import escape
from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import HTMLResponse
from pydantic import BaseModel

from eva_engine.recipes import METHODS, PRESETS
from eva_engine.specs.camera import CAMERA_PRESETS
from jobs.options import JobOptions
from service.animation_schemas import AnimationForm
from service.schemas import AvatarForm

STATIC_DIR = Path(__file__).resolve().parent.parent / "static"
PRESET_OPTIONS, METHOD_OPTIONS = "<!-- preset options -->", "<!-- method options -->"
CAMERA_OPTIONS = "<!-- camera options -->"
# Form id in index.html -> the schema its fields are validated with.
FORM_SCHEMAS: dict[str, type[BaseModel]] = {"upload-form": AvatarForm, "animate-form": AnimationForm}
_FORM = re.compile(r'<form id="([\w-]+)".*?</form>', re.S)
_NUMBER_INPUT = re.compile(r'<input [^>]*type="number"[^>]*>')

router = APIRouter(include_in_schema=False)


def select_options(choices: dict[str, str], selected: str | None = None) -> str:
    """``<option>`` elements for ``choices`` (value -> what it is)."""
    return "".join(
        f'<option value="{escape(name)}"{" selected" if name == selected else ""}>'
        f"{escape(name)} ({escape(what)})</option>"
        for name, what in choices.items()
    )


def camera_options() -> str:
    """``<option>`` elements for the animation's camera: every preset view, then the driving
    video's own camera, the form's default selected."""
    views = {name: name.replace("_", " ") for name in CAMERA_PRESETS} | {"driving": "the driving video's"}
    default = AnimationForm.model_fields["camera"].default
    return "".join(
        f'<option value="{escape(name)}"{" selected" if name == default else ""}>{escape(label)}</option>'
        for name, label in views.items()
    )


def _attribute(tag: str, name: str) -> str | None:
    found = re.search(rf'\b{name}="([^"]*)"', tag)
    return found.group(1) if found else None


def number_input(tag: str, schema: type[BaseModel]) -> str:
    """The ``<input type="number">`` ``tag`` with ``min``, ``max`` (and ``placeholder``: the
    default, where there is one) of its field in ``schema``."""
    field = schema.model_fields[_attribute(tag, "name")]
    # HTML's min and max are inclusive and values step from min: an exclusive bound becomes the
    # first step inside it (gt=0.05 with step 0.01: min 0.06).
    step = float(_attribute(tag, "step") or 1)
    attrs = {}
    for bound in field.metadata:  # pydantic's Ge, Gt, Le, Lt constraints
        if getattr(bound, "ge", None) is not None:
            attrs["min"] = bound.ge
        elif getattr(bound, "gt", None) is not None:
            attrs["min"] = round(bound.gt + step, 10)
        elif getattr(bound, "le", None) is not None:
            attrs["max"] = bound.le
        elif getattr(bound, "lt", None) is not None:
            attrs["max"] = round(bound.lt - step, 10)
    if field.default is not None:
        attrs["placeholder"] = field.default
    for name in attrs:
        tag = re.sub(rf'\s{name}="[^"]*"', "", tag)
    return tag[:-1] + "".join(f' {name}="{value:g}"' for name, value in attrs.items()) + ">"


def with_bounds(page: str) -> str:
    """``page`` with every number input of the forms of ``FORM_SCHEMAS`` bounded by its schema."""

    def form(match: re.Match) -> str:
        schema = FORM_SCHEMAS.get(match.group(1))
        if schema is None:  # a form without number fields (the key's)
            return match.group(0)
        return _NUMBER_INPUT.sub(lambda tag: number_input(tag.group(0), schema), match.group(0))

    return _FORM.sub(form, page)


@router.get("/")
def index() -> HTMLResponse:
    page = (STATIC_DIR / "index.html").read_text()
    presets = {name: p.summary for name, p in PRESETS.items()}
    page = page.replace(PRESET_OPTIONS, select_options(presets, JobOptions().preset))
    page = page.replace(METHOD_OPTIONS, select_options({name: m.summary for name, m in METHODS.items()}))
    page = with_bounds(page.replace(CAMERA_OPTIONS, camera_options()))
    headers = {"Cache-Control": "no-cache"}  # a new version of the service shows its new page at once
    return HTMLResponse(page, headers=headers)
