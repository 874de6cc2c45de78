"""Reading the files datasets are made of: images, masks, pickled numpy dicts, JSON.

Each reader checks what it got and raises :class:`~stg_node.data.errors.DatasetError` naming
the file: OpenCV returns ``None`` for a corrupt image and numpy raises bare pickling errors, and
neither says which of ten thousand files is broken. Pickled and ``.npz`` files are read through
:mod:`stg_node.safe_load`, so a crafted dataset file cannot run code.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from stg_node.data.errors import DatasetError
from stg_node.safe_load import RefusedPickleError, load_npy, load_npz

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".bmp")

# Threshold for lossy (JPEG) masks, whose edges and background carry compression noise.
# Lossless masks count every non-zero value as foreground (ZJU-MoCap's mask_cihp stores part
# labels 1..N, its mask/ folder 0/1 or 0/255).
JPEG_MASK_THRESHOLD = 128


def read_image(path: str | Path) -> np.ndarray:
    """An RGB ``(H, W, 3)`` uint8 image; grey and RGBA inputs are converted."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "image file is missing", "an existing .jpg/.png file")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.size == 0:
        raise DatasetError(path, "image cannot be decoded (corrupt or not an image)", "a readable JPEG/PNG")
    if data.dtype == np.uint16:
        data = (data // 257).astype(np.uint8)
    if data.dtype != np.uint8:
        raise DatasetError(path, f"image has dtype {data.dtype}", "8-bit (or 16-bit) pixels")
    if data.ndim == 2:
        return cv2.cvtColor(data, cv2.COLOR_GRAY2RGB)
    if data.shape[2] == 4:
        return cv2.cvtColor(data, cv2.COLOR_BGRA2RGB)
    if data.shape[2] == 3:
        return cv2.cvtColor(data, cv2.COLOR_BGR2RGB)
    raise DatasetError(path, f"image has {data.shape[2]} channels", "1, 3 or 4 channels")


def read_mask(path: str | Path) -> np.ndarray:
    """A ``(H, W)`` uint8 mask, 255 on the person and 0 elsewhere.

    Lossless files (PNG, BMP): any non-zero value is the person. JPEG files: values of at least
    ``JPEG_MASK_THRESHOLD``. Colour masks use their maximum over channels.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "mask file is missing", "an existing .png/.jpg mask")
    data = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if data is None or data.size == 0:
        raise DatasetError(path, "mask cannot be decoded (corrupt or not an image)", "a readable PNG/JPEG")
    if data.ndim == 3:
        data = data[..., :3].max(axis=2) if data.shape[2] >= 3 else data[..., 0]
    lossy = path.suffix.lower() in (".jpg", ".jpeg")
    if lossy:
        scale = 257 if data.dtype == np.uint16 else 1
        on = data >= JPEG_MASK_THRESHOLD * scale
    else:
        on = data != 0
    return np.where(on, np.uint8(255), np.uint8(0))


def load_npy_dict(path: str | Path) -> dict[str, Any]:
    """A dict saved with ``np.save(path, dict)`` (ZJU-MoCap's annots.npy, new_params/*.npy).

    Read by :func:`stg_node.safe_load.load_npy`: only numpy arrays and plain containers are
    rebuilt; a pickle naming anything else (``os.system``) is refused before it runs.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file is missing", "a .npy file holding a pickled dict")
    try:
        data = load_npy(path)
    except RefusedPickleError as exc:
        raise DatasetError(
            path, f"refused: {str(exc).removeprefix(f'{path}: ')}", "a dict of arrays saved with np.save"
        ) from None
    except Exception as exc:  # numpy raises ValueError, UnpicklingError, EOFError, OSError ...
        raise DatasetError(
            path, f"cannot be read as .npy ({type(exc).__name__}: {exc})", "a .npy file written by np.save"
        ) from exc
    if not isinstance(data, dict):
        raise DatasetError(path, f"holds a {type(data).__name__}", "a dict saved with np.save(path, dict)")
    return data


def load_npz_arrays(path: str | Path, expected: str) -> dict[str, np.ndarray]:
    """Every array of an ``.npz`` (:func:`stg_node.safe_load.load_npz`: no pickled members);
    ``expected`` says what the file should hold, for the error."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file is missing", expected)
    try:
        return load_npz(path)
    except RefusedPickleError as exc:
        raise DatasetError(
            path, f"refused: {str(exc).removeprefix(f'{path}: ')}", f"{expected}, plain arrays only"
        ) from None
    except Exception as exc:
        raise DatasetError(
            path, f"cannot be read ({type(exc).__name__}: {short(exc)})", f"an .npz archive: {expected}"
        ) from exc


def load_json(path: str | Path) -> Any:
    path = Path(path)
    if not path.is_file():
        raise DatasetError(path, "file is missing", "a JSON file")
    try:
        return json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(path, f"is not valid JSON ({exc})", "a JSON document") from exc


def as_array(
    value: Any, shape: tuple[int, ...], *, path: str | Path, name: str, dtype=np.float64
) -> np.ndarray:
    """``value`` as a finite array of ``shape`` (size-compatible reshapes allowed), else an error."""
    try:
        array = np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise DatasetError(path, f"{name} is not numeric ({exc})", f"{name} of shape {shape}") from exc
    if array.size != int(np.prod(shape)):
        raise DatasetError(path, f"{name} has shape {array.shape}", f"{name} of shape {shape}")
    array = array.reshape(shape)
    if not np.all(np.isfinite(array)):
        raise DatasetError(path, f"{name} contains NaN or infinite values", f"finite {name}")
    return array


#: OpenCV's distortion models: how many coefficients each takes (0: none).
DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)


def as_distortion(value: Any, *, path: str | Path, name: str) -> np.ndarray:
    """OpenCV distortion coefficients: finite, and as many as one of its models takes."""
    D = as_array(value, (np.size(value),), path=path, name=name)
    if D.size not in DISTORTION_COUNTS:
        raise DatasetError(
            path, f"{name} has {D.size} coefficients", f"{name}: one of {DISTORTION_COUNTS} (OpenCV)"
        )
    return D


def short(exc: BaseException, limit: int = 200) -> str:
    """An exception as one short line (some, a damaged zip's, quote kilobytes of its bytes)."""
    text = " ".join(str(exc).split())
    return text if len(text) <= limit else text[: limit - 3] + "..."


def as_size(value: Any, *, path: str | Path, name: str) -> int:
    """An image dimension: a positive whole number, else an error naming ``path`` and ``name``."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        number = float("nan")
    if not (np.isfinite(number) and number >= 1 and number == int(number) and number < 1e6):
        raise DatasetError(path, f"{name} is {value!r}", f"{name} as a positive whole number of pixels")
    return int(number)


def as_rows(value: Any, *, path: str | Path, name: str) -> np.ndarray:
    """An array with a leading axis of one row per frame (at least 1-D), else an error."""
    array = np.asarray(value)
    if array.ndim < 1 or array.dtype.kind not in "biuf":
        raise DatasetError(
            path,
            f"{name} is a {array.dtype} array of shape {array.shape}",
            f"{name}: numbers, one row per frame",
        )
    return array


def find_image(stem: Path) -> Path | None:
    """The existing file ``stem`` + one of the image suffixes, or None."""
    for suffix in IMAGE_SUFFIXES:
        candidate = stem.with_name(stem.name + suffix)
        if candidate.is_file():
            return candidate
    return None
