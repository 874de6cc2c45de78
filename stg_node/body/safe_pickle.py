"""A pickle reader that rebuilds numpy arrays and plain containers, and nothing else.

SMPL model files and ZJU-MoCap pose files (``new_params/*.npy``, a pickled dict) are pickles;
loading them with plain :mod:`pickle` (or ``np.load(allow_pickle=True)``) would run whatever a
crafted file asks for. :class:`NumpyUnpickler` resolves only the globals numpy uses to rebuild
arrays, dtypes and scalars; :mod:`stg_node.body.smpl_io` extends it for chumpy and scipy.sparse.
"""

from __future__ import annotations

import codecs
import io
import pickle
from pathlib import Path

import numpy as np

_CORE = getattr(np, "_core", None) or np.core
# Builtins that only build plain values (old pickles reduce sets, slices and complex numbers through them).
_SAFE_BUILTINS = {"set", "frozenset", "list", "dict", "tuple", "slice", "complex", "bytearray", "object"}


class NumpyUnpickler(pickle.Unpickler):
    """Unpickler allowing numpy arrays, dtypes and scalars (and Python's own containers)."""

    def find_class(self, module: str, name: str):
        if module in ("numpy.core.multiarray", "numpy._core.multiarray") and name in (
            "_reconstruct",
            "scalar",
        ):
            return getattr(_CORE.multiarray, name)
        if module in ("numpy.core.numeric", "numpy._core.numeric") and name == "_frombuffer":
            return _CORE.numeric._frombuffer
        if module in (
            "numpy",
            "numpy.core.numeric",
            "numpy._core.numeric",
            "numpy.core.multiarray",
            "numpy._core.multiarray",
        ) and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module == "numpy.dtypes" and name.endswith("DType"):
            import numpy.dtypes

            return getattr(numpy.dtypes, name)
        if module in ("__builtin__", "builtins") and name in _SAFE_BUILTINS:
            import builtins

            return getattr(builtins, name)
        if module == "_codecs" and name == "encode":  # bytes in protocol-2 pickles written by Python 3
            return codecs.encode
        raise pickle.UnpicklingError(
            f"refusing to unpickle {module}.{name}: only numpy arrays and plain containers are allowed"
        )


def load_npy(path: str | Path, unpickler: type[pickle.Unpickler] = NumpyUnpickler):
    """Read a ``.npy`` file; an object array (e.g. a saved dict) is unpickled safely.

    Returns the array, or for a 0-d object array (``np.save(path, some_dict)``) the object itself.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, fortran, dtype = np.lib.format.read_array_header_1_0(fh)
        else:
            shape, fortran, dtype = np.lib.format.read_array_header_2_0(fh)
        if not dtype.hasobject:
            fh.seek(0)
            return np.load(fh, allow_pickle=False)
        array = unpickler(io.BytesIO(fh.read()), encoding="latin1").load()
    if isinstance(array, np.ndarray) and array.dtype.hasobject and array.shape == ():
        return array.item()
    return array
