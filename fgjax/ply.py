"""Gaussians as a standard 3DGS .ply file (the INRIA layout that splat viewers and tools read), and back.

The file is a binary little-endian PLY with one element, ``vertex``, one row per Gaussian, every property a
float32, in this order:

    x, y, z                       centre (scene units)
    nx, ny, nz                    zeros (unused, kept for the layout)
    f_dc_0, f_dc_1, f_dc_2        SH coefficient 0 (the DC term) of R, G, B
    f_rest_0 .. f_rest_{3(K-1)-1} SH coefficients 1..K-1, channel-major: all K-1 of R, then of G, then of B
                                  (f_rest_{c(K-1) + j - 1} = sh[:, j, c]); K = (degree + 1)^2 in {1, 4, 9, 16}
    opacity                       logit (the activated opacity is sigmoid(opacity))
    scale_0, scale_1, scale_2     log-scales (the activated scales are exp(scale_i))
    rot_0 .. rot_3                quaternion w, x, y, z (not necessarily normalised)

These are the raw parameters of `fgjax.gaussians.Gaussians` (``sh`` [N, K, 3] with RGB = max(SH sum + 0.5, 0)),
so a file written here renders in another 3DGS viewer as fgjax renders it. Reference: Kerbl et al., "3D Gaussian
Splatting for Real-Time Radiance Field Rendering" (SIGGRAPH 2023), whose ``save_ply`` defines the layout.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fgjax.gaussians import Gaussians
from fgjax.io import atomic_write

__all__ = ["ply_property_names", "write_ply", "read_ply"]

_PLY_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1", "uint8": "u1",
              "char": "i1", "int8": "i1", "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2",
              "int": "<i4", "int32": "<i4", "uint": "<u4", "uint32": "<u4"}


def ply_property_names(num_sh_coeffs: int) -> list[str]:
    """The vertex properties of the layout, in file order, for K = ``num_sh_coeffs`` SH coefficients per channel."""
    if num_sh_coeffs not in (1, 4, 9, 16):
        raise ValueError(f"ply_property_names: num_sh_coeffs must be 1, 4, 9 or 16, got {num_sh_coeffs}")
    return (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
            + [f"f_rest_{i}" for i in range(3 * (num_sh_coeffs - 1))]
            + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])


def _rows(g: Gaussians, k: int) -> np.ndarray:
    """[N, P] float32 rows of the layout from the first ``k`` SH coefficients of ``g``."""
    means = np.asarray(g.means, np.float32)
    n = means.shape[0]
    sh = np.asarray(g.sh, np.float32)[:, :k]  # [N, k, 3]
    rest = np.transpose(sh[:, 1:], (0, 2, 1)).reshape(n, 3 * (k - 1))  # [N, 3(k-1)], channel-major
    return np.concatenate([means, np.zeros((n, 3), np.float32), sh[:, 0], rest,
                           np.asarray(g.opacity_logits, np.float32)[:, None], np.asarray(g.log_scales, np.float32),
                           np.asarray(g.quats, np.float32)], axis=1)


def write_ply(path: str | Path, g: Gaussians, *, sh_degree: int | None = None) -> Path:
    """Write every row of ``g`` to ``path`` in the layout of the module docstring (atomically; the folder must
    exist).

    Args:
        path: the .ply file.
        g: Gaussians (raw parameters; any float dtype, written as float32). Select the rows to keep first.
        sh_degree: keep the SH coefficients up to this degree (the degree the scene renders with); None: all of
            ``g.sh``.

    Returns:
        ``path``.
    """
    k = g.sh.shape[1] if sh_degree is None else (int(sh_degree) + 1) ** 2
    if not 1 <= k <= g.sh.shape[1] or k not in (1, 4, 9, 16):
        raise ValueError(f"write_ply: sh_degree {sh_degree} needs {k} SH coefficients; the Gaussians have "
                         f"{g.sh.shape[1]}")
    rows = _rows(g, k)
    names = ply_property_names(k)
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {rows.shape[0]}"]
    header += [f"property float {n}" for n in names] + ["end_header"]
    head = ("\n".join(header) + "\n").encode("ascii")
    body = np.ascontiguousarray(rows, "<f4").tobytes()

    def write(f):
        f.write(head)
        f.write(body)

    return atomic_write(path, write)


def _parse_header(path: Path, data: bytes) -> tuple[int, np.dtype, int]:
    """(vertex count, the vertex row dtype, offset of the body) of a binary little-endian PLY."""
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' line or no 'end_header')")
    lines = data[:end].decode("ascii", errors="replace").splitlines()[1:]
    count, fields, elements = None, [], []
    for line in lines:
        parts = line.split()
        if not parts or parts[0] in ("comment", "obj_info"):
            continue
        if parts[0] == "format":
            if parts[1:] != ["binary_little_endian", "1.0"]:
                raise ValueError(f"{path}: format {' '.join(parts[1:])!r}; only binary_little_endian 1.0 is read")
        elif parts[0] == "element":
            if len(parts) != 3 or not parts[2].isdigit():
                raise ValueError(f"{path}: malformed header line {line!r}")
            elements.append(parts[1])
            if parts[1] == "vertex":
                count = int(parts[2])
        elif parts[0] == "property":
            if elements[-1:] != ["vertex"]:
                continue
            if len(parts) != 3 or parts[1] not in _PLY_TYPES:  # a list property has 5 words
                raise ValueError(f"{path}: vertex property {' '.join(parts[1:])!r} is not a scalar PLY type")
            fields.append((parts[2], _PLY_TYPES[parts[1]]))
        else:
            raise ValueError(f"{path}: unexpected header line {line!r}")
    if count is None or elements[:1] != ["vertex"]:
        raise ValueError(f"{path}: the first element must be 'vertex'; got {elements}")
    return count, np.dtype(fields), end + len(b"end_header\n")


def read_ply(path: str | Path) -> Gaussians:
    """Gaussians (numpy float32 leaves, exactly the values stored) from a 3DGS .ply file.

    Reads the layout of the module docstring by property name (extra vertex properties are ignored; a float64
    file is read and cast to float32). ValueError, naming the file, for anything else: another format, a missing
    property, an SH count that is not 1, 4, 9 or 16 coefficients per channel, a truncated body.
    """
    path = Path(path)
    data = path.read_bytes()
    count, dtype, offset = _parse_header(path, data)
    need = count * dtype.itemsize
    if len(data) - offset < need:
        raise ValueError(f"{path}: truncated: {count} vertices need {need} bytes after the header, the file has "
                         f"{len(data) - offset}")
    rows = np.frombuffer(data, dtype, count, offset)
    names = set(dtype.names or ())
    n_rest = sum(1 for n in names if n.startswith("f_rest_"))
    if n_rest % 3 or n_rest // 3 + 1 not in (1, 4, 9, 16):
        raise ValueError(f"{path}: {n_rest} f_rest properties; need 3 (K - 1) with K in 1, 4, 9, 16")
    k = n_rest // 3 + 1
    missing = [n for n in ply_property_names(k) if n not in names and n not in ("nx", "ny", "nz")]
    if missing:
        raise ValueError(f"{path}: vertex properties missing: {', '.join(missing)}")

    def col(*ns: str) -> np.ndarray:  # [N, len(ns)] float32
        out = np.empty((count, len(ns)), np.float32)
        for i, n in enumerate(ns):
            out[:, i] = rows[n]
        return out

    rest = col(*(f"f_rest_{i}" for i in range(n_rest))).reshape(count, 3, k - 1)  # [N, 3, K-1]
    sh = np.concatenate([col("f_dc_0", "f_dc_1", "f_dc_2")[:, None], np.transpose(rest, (0, 2, 1))], axis=1)
    return Gaussians(col("x", "y", "z"), col("scale_0", "scale_1", "scale_2"), col("rot_0", "rot_1", "rot_2", "rot_3"),
                     np.asarray(rows["opacity"], np.float32), sh)
