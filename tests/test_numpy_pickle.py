"""The numpy-only unpickler: arrays and plain containers load, any other global is refused
before it runs."""

import os
import pickle

import numpy as np
import pytest

from eva_engine.numpy_pickle import UnsafePickleError, load_numpy_pickle


class _RunsCommand:
    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


class _CallsEval:
    def __reduce__(self):
        return (eval, ("1 + 1",))


def test_numpy_pickle_loads_arrays_and_refuses_other_globals(tmp_path):
    good = {"a": {"kernel": np.arange(6, dtype=np.float32).reshape(2, 3)}, "b": [np.zeros(2), 1.5, "x"]}
    loaded = load_numpy_pickle(pickle.dumps(good, protocol=3))
    np.testing.assert_array_equal(loaded["a"]["kernel"], good["a"]["kernel"])
    assert loaded["b"][1:] == [1.5, "x"]

    marker = tmp_path / "pwned"
    malicious = pickle.dumps({"weights": np.zeros(3), "payload": _RunsCommand(f"touch {marker}")})
    assert b"system" in malicious
    path = tmp_path / "evil.ckpt"
    path.write_bytes(malicious)
    for source in (malicious, path):
        with pytest.raises(UnsafePickleError, match="system"):
            load_numpy_pickle(source)
    assert not marker.exists()
    with pytest.raises(UnsafePickleError, match="eval"):
        load_numpy_pickle(pickle.dumps([_CallsEval()]))
    with pytest.raises(UnsafePickleError, match="object-dtype"):
        load_numpy_pickle(pickle.dumps(np.array([1, "a"], dtype=object)))
