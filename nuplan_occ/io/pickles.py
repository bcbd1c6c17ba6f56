"""Safe loading of the pickled calibration columns (lidar/camera translation, rotation, intrinsic, distortion).

The devkit stores these as pickles of plain lists or of its own list subclasses.
Loading them with `pickle.loads` would execute any callable a crafted DB names, so a restricted
unpickler resolves only containers, numbers and numpy arrays; every other global is refused before it can
be called.
"""

from __future__ import annotations

import io
import pickle

import numpy as np

from nuplan_occ.io.errors import UnsafePickleError

_DEVKIT_TYPES_MODULE = "nuplan.database.common.data_types"


class _DevkitList(list):
    """Stand-in for the devkit's Translation / Rotation / CameraIntrinsic list subclasses (accepts their state)."""


_ALLOWED: dict[tuple[str, str], object] = {
    ("builtins", "list"): list,
    ("builtins", "tuple"): tuple,
    ("builtins", "float"): float,
    ("builtins", "int"): int,
    ("builtins", "object"): object,
    ("__builtin__", "list"): list,
    ("__builtin__", "tuple"): tuple,
    ("__builtin__", "float"): float,
    ("__builtin__", "int"): int,
    ("__builtin__", "object"): object,
}
_NUMPY_NAMES: dict[tuple[str, str], str] = {
    **{(mod, "_reconstruct"): "_reconstruct" for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(mod, "scalar"): "scalar" for mod in ("numpy.core.multiarray", "numpy._core.multiarray")},
    **{(mod, "_frombuffer"): "_frombuffer" for mod in ("numpy.core.numeric", "numpy._core.numeric")},
    ("numpy", "ndarray"): "ndarray",
    ("numpy", "dtype"): "dtype",
}


def _reconstructor(cls: type, base: type, state: object) -> object:
    """copyreg._reconstructor for protocol 0/1 pickles of list subclasses, limited to allowed classes."""
    if cls not in (_DevkitList, list, tuple) or base not in (list, tuple, object):
        raise pickle.UnpicklingError(f"refused reconstruction of {cls!r} from {base!r}")
    return cls() if state is None else cls(state)


def _latin1_encode(text: str, encoding: str = "utf-8") -> bytes:
    """_codecs.encode as protocol 0-2 pickles use it for numpy's raw bytes; only the latin-1 codec."""
    if not isinstance(text, str) or encoding.lower().replace("_", "-") not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"refused _codecs.encode with codec {encoding!r}")
    return text.encode("latin-1")


class _CalibrationUnpickler(pickle.Unpickler):
    """Resolves only allow-listed globals; anything else raises before being called."""

    def find_class(self, module: str, name: str) -> object:
        if module == _DEVKIT_TYPES_MODULE:
            return _DevkitList
        if (module, name) in _ALLOWED:
            return _ALLOWED[(module, name)]
        if (module, name) in _NUMPY_NAMES:
            return super().find_class(module, name)
        if module in ("copyreg", "copy_reg") and name == "_reconstructor":
            return _reconstructor
        if (module, name) == ("_codecs", "encode"):
            return _latin1_encode
        raise pickle.UnpicklingError(f"refused global {module}.{name}")

    def persistent_load(self, pid: object) -> object:
        raise pickle.UnpicklingError("refused persistent id")


def load_calibration_blob(blob: bytes, source: str) -> np.ndarray:
    """A calibration pickle (translation, quaternion [w,x,y,z], 3x3 K or distortion) as a float64 array.

    source names the DB file (and column) in errors. Raises UnsafePickleError if the pickle references any
    callable or class other than lists, tuples, numbers, numpy arrays and the devkit's list subclasses, or if
    it is corrupt or not numeric; the refused payload is never executed.
    """
    if not isinstance(blob, (bytes, bytearray, memoryview)):
        raise UnsafePickleError(source, f"expected a pickled BLOB, got {type(blob).__name__}")
    try:
        value = _CalibrationUnpickler(io.BytesIO(bytes(blob))).load()
    except pickle.UnpicklingError as exc:
        raise UnsafePickleError(source, f"refused calibration pickle ({exc})") from None
    except Exception as exc:  # noqa: BLE001 - any failure of a corrupt pickle is a format error of this file
        raise UnsafePickleError(source, f"corrupt calibration pickle ({type(exc).__name__}: {exc})") from None
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise UnsafePickleError(source, f"calibration pickle is not a numeric array ({exc})") from None
    return array
