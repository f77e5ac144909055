"""Compiled CPU kernels (small C++/OpenMP torch extensions), built once per machine.

Each ``NativeLibrary`` is one C++ source whose ``TORCH_LIBRARY(<namespace>, m)`` block registers
its ops (``torch.ops.<namespace>``), and has a pure-torch fallback in the package that owns it:
the rasterizer's (``eva_engine/render/native.py``) and the skinning's
(``eva_engine/avatar/skinning.py``). Which implementation runs is a ``kernel`` argument: "cpp"
forces the compiled one (an error if it cannot be built), "torch" the fallback, and "auto" (the
default) reads the library's environment variable (auto | cpp | torch), else uses the compiled
kernels for CPU float32/float64 tensors whenever they load.

Building: ``load()`` compiles the source with ``torch.utils.cpp_extension`` (g++ and ninja,
installed by ``scripts/install-system-deps.sh``; under a minute) into
``cache_dir("torch_extensions")``. ``eva setup`` does it at install time; otherwise the first call
does. The library's name hashes the source, the flags, torch, Python and the CPU, so a changed
source or another machine builds afresh and a stale library is never loaded. A file lock makes
concurrent processes build once; a failed build leaves a marker beside it, so later processes
fall back at once instead of retrying (``load(force=True)`` retries).
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


class KernelUnavailableError(RuntimeError):
    """kernel="cpp" was asked for but the compiled kernels could not be built or loaded."""


def _cflags() -> list[str]:
    # No value-changing math flags (no -ffast-math); without trapping math GCC may if-convert and
    # so vectorise the inner loops.
    flags = ["-O3", "-fopenmp", "-fno-trapping-math", "-fno-math-errno"]
    if platform.machine() in ("x86_64", "AMD64"):
        flags.append("-march=native")  # AVX2/AVX-512 for the inner loops; the name hashes the CPU
    return flags


def _cpu_signature() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line
    except OSError:
        pass
    return platform.processor()


def library_name(source: Path, prefix: str) -> str:
    """``<prefix>_<hash>``: one library per source, flags, torch, Python and CPU."""
    h = hashlib.sha256(source.read_bytes())
    for part in (*_cflags(), torch.__version__, sys.version, platform.machine(), _cpu_signature()):
        h.update(part.encode())
    return f"{prefix}_{h.hexdigest()[:16]}"


def build_library(
    source: Path, root: Path, prefix: str = "eva_native", build: bool = True, force: bool = False
) -> Path | None:
    """Path of the shared library built from ``source`` under ``root``, building it if needed.

    Returns None if it is not built and ``build`` is False. Raises if the build fails (and
    leaves ``<root>/<name>.failed``, which makes later calls raise at once unless ``force``).
    """
    name = library_name(source, prefix)
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

        log.warning("building C++ kernels %s into %s (once per machine, < 1 min)", source.name, folder)
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


class NativeLibrary:
    """One compiled library and the choice between it and its torch fallback.

    namespace: the ``TORCH_LIBRARY`` namespace of ``source`` (the ops are
    ``torch.ops.<namespace>``, and the built library's name starts with it); env: the
    environment variable that picks the kernel when ``kernel="auto"``; what: how messages name it.
    The library loads at most once per process (``state`` says what happened).
    """

    def __init__(self, namespace: str, source: Path, env: str, what: str) -> None:
        self.namespace, self.source, self.env, self.what = namespace, source, env, what
        self._lock = threading.Lock()
        # "ops" -> the loaded namespace; "error" -> why not ("unbuilt": may still build).
        self.state: dict[str, object] = {}

    def load(self, build: bool = True, force: bool = False):
        """The compiled ops (``torch.ops.<namespace>``), or None when they are unavailable.

        build: compile them if this machine has no build yet (else only load an existing one);
        force: retry a build that failed before. The reason for None is in
        ``unavailable_reason()``. Later calls return the same namespace.
        """
        with self._lock:
            state = self.state
            if "ops" in state:
                return state["ops"]
            if "error" in state and not force and not (build and state.get("unbuilt")):
                return None
            state.pop("unbuilt", None)
            try:
                path = build_library(
                    self.source, cache_dir("torch_extensions"), self.namespace, build=build, force=force
                )
            except Exception as err:  # any build failure means: use the torch kernels
                state["error"] = f"{type(err).__name__}: {err}"
                log.warning("compiled %s kernels unavailable, using the torch kernels: %s", self.what, err)
                return None
            if path is None:
                state.update(error="not built yet (eva setup builds it)", unbuilt=True)
                return None
            torch.ops.load_library(str(path))
            state.pop("error", None)
            state["ops"] = getattr(torch.ops, self.namespace)
            return state["ops"]

    def unavailable_reason(self) -> str | None:
        """Why ``load`` returned None (None if it has not failed)."""
        return self.state.get("error")  # type: ignore[return-value]

    def resolve(self, kernel: Kernel, like: torch.Tensor) -> Literal["cpp", "torch"]:
        """Which kernels run for tensors like ``like`` (see the module docstring)."""
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        if kernel == "auto":
            kernel = os.environ.get(self.env, "auto").strip().lower() or "auto"  # type: ignore[assignment]
            if kernel not in KERNELS:
                raise ValueError(f"{self.env} must be one of {KERNELS}, got {kernel!r}")
        if kernel == "torch":
            return "torch"
        supported = like.device.type == "cpu" and like.dtype in (torch.float32, torch.float64)
        if kernel == "cpp":
            if not supported:
                raise KernelUnavailableError(
                    f"the C++ kernels take CPU float32/float64, got {like.dtype} on {like.device}"
                )
            if self.load() is None:
                raise KernelUnavailableError(
                    f"the C++ {self.what} kernels are unavailable: {self.unavailable_reason()}"
                )
            return "cpp"
        return "cpp" if supported and self.load() is not None else "torch"
