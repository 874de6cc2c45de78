"""The one way stg_node reads files a user brings: nothing in such a file can run code.

Every reader of a user's file (datasets' ``annots.npy`` and ``new_params/*.npy``, SMPL model
``.pkl``/``.npz``, THuman4.0 and folder-format ``.npz``, LPIPS weights, checkpoints, launch files,
recorded messages) goes through one of these:

- pickles: :class:`SafeUnpickler` rebuilds numpy arrays, dtypes and scalars and Python's plain
  containers, and refuses every other global with :class:`RefusedPickleError` (a
  :class:`pickle.UnpicklingError`); a format that needs a few more harmless classes (SMPL's
  chumpy values and scipy-sparse matrices) subclasses it and widens ``find_class``. Never
  ``pickle.load`` or ``np.load(allow_pickle=True)``: a pickle's ``__reduce__`` can name
  ``os.system`` and numpy would call it.
- ``.npy`` (:func:`load_npy`): ``np.load(allow_pickle=False)`` first; only an object array (a
  dict saved with ``np.save``) is read by hand: the header through ``numpy.lib.format``, the
  payload through the safe unpickler.
- ``.npz`` (:func:`load_npz`): every member with ``allow_pickle=False``; a member holding pickled
  objects is refused, or, where the caller passes an unpickler, read like an object ``.npy``.
- torch files (:func:`load_torch`): ``torch.load(weights_only=True)`` (torch's own allow-list).
- YAML (:func:`load_yaml`): ``yaml.safe_load`` (no Python tags).
- msgpack (:data:`unpack_msgpack`): extension types refused (``ExtType`` would otherwise come
  through as an opaque object; msgpack's built-in timestamp extension decodes to a plain
  ``msgpack.Timestamp`` value, which no header field accepts).

docs/SECURITY.md says what is trusted and what is not.
"""

from __future__ import annotations

import builtins
import codecs
import collections
import functools
import io
import pickle
import zipfile
import zlib
from pathlib import Path
from typing import Any, BinaryIO

import msgpack
import numpy as np

_CORE = getattr(np, "_core", None) or np.core
# Builtins that only build plain values (old pickles reduce sets, slices and complex numbers through them).
_SAFE_BUILTINS = frozenset(
    {"set", "frozenset", "list", "dict", "tuple", "slice", "complex", "bytearray", "object"}
)
_NUMPY_MULTIARRAY = ("numpy.core.multiarray", "numpy._core.multiarray")
_NUMPY_NUMERIC = ("numpy.core.numeric", "numpy._core.numeric")
NPY_MAGIC = b"\x93NUMPY"


class UnreadableFileError(ValueError):
    """A file that is not what it should be (truncated, another format, an array header that
    promises more bytes than the file holds); the message names the file."""


def _array_header(fh) -> tuple[tuple, np.dtype, int]:
    """(shape, dtype, bytes the array needs) from a ``.npy`` stream at its start; ValueError if
    the header is not one."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        shape, _fortran, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version in ((2, 0), (3, 0)):
        shape, _fortran, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        raise ValueError(f"unsupported .npy format version {version}")
    count = 1
    for n in shape:
        count *= int(n)
    return shape, dtype, count * dtype.itemsize


def _check_array_size(fh, available: int, where: str) -> None:
    """Refuse an array whose header promises more bytes than ``available`` after the header: read
    as it is, numpy would first allocate what it promises (a 16-byte file can ask for terabytes)."""
    start = fh.tell()
    try:
        shape, dtype, nbytes = _array_header(fh)
    except ValueError as exc:
        raise UnreadableFileError(f"{where}: not a .npy array ({_short(exc)})") from None
    held = available - (fh.tell() - start)
    fh.seek(start)
    if not dtype.hasobject and nbytes > held:
        raise UnreadableFileError(
            f"{where}: its header promises a {'x'.join(map(str, shape)) or 'scalar'} {dtype} array "
            f"({nbytes} bytes) but {max(held, 0)} bytes follow (truncated or damaged)"
        )


def _short(exc: BaseException, limit: int = 200) -> str:
    """An exception as one short line (a damaged zip's quotes kilobytes of its bytes)."""
    text = " ".join(str(exc).split())
    return f"{type(exc).__name__}: " + (text if len(text) <= limit else text[: limit - 3] + "...")


#: What reading a damaged .npy/.npz raises, besides ValueError: wrapped into UnreadableFileError.
_READ_ERRORS = (EOFError, OSError, zipfile.BadZipFile, zlib.error, pickle.UnpicklingError, MemoryError)


class RefusedPickleError(pickle.UnpicklingError):
    """A pickle asked for a global outside the allow-list; nothing of it was run."""


class SafeUnpickler(pickle.Unpickler):
    """Unpickles numpy arrays, dtypes and scalars and Python's plain containers; refuses the rest.

    Subclasses widen the allow-list by overriding :meth:`find_class` and calling this one last.
    """

    #: what the refusal message says this file may hold
    allowed_description = "only numpy arrays and plain containers are allowed"

    def find_class(self, module: str, name: str):
        if module in _NUMPY_MULTIARRAY and name in ("_reconstruct", "scalar"):
            return getattr(_CORE.multiarray, name)
        if module in _NUMPY_NUMERIC and name == "_frombuffer":
            return _CORE.numeric._frombuffer
        if module in ("numpy", *_NUMPY_MULTIARRAY, *_NUMPY_NUMERIC) and name in ("ndarray", "dtype"):
            return getattr(np, name)
        if module == "numpy.dtypes" and name.endswith("DType"):
            import numpy.dtypes

            found = getattr(numpy.dtypes, name, None)
            if isinstance(found, type):
                return found
        if module in ("__builtin__", "builtins") and name in _SAFE_BUILTINS:
            return getattr(builtins, name)
        if module == "collections" and name == "OrderedDict":
            return collections.OrderedDict
        if module == "_codecs" and name == "encode":  # bytes in protocol-2 pickles written by Python 3
            return codecs.encode
        raise RefusedPickleError(f"refusing to unpickle {module}.{name}: {self.allowed_description}")


def safe_loads(data: bytes, unpickler: type[pickle.Unpickler] = SafeUnpickler) -> Any:
    """Unpickle ``data`` through ``unpickler`` (latin-1 strings, as Python-2 pickles need)."""
    return unpickler(io.BytesIO(data), encoding="latin1").load()


def _unwrap_object_array(array):
    """``np.save(path, some_dict)`` stores a 0-d object array; give back the object itself."""
    if isinstance(array, np.ndarray) and array.dtype.hasobject and array.shape == ():
        return array.item()
    return array


def _read_object_payload(fh, unpickler: type[pickle.Unpickler]):
    """Read a ``.npy`` stream positioned at its start whose dtype holds objects."""
    version = np.lib.format.read_magic(fh)
    if version == (1, 0):
        _, _, dtype = np.lib.format.read_array_header_1_0(fh)
    elif version == (2, 0):
        _, _, dtype = np.lib.format.read_array_header_2_0(fh)
    else:
        raise ValueError(f"unsupported .npy format version {version} for an object array")
    if not dtype.hasobject:
        raise ValueError(f"expected an object array, the header says {dtype}")
    return unpickler(fh, encoding="latin1").load()


def _is_object_array_error(exc: ValueError) -> bool:
    return "allow_pickle" in str(exc)


def load_npy(path: str | Path, unpickler: type[pickle.Unpickler] = SafeUnpickler):
    """A ``.npy`` file; an object array (e.g. a saved dict) is unpickled through ``unpickler``.

    Returns the array, or for a 0-d object array (``np.save(path, some_dict)``) the object itself.
    A file that is a bare pickle rather than ``.npy`` (``np.load`` reads those too) goes through
    the same unpickler. Raises :class:`RefusedPickleError` for a pickle that names anything
    outside the allow-list, and numpy's or pickle's own errors for a file that is neither.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        bare_pickle = fh.read(len(NPY_MAGIC)) != NPY_MAGIC
        fh.seek(0)
        if not bare_pickle:
            _check_array_size(fh, path.stat().st_size, str(path))
            try:
                return np.load(fh, allow_pickle=False)
            except ValueError as exc:
                if not _is_object_array_error(exc):
                    raise UnreadableFileError(f"{path}: cannot be read as .npy ({_short(exc)})") from None
            except _READ_ERRORS as exc:
                raise UnreadableFileError(f"{path}: cannot be read as .npy ({_short(exc)})") from None
        fh.seek(0)
        try:
            if bare_pickle:
                return unpickler(fh, encoding="latin1").load()
            return _unwrap_object_array(_read_object_payload(fh, unpickler))
        except RefusedPickleError as exc:
            raise RefusedPickleError(f"{path}: {exc}") from None
        except (ValueError, *_READ_ERRORS) as exc:
            what = "a pickle" if bare_pickle else "an object .npy"
            raise UnreadableFileError(f"{path}: cannot be read as {what} ({_short(exc)})") from None


def load_npz(path: str | Path, unpickler: type[pickle.Unpickler] | None = None) -> dict[str, Any]:
    """Every member of an ``.npz`` archive as a dict, read with ``allow_pickle=False``.

    A member that holds pickled objects raises :class:`RefusedPickleError` naming it, unless
    ``unpickler`` is given: then it is unpickled through that restricted unpickler (and a 0-d
    object array becomes its object), as :func:`load_npy` does.
    """
    path = Path(path)
    out: dict[str, Any] = {}
    if not zipfile.is_zipfile(path):
        raise UnreadableFileError(f"{path}: not an .npz archive (a zip file of .npy arrays)")
    try:
        archive = np.load(path, allow_pickle=False)
    except (ValueError, *_READ_ERRORS) as exc:
        raise UnreadableFileError(f"{path}: cannot be read as .npz ({_short(exc)})") from None
    with archive:
        for key in archive.files:
            where = f"{path} member {key!r}"
            try:
                with archive.zip.open(f"{key}.npy") as member:
                    _check_array_size(member, archive.zip.getinfo(f"{key}.npy").file_size, where)
                out[key] = archive[key]
                continue
            except ValueError as exc:
                if isinstance(exc, UnreadableFileError):
                    raise
                if not _is_object_array_error(exc):
                    raise UnreadableFileError(f"{where}: cannot be read ({_short(exc)})") from None
            except _READ_ERRORS as exc:
                raise UnreadableFileError(f"{where}: cannot be read ({_short(exc)})") from None
            if unpickler is None:
                raise RefusedPickleError(
                    f"{path}: refusing member {key!r}: it holds pickled Python objects, which are not "
                    "loaded from .npz (re-save it with plain arrays)"
                )
            try:
                with archive.zip.open(f"{key}.npy") as member:
                    payload = io.BytesIO(member.read())
                out[key] = _unwrap_object_array(_read_object_payload(payload, unpickler))
            except RefusedPickleError as exc:
                raise RefusedPickleError(f"{path} member {key!r}: {exc}") from None
            except (ValueError, *_READ_ERRORS) as exc:
                raise UnreadableFileError(f"{where}: cannot be read ({_short(exc)})") from None
    return out


def load_torch(source: str | Path | BinaryIO, map_location: str = "cpu"):
    """``torch.load(source, weights_only=True)``: tensors and plain containers, no pickled code.

    ``source`` is a path or a binary file object. torch is imported here, not at module import,
    so readers of other formats stay torch-free.
    """
    import torch

    if isinstance(source, str | Path):
        source = Path(source)
    return torch.load(source, map_location=map_location, weights_only=True)


def load_yaml(path: str | Path) -> Any:
    """A YAML file by ``yaml.safe_load``: Python tags (``!!python/object/apply:os.system``) raise
    ``yaml.YAMLError`` instead of running."""
    return loads_yaml(Path(path).read_text())


def loads_yaml(text: str) -> Any:
    """YAML text by ``yaml.safe_load`` (see :func:`load_yaml`)."""
    import yaml

    return yaml.safe_load(text)


def _refuse_extension(code: int, data: bytes):
    raise ValueError(f"msgpack extension type {code} refused: stg_node headers hold plain values only")


#: ``msgpack.unpackb`` refusing extension types (a ``ValueError``); msgpack's defaults otherwise
#: (``raw=False``: str stays str; ``strict_map_key=True``: str/bytes keys). The bus decodes every
#: header with it (stg_node.bus.codec); a partial, not a wrapper, because that path is hot.
unpack_msgpack = functools.partial(msgpack.unpackb, ext_hook=_refuse_extension)
