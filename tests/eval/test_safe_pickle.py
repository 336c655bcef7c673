"""The restricted unpickler admits numpy arrays in plain containers and nothing else."""

from __future__ import annotations

import os
import pickle

import numpy as np
import pytest

from eval.safe_pickle import UnsafePickleError, load_numpy_pickle, loads_numpy_pickle
from mvgeo.common.errors import InputError


class _RunsCode:
    """Unpickling this calls os.system: the classic pickle exploit."""

    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


class _CallsEval:
    def __reduce__(self):
        return (eval, ("1 + 1",))


# Protocol 2 stores bytes through `_codecs.encode`, which the allow-list refuses; the
# LPIPS file and numpy since 2019 use protocol >= 3.
@pytest.mark.parametrize("protocol", [3, 4, 5])
def test_arrays_in_containers_round_trip(protocol):
    rng = np.random.default_rng(0)
    tree = {"a": {"w": rng.normal(size=(3, 4)).astype(np.float32), "b": np.arange(5)},
            "lst": [np.zeros((2, 2, 2), np.float64), (1, 2.5, "x", None, True)],
            "fortran": np.asfortranarray(rng.normal(size=(3, 5)))}
    out = loads_numpy_pickle(pickle.dumps(tree, protocol=protocol))
    np.testing.assert_array_equal(out["a"]["w"], tree["a"]["w"])
    assert out["a"]["w"].dtype == np.float32
    np.testing.assert_array_equal(out["a"]["b"], tree["a"]["b"])
    np.testing.assert_array_equal(out["lst"][0], tree["lst"][0])
    assert out["lst"][1] == (1, 2.5, "x", None, True)
    np.testing.assert_array_equal(out["fortran"], tree["fortran"])


def test_code_execution_is_refused(tmp_path):
    marker = tmp_path / "pwned"
    data = pickle.dumps({"w": np.ones(3), "evil": _RunsCode(marker)})
    with pytest.raises(UnsafePickleError, match="system"):
        loads_numpy_pickle(data)
    assert not marker.exists()
    # Sanity of the exploit itself: the standard unpickler would have run it.
    pickle.loads(data)
    assert marker.exists()


def test_builtins_eval_is_refused():
    with pytest.raises(UnsafePickleError, match="eval"):
        loads_numpy_pickle(pickle.dumps(_CallsEval()))


def test_other_classes_and_object_arrays_are_refused():
    with pytest.raises(UnsafePickleError):
        loads_numpy_pickle(pickle.dumps({1, 2}))  # a set needs builtins.set
    with pytest.raises(UnsafePickleError):
        loads_numpy_pickle(pickle.dumps(np.array([1, "a"], dtype=object)))


def test_missing_and_corrupt_files(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        load_numpy_pickle(tmp_path / "none.ckpt")
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(b"not a pickle at all")
    with pytest.raises(InputError, match="bad.ckpt"):
        load_numpy_pickle(bad)
