"""Gaussians to and from PLY files in the standard 3D Gaussian Splatting attribute layout.

One ``vertex`` element, little-endian float32 properties, in this order (what the 3DGS
reference code writes and what splat viewers such as SuperSplat, antimatter15/splat or
gsplat's viewer read):

    x y z            centre (metres)
    nx ny nz         unused normals, written as 0
    f_dc_0..2        degree-0 spherical-harmonics coefficient per RGB channel
    f_rest_0..M-1    higher SH coefficients, channel-major: all of R's, then G's, then B's
    opacity          logit(opacity)
    scale_0..2       log(scale)
    rot_0..3         quaternion w, x, y, z (as stored; not normalised)

In memory we keep activated values, like ``rasterize`` takes them. RGB colours map to the DC
coefficient by ``rgb = 0.5 + SH_C0 * f_dc`` (the 3DGS convention). Opacities are clamped
to [OPACITY_EPS, 1 - OPACITY_EPS] and scales to >= SCALE_MIN before the logit / log, so
the file never holds inf.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

SH_C0 = 0.28209479177387814
OPACITY_EPS = 1e-7
SCALE_MIN = 1e-20

_PLY_TYPES = {
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "i2",
    "int16": "i2",
    "ushort": "u2",
    "uint16": "u2",
    "int": "i4",
    "int32": "i4",
    "uint": "u4",
    "uint32": "u4",
    "float": "f4",
    "float32": "f4",
    "double": "f8",
    "float64": "f8",
}


def rgb_to_sh(rgb):
    """Activated RGB in [0, 1] -> degree-0 SH coefficient (works on numpy and torch)."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh_dc):
    """Degree-0 SH coefficient -> RGB (not clamped)."""
    return sh_dc * SH_C0 + 0.5


@dataclass
class GaussianPly:
    """Gaussians as read from / written to a PLY file (numpy float32, activated values)."""

    means: np.ndarray  # [N, 3]
    quats: np.ndarray  # [N, 4] wxyz
    scales: np.ndarray  # [N, 3] activated
    opacities: np.ndarray  # [N] activated
    sh_dc: np.ndarray  # [N, 3]
    sh_rest: np.ndarray  # [N, K, 3], K = 0, 3, 8 or 15 for SH degree 0..3

    @property
    def colors(self) -> np.ndarray:
        """RGB from the DC coefficient (view-independent colour), clipped to [0, 1]."""
        return np.clip(sh_to_rgb(self.sh_dc), 0.0, 1.0).astype(np.float32)

    def __len__(self) -> int:
        return int(self.means.shape[0])


def _as_numpy(name: str, value, shape: tuple) -> np.ndarray:
    if value is None:
        raise ValueError(f"{name} is required")
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim != len(shape) or any(s is not None and a != s for a, s in zip(arr.shape, shape, strict=True)):
        want = "[" + ", ".join("?" if s is None else str(s) for s in shape) + "]"
        raise ValueError(f"{name} must be {want}, got {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} contains NaN or inf; refusing to write a corrupt PLY")
    return arr


def save_ply(path, means, quats, scales, opacities, colors=None, *, sh_dc=None, sh_rest=None) -> Path:
    """Write Gaussians (activated values, numpy or torch) to ``path`` in the 3DGS layout.

    Give either ``colors`` ([N, 3] RGB in [0, 1], stored as the SH DC term) or ``sh_dc``
    ([N, 3]); ``sh_rest`` ([N, K, 3]) is optional.
    """
    means = _as_numpy("means", means, (None, 3))
    n = means.shape[0]
    quats = _as_numpy("quats", quats, (n, 4))
    scales = _as_numpy("scales", scales, (n, 3))
    opacities = _as_numpy("opacities", opacities, (n,))
    if (colors is None) == (sh_dc is None):
        raise ValueError("give exactly one of colors (RGB) or sh_dc")
    if colors is not None:
        dc = rgb_to_sh(_as_numpy("colors", colors, (n, 3)))
    else:
        dc = _as_numpy("sh_dc", sh_dc, (n, 3))
    rest = np.zeros((n, 0, 3)) if sh_rest is None else _as_numpy("sh_rest", sh_rest, (n, None, 3))
    if np.any(scales < 0):
        raise ValueError("scales must be activated (>= 0) values")

    k = rest.shape[1]
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    o = np.clip(opacities, OPACITY_EPS, 1.0 - OPACITY_EPS)
    columns = [
        means,
        np.zeros((n, 3)),
        dc,
        rest.transpose(0, 2, 1).reshape(n, 3 * k),  # channel-major, as 3DGS writes it
        np.log(o / (1.0 - o))[:, None],
        np.log(np.maximum(scales, SCALE_MIN)),
        quats,
    ]
    data = np.concatenate(columns, axis=1).astype("<f4")
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment stg_node.splat 3DGS layout: opacity=logit, scale=log, rot=wxyz",
        f"element vertex {n}",
    ]
    header += [f"property float {name}" for name in names]
    header.append("end_header")
    path = Path(path)
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        f.write(np.ascontiguousarray(data).tobytes())
    return path


def _parse_header(f, path) -> tuple[str, list[tuple[str, int, list[tuple[str, str]]]], int]:
    if f.readline().strip() != b"ply":
        raise ValueError(f"{path} is not a PLY file (it does not start with 'ply')")
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []
    while True:
        line = f.readline()
        if not line:
            raise ValueError(f"{path}: PLY header has no end_header line (truncated file?)")
        parts = line.decode("ascii", errors="replace").split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            fmt = parts[1]
        elif parts[0] == "element":
            elements.append((parts[1], int(parts[2]), []))
        elif parts[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element")
            if parts[1] == "list":
                elements[-1][2].append((parts[-1], "list"))
            else:
                if parts[1] not in _PLY_TYPES:
                    raise ValueError(f"{path}: unknown PLY property type {parts[1]!r}")
                elements[-1][2].append((parts[2], _PLY_TYPES[parts[1]]))
    if fmt not in ("binary_little_endian", "binary_big_endian", "ascii"):
        raise ValueError(f"{path}: unsupported PLY format {fmt!r}")
    return fmt, elements, f.tell()


def load_ply(path) -> GaussianPly:
    """Read a 3DGS-layout PLY (any of the three PLY encodings) into activated values."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no PLY file at {path}")
    with open(path, "rb") as f:
        fmt, elements, start = _parse_header(f, path)
        body = f.read()
    vertex = None
    offset = 0
    for name, count, props in elements:
        if any(t == "list" for _, t in props):
            if name == "vertex":
                raise ValueError(f"{path}: vertex element has list properties; not a Gaussian PLY")
            if fmt != "ascii":
                break  # lists after the vertices do not matter; before them we cannot skip
        if name == "vertex":
            vertex = (count, props)
            break
        if fmt == "ascii":
            raise ValueError(f"{path}: ascii PLY with elements before 'vertex' is not supported")
        offset += count * sum(np.dtype(t).itemsize for _, t in props)
    if vertex is None:
        raise ValueError(f"{path}: PLY file has no 'vertex' element")
    n, props = vertex
    names = [p for p, _ in props]
    if fmt == "ascii":
        text = body.decode("ascii", errors="replace").split("\n")
        rows = [line.split() for line in text if line.strip()][:n]
        if len(rows) < n:
            raise ValueError(f"{path}: expected {n} vertices, file holds {len(rows)} (truncated?)")
        table = np.asarray(rows, dtype=np.float64)
        columns = {name: table[:, i] for i, name in enumerate(names)}
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        dtype = np.dtype([(p, endian + t) for p, t in props])
        need = offset + n * dtype.itemsize
        if len(body) < need:
            raise ValueError(
                f"{path}: expected {n} vertices ({need} bytes of data), file holds {len(body)} (truncated?)"
            )
        table = np.frombuffer(body, dtype=dtype, count=n, offset=offset)
        columns = {name: table[name].astype(np.float64) for name in names}

    required = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        "scale_0",
        "scale_1",
        "scale_2",
        "rot_0",
        "rot_1",
        "rot_2",
        "rot_3",
    ]
    missing = [r for r in required if r not in columns]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing properties {', '.join(missing)}")
    rest_names = sorted((c for c in columns if c.startswith("f_rest_")), key=lambda c: int(c[7:]))
    if len(rest_names) % 3:
        raise ValueError(f"{path}: {len(rest_names)} f_rest_* properties is not a multiple of 3")
    k = len(rest_names) // 3

    def stack(keys):
        return np.stack([columns[key] for key in keys], axis=1) if keys else np.zeros((n, 0))

    rest = stack(rest_names).reshape(n, 3, k).transpose(0, 2, 1)
    with np.errstate(over="ignore"):
        opacities = 1.0 / (1.0 + np.exp(-columns["opacity"]))
        scales = np.exp(stack(["scale_0", "scale_1", "scale_2"]))
    out = GaussianPly(
        means=stack(["x", "y", "z"]).astype(np.float32),
        quats=stack(["rot_0", "rot_1", "rot_2", "rot_3"]).astype(np.float32),
        scales=scales.astype(np.float32),
        opacities=opacities.astype(np.float32),
        sh_dc=stack(["f_dc_0", "f_dc_1", "f_dc_2"]).astype(np.float32),
        sh_rest=np.ascontiguousarray(rest, dtype=np.float32),
    )
    for field in ("means", "quats", "scales", "opacities", "sh_dc"):
        if not np.all(np.isfinite(getattr(out, field))):
            raise ValueError(f"{path}: {field} contains NaN or inf")
    return out
