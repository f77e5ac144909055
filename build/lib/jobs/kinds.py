"""The job kinds the queue runs, by name (``JobKind``): a new kind is one module that defines its
``JobKind``, named here. A kind's module is imported when the kind is first asked for, and loads
no torch until its stages run (in the job's own process): neither ``python -m jobs probe`` nor
the worker's parent process should pay for it."""

from __future__ import annotations

import importlib

from jobs.pipeline import JobKind

KIND_MODULES: dict[str, tuple[str, str]] = {
    "avatar": ("jobs.avatar", "AVATAR"),
    "animation": ("jobs.animation", "ANIMATION"),
}
"""Kind name -> (module, attribute) of its ``JobKind``."""


def job_kind(name: str) -> JobKind:
    """The kind called ``name``; ValueError for an unknown one."""
    if name not in KIND_MODULES:
        raise ValueError(f"unknown job kind {name!r}; choose one of {sorted(KIND_MODULES)}")
    module, attribute = KIND_MODULES[name]
    kind = getattr(importlib.import_module(module), attribute)
    if kind.name != name:
        raise ValueError(f"{module}.{attribute} is the kind {kind.name!r}, not {name!r}")
    return kind


def job_kinds() -> dict[str, JobKind]:
    """Every kind by name (imports all their modules)."""
    return {name: job_kind(name) for name in KIND_MODULES}


__all__ = ["KIND_MODULES", "JobKind", "job_kind", "job_kinds"]
