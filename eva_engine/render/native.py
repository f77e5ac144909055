"""The rasterizer's compiled CPU kernels (``csrc/raster.cpp``), built once per machine.

The projection, the tile binning and the tile compositing (forwards and backwards) have two
implementations that follow the same rules: the pure-torch ones in ``projection.py``, ``tiles.py``
and ``composite.py``, which run anywhere, and a small C++/OpenMP torch extension, several times
faster on CPU. Which one runs is
``kernel``: "cpp" forces the compiled one (an error if it cannot be built), "torch" the fallback,
and "auto" (the default) reads ``EVA_RASTER_KERNEL`` (auto | cpp | torch), else uses the compiled
kernels for CPU float32/float64 tensors whenever they load.

Building: ``load_kernels()`` compiles the source with ``torch.utils.cpp_extension`` (g++ and ninja,
installed by ``scripts/install-system-deps.sh``; under a minute) into
``cache_dir("torch_extensions")``. ``eva setup`` does it at install time; otherwise the first
rasterization does. The library's name hashes the source, the flags, torch, Python and the CPU,
so a changed source or another machine builds afresh and a stale library is never loaded. A file
lock makes concurrent processes build once; a failed build leaves a marker beside it, so later
processes fall back at once instead of retrying (``load_kernels(force=True)`` retries).
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import sys
import threading
from pathlib import Path
from typing import Literal

import torch

from eva_engine.paths import cache_dir

log = logging.getLogger(__name__)

Kernel = Literal["auto", "cpp", "torch"]
KERNELS = ("auto", "cpp", "torch")
KERNEL_ENV = "EVA_RASTER_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "raster.cpp"

_lock = threading.Lock()
# Per process: "ops" -> torch.ops.eva_raster once loaded; "error" -> why not ("unbuilt": may build).
_loaded: dict[str, object] = {}


class KernelUnavailableError(RuntimeError):
    """kernel="cpp" was asked for but the compiled kernels could not be built or loaded."""


def _cflags() -> list[str]:
    # No value-changing math flags (no -ffast-math); without trapping math GCC may if-convert and
    # so vectorise the per-pixel loops.
    flags = ["-O3", "-fopenmp", "-fno-trapping-math", "-fno-math-errno"]
    if platform.machine() in ("x86_64", "AMD64"):
        flags.append("-march=native")  # AVX2/AVX-512 for the per-pixel loops; the name hashes the CPU
    return flags


def _cpu_signature() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


def library_name(source: Path = SOURCE) -> str:
    """``eva_raster_<hash>``: one library per source, flags, torch, Python and CPU."""
    h = hashlib.sha256(source.read_bytes())
    for part in (*_cflags(), torch.__version__, sys.version, platform.machine(), _cpu_signature()):
        h.update(part.encode())
    return f"eva_raster_{h.hexdigest()[:16]}"


def load_kernels(build: bool = True, force: bool = False):
    """The compiled kernels (``torch.ops.eva_raster``), or None when they are unavailable.

    build: compile them if this machine has no build yet (else only load an existing one);
    force: retry a build that failed before. The reason for None is in ``unavailable_reason()``.
    Loaded once per process; later calls return the same namespace.
    """
    with _lock:
        if "ops" in _loaded:
            return _loaded["ops"]
        if "error" in _loaded and not force and not (build and _loaded.get("unbuilt")):
            return None
        _loaded.pop("unbuilt", None)
        try:
            path = build_library(SOURCE, cache_dir("torch_extensions"), build=build, force=force)
        except Exception as err:  # any build failure means: use the torch kernels
            _loaded["error"] = f"{type(err).__name__}: {err}"
            log.warning("compiled rasterizer kernels unavailable, using the torch kernels: %s", err)
            return None
        if path is None:
            _loaded.update(error="not built yet (eva setup builds it)", unbuilt=True)
            return None
        torch.ops.load_library(str(path))
        _loaded.pop("error", None)
        _loaded["ops"] = torch.ops.eva_raster
        return _loaded["ops"]


def unavailable_reason() -> str | None:
    """Why ``load_kernels`` returned None (None if it has not failed)."""
    return _loaded.get("error")  # type: ignore[return-value]


def build_library(source: Path, root: Path, build: bool = True, force: bool = False) -> Path | None:
    """Path of the shared library built from ``source`` under ``root``, building it if needed.

    Returns None if it is not built and ``build`` is False. Raises if the build fails (and
    leaves ``<root>/<name>.failed``, which makes later calls raise at once unless ``force``).
    """
    name = library_name(source)
    folder = root / name
    path = folder / f"{name}.so"
    failed = root / f"{name}.failed"
    if path.is_file():
        return path
    if failed.is_file() and not force:
        raise RuntimeError(f"an earlier build failed, see {failed} (eva setup --force retries)")
    if not build:
        return None
    folder.mkdir(parents=True, exist_ok=True)
    with _FileLock(root / f"{name}.lock"):
        if path.is_file():  # another process built it while we waited
            return path
        from torch.utils import cpp_extension

        log.warning("building the rasterizer's C++ kernels into %s (once per machine, < 1 min)", folder)
        try:
            # is_python_module=False: a plain library whose TORCH_LIBRARY block registers the ops;
            # the caller loads it with torch.ops.load_library.
            cpp_extension.load(
                name=name,
                sources=[str(source)],
                extra_cflags=_cflags(),
                extra_ldflags=["-fopenmp"],
                build_directory=str(folder),
                is_python_module=False,
                verbose=False,
            )
        except Exception as err:
            failed.write_text(f"{type(err).__name__}: {err}\n")
            raise
        failed.unlink(missing_ok=True)
    return path


class _FileLock:
    """An exclusive advisory lock on a file (fcntl; a no-op where fcntl does not exist)."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        self.fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            import fcntl

            fcntl.flock(self.fd, fcntl.LOCK_EX)
        except ImportError:
            pass
        return self

    def __exit__(self, *exc):
        os.close(self.fd)  # closing releases the lock


def resolve_kernel(kernel: Kernel, like: torch.Tensor) -> Literal["cpp", "torch"]:
    """Which kernels run for tensors like ``like`` (see the module docstring)."""
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
    if kernel == "auto":
        kernel = os.environ.get(KERNEL_ENV, "auto").strip().lower() or "auto"  # type: ignore[assignment]
        if kernel not in KERNELS:
            raise ValueError(f"{KERNEL_ENV} must be one of {KERNELS}, got {kernel!r}")
    if kernel == "torch":
        return "torch"
    supported = like.device.type == "cpu" and like.dtype in (torch.float32, torch.float64)
    if kernel == "cpp":
        if not supported:
            raise KernelUnavailableError(
                f"the C++ kernels take CPU float32/float64, got {like.dtype} on {like.device}"
            )
        if load_kernels() is None:
            raise KernelUnavailableError(
                f"the C++ rasterizer kernels are unavailable: {unavailable_reason()}"
            )
        return "cpp"
    return "cpp" if supported and load_kernels() is not None else "torch"
