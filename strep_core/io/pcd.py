"""A small reader and writer of PCD v0.7 files (ascii and binary).

Open3D reads PCD too, but DeepMapping's frames come inside a ``.tar``; parsing bytes here
avoids extracting to disk and keeps the 2D reader free of Open3D. `parse_pcd_fields` keeps
every field of the file (a LiDAR's intensity, ring, time; normals, curvature), which Open3D's
legacy reader drops; ``binary_compressed`` files are left to Open3D (`strep_core.io.folder`).
"""

from __future__ import annotations

import numpy as np

from strep_core.errors import FormatError

_TYPES = {
    ("F", 4): "<f4",
    ("F", 8): "<f8",
    ("I", 1): "<i1",
    ("I", 2): "<i2",
    ("I", 4): "<i4",
    ("U", 1): "<u1",
    ("U", 2): "<u2",
    ("U", 4): "<u4",
}


class PcdLayoutError(FormatError):
    """A PCD layout this reader does not parse (``binary_compressed``): read it with Open3D."""


def parse_pcd(data: bytes, *, name: str = "<pcd>") -> np.ndarray:
    """Parse PCD bytes into an ``(N, 3)`` float64 array of x, y, z.

    Raises:
        FormatError: not a PCD file, an unsupported layout, or truncated data.
    """
    fields = parse_pcd_fields(data, name=name)
    return np.stack([fields["x"], fields["y"], fields["z"]], 1).astype(np.float64)


def parse_pcd_fields(data: bytes, *, name: str = "<pcd>") -> dict[str, np.ndarray]:
    """Parse PCD bytes into every field, in the file's order: ``(N,)`` arrays (``(N, c)`` for a
    field of COUNT c), in the field's own type (float64 for ascii files), copies of the bytes.

    Raises:
        FormatError: not a PCD file, an unsupported layout (``binary_compressed``), or
            truncated data.
    """
    header: dict[str, list[str]] = {}
    pos = 0
    while True:
        end = data.find(b"\n", pos)
        if end < 0:
            raise FormatError(f"{name}: PCD header ends before its DATA line")
        line = data[pos:end].decode("ascii", errors="replace").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *vals = line.split()
        header[key.upper()] = vals
        if key.upper() == "DATA":
            break
        if len(header) > 20:
            raise FormatError(f"{name}: not a PCD file")
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        n = int(header["POINTS"][0])
        mode = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as exc:
        raise FormatError(f"{name}: malformed PCD header ({exc})") from exc
    # PCL pads records with fields named "_": unique names here, dropped from the output
    fields = [f"_pad{i}" if f == "_" else f for i, f in enumerate(fields)]
    if len(set(fields)) != len(fields):
        raise FormatError(f"{name}: PCD names a field twice ({fields})")
    if not {"x", "y", "z"} <= set(fields):
        raise FormatError(f"{name}: PCD has fields {fields}, needs x y z")
    if n < 0 or not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise FormatError(f"{name}: inconsistent PCD header")
    if mode == "ascii":
        width = sum(counts)
        # at most n * width tokens: a file longer than its header says costs no more memory
        text = data[pos:].decode("ascii", errors="replace").split(None, n * width)
        if len(text) < n * width:
            raise FormatError(f"{name}: PCD has {len(text) // max(width, 1)} of {n} points")
        table = np.asarray(text[: n * width], dtype=np.float64).reshape(n, width)
        offsets = np.cumsum([0, *counts[:-1]])
        return {
            f: table[:, o] if c == 1 else table[:, o : o + c].copy()
            for f, o, c in zip(fields, offsets, counts, strict=True)
            if not f.startswith("_pad")
        }
    if mode != "binary":
        raise PcdLayoutError(f"{name}: PCD DATA {mode!r} is not supported (ascii or binary only)")
    try:
        dtype = np.dtype(
            [
                (f, _TYPES[(t.upper(), s)], (c,)) if c > 1 else (f, _TYPES[(t.upper(), s)])
                for f, s, t, c in zip(fields, sizes, types, counts, strict=True)
            ]
        )
    except KeyError as exc:
        raise FormatError(f"{name}: unsupported PCD field type {exc}") from exc
    need = dtype.itemsize * n
    if len(data) - pos < need:
        raise FormatError(f"{name}: PCD data truncated ({len(data) - pos} of {need} bytes)")
    rec = np.frombuffer(data, dtype=dtype, count=n, offset=pos)
    return {f: np.array(rec[f]) for f in dtype.names or () if not f.startswith("_pad")}


def format_pcd(points: np.ndarray) -> bytes:
    """Binary PCD v0.7 bytes for ``(N, 2|3)`` points (2D padded with z = 0), float32."""
    pts = np.asarray(points, dtype=np.float32)
    if pts.shape[1] == 2:
        pts = np.concatenate([pts, np.zeros((len(pts), 1), np.float32)], 1)
    head = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n"
        f"TYPE F F F\nCOUNT 1 1 1\nWIDTH {len(pts)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {len(pts)}\nDATA binary\n"
    )
    return head.encode("ascii") + np.ascontiguousarray(pts, dtype="<f4").tobytes()
