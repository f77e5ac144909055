"""Where the project keeps generated data (body-model caches, datasets, avatars).

One rule, no global state: ``EVA_DATA_DIR`` if set; else ``<repo>/data`` when running from a
source checkout (the Makefile's default); else ``~/.cache/eva``.
"""

from __future__ import annotations

import os
from pathlib import Path

_REPO_ROOT = Path(__file__).resolve().parents[1]


def data_dir() -> Path:
    """The project's data directory (created on demand by callers that write into it)."""
    env = os.environ.get("EVA_DATA_DIR")
    if env:
        return Path(env).expanduser().resolve()
    if (_REPO_ROOT / "pyproject.toml").is_file():
        return _REPO_ROOT / "data"
    return Path.home() / ".cache" / "eva"


def cache_dir(name: str) -> Path:
    """A named cache folder under the data directory, e.g. ``cache_dir("anny")``."""
    return data_dir() / "cache" / name
