"""The rasterizer's compiled CPU kernels (``csrc/raster.cpp``), built once per machine.

The projection, the tile binning and the tile compositing (forwards and backwards) have two
implementations that follow the same rules: the pure-torch ones in ``projection.py``, ``tiles.py``
and ``composite.py``, which run anywhere, and a small C++/OpenMP torch extension, several times
faster on CPU. ``EVA_RASTER_KERNEL`` (auto | cpp | torch) picks one when ``kernel="auto"``; how
the library is built, cached and chosen is ``eva_engine.native``.
"""

from __future__ import annotations

from pathlib import Path

from eva_engine.native import KERNELS, Kernel, KernelUnavailableError, NativeLibrary

__all__ = ["KERNELS", "KERNEL_ENV", "RASTER", "Kernel", "KernelUnavailableError"]

KERNEL_ENV = "EVA_RASTER_KERNEL"
SOURCE = Path(__file__).resolve().parent / "csrc" / "raster.cpp"
RASTER = NativeLibrary("eva_raster", SOURCE, KERNEL_ENV, "rasterizer")
