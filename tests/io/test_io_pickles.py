"""Restricted unpickling of calibration blobs: devkit/plain/numpy pickles load, anything else is refused unrun."""

from __future__ import annotations

import codecs
import os
import pickle
import subprocess
import sys
import types

import numpy as np
import pytest

from nuplan_occ.io.errors import UnsafePickleError
from nuplan_occ.io.pickles import load_calibration_blob


def _devkit_pickle(values, protocol):
    """A pickle of the devkit's Translation(list) class, made without the devkit installed."""
    module = types.ModuleType("nuplan.database.common.data_types")
    cls = type("Translation", (list,), {"__module__": module.__name__})
    module.Translation = cls
    names = ["nuplan", "nuplan.database", "nuplan.database.common", "nuplan.database.common.data_types"]
    saved = {n: sys.modules.get(n) for n in names}
    try:
        for n in names[:-1]:
            sys.modules[n] = types.ModuleType(n)
        sys.modules[names[-1]] = module
        return pickle.dumps(cls(values), protocol=protocol)
    finally:
        for n, m in saved.items():
            if m is None:
                sys.modules.pop(n, None)
            else:
                sys.modules[n] = m


@pytest.mark.parametrize("protocol", [0, 2, 4, 5])
def test_allowed_pickles_load(protocol):
    want = [1.5, -0.25, 2.0]
    for blob in (pickle.dumps(want, protocol=protocol), pickle.dumps(tuple(want), protocol=protocol),
                 pickle.dumps(np.array(want), protocol=protocol), _devkit_pickle(want, protocol)):
        np.testing.assert_array_equal(load_calibration_blob(blob, "x.db"), want)
    K = [[1.0, 0.0, 2.0], [0.0, 1.0, 3.0], [0.0, 0.0, 1.0]]
    assert load_calibration_blob(pickle.dumps(K, protocol=protocol), "x.db").shape == (3, 3)


class _System:
    def __init__(self, command):
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


class _Call:
    def __init__(self, func, *args):
        self.func, self.args = func, args

    def __reduce__(self):
        return (self.func, self.args)


def test_os_system_payload_is_refused_and_not_run(tmp_path):
    marker = tmp_path / "marker"
    blob = pickle.dumps(_System(f"touch {marker}"))
    pickle.loads(pickle.dumps(_System("true")))  # sanity: the payload kind does run under plain pickle
    with pytest.raises(UnsafePickleError, match="refused") as err:
        load_calibration_blob(blob, "evil.db")
    assert err.value.path == "evil.db" and not marker.exists()


@pytest.mark.parametrize("payload", [
    _Call(eval, "1+1"), _Call(getattr, [], "append"), _Call(subprocess.call, ["true"]), _Call(np.load, "x.npy"),
    _Call(np.frombuffer, b"\x00" * 8), _Call(print, "hi"), _Call(codecs.encode, "abc", "rot13"),
])
def test_other_callables_are_refused(payload):
    with pytest.raises(UnsafePickleError):
        load_calibration_blob(pickle.dumps([1.0, payload]), "evil.db")


@pytest.mark.parametrize("blob", [b"", b"\x80\x04garbage", pickle.dumps(["a", "b"]), pickle.dumps({"a": 1}), None])
def test_corrupt_or_non_numeric_blobs(blob):
    with pytest.raises(UnsafePickleError) as err:
        load_calibration_blob(blob, "odd.db")
    assert "odd.db" in str(err.value)
