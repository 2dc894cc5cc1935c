"""A small reader of the vertex element of PLY files, every property kept.

Open3D's legacy reader keeps positions, normals and colours only, and its tensor reader skips
``ushort`` properties (a Velodyne's ``ring``); a LiDAR's PLY scans carry intensity, ring and time
per point (`strep_core.io.folder` reads them here). Files whose vertex element comes after an
element with list properties are left to Open3D (`PlyLayoutError`).
"""

from __future__ import annotations

import numpy as np

from strep_core.errors import FormatError

_TYPES = {
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
_ORDER = {"ascii": "<", "binary_little_endian": "<", "binary_big_endian": ">"}


class PlyLayoutError(FormatError):
    """A valid PLY layout this reader does not parse (an element with list properties, e.g.
    faces, before the vertices): read it with Open3D instead."""


def parse_ply_fields(data: bytes, *, name: str = "<ply>") -> dict[str, np.ndarray]:
    """Parse the ``vertex`` element of PLY bytes into ``(N,)`` arrays, one per property, in
    the file's order and the property's own type (float64 for ascii files).

    Raises:
        FormatError: not a PLY file, a malformed header, truncated data, no x y z.
        PlyLayoutError: an element with list properties before the vertices.
    """
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise FormatError(f"{name}: not a PLY file (no 'ply' ... 'end_header' header)")
    stop = data.find(b"\n", end)
    pos = len(data) if stop < 0 else stop + 1
    fmt = None
    elements: list[tuple[str, int, list[tuple[str, str]], bool]] = []  # name, count, properties, has lists
    for raw in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        tokens = raw.split()
        if not tokens or tokens[0] in ("comment", "obj_info"):
            continue
        try:
            if tokens[0] == "format":
                fmt = tokens[1]
            elif tokens[0] == "element":
                elements.append((tokens[1], int(tokens[2]), [], False))
            elif tokens[0] == "property" and elements:
                el = elements[-1]
                if tokens[1] == "list":
                    elements[-1] = (el[0], el[1], el[2], True)
                else:
                    el[2].append((tokens[2], tokens[1]))
        except (IndexError, ValueError) as exc:
            raise FormatError(f"{name}: malformed PLY header line {raw!r}") from exc
    if fmt not in _ORDER:
        raise FormatError(f"{name}: PLY format {fmt!r} is not ascii or binary")
    skip_rows = 0
    for el_name, count, props, lists in elements:
        if el_name == "vertex":
            break
        if lists:
            raise PlyLayoutError(f"{name}: element {el_name!r} with lists before the vertices")
        skip_rows += count if fmt == "ascii" else 0
        if fmt != "ascii":
            pos += count * np.dtype([(p, _type(t, name)) for p, t in props]).itemsize
    else:
        raise FormatError(f"{name}: PLY has no vertex element")
    _, n, props, lists = next(e for e in elements if e[0] == "vertex")
    if lists:
        raise PlyLayoutError(f"{name}: a vertex element with list properties")
    names = [p for p, _ in props]
    if not {"x", "y", "z"} <= set(names) or len(set(names)) != len(names):
        raise FormatError(f"{name}: PLY vertex properties {names} need x y z, each once")
    if fmt == "ascii":
        lines = data[pos:].decode("ascii", errors="replace").split("\n", skip_rows + n)
        rows = [ln.split() for ln in lines[skip_rows : skip_rows + n]]
        if len(rows) < n or any(len(r) != len(names) for r in rows):
            raise FormatError(f"{name}: PLY has fewer than {n} vertex rows of {len(names)} values")
        table = np.asarray(rows, dtype=np.float64).reshape(n, len(names))
        return {p: table[:, i].copy() for i, p in enumerate(names)}
    dtype = np.dtype([(p, _ORDER[fmt] + _type(t, name)) for p, t in props])
    if len(data) - pos < dtype.itemsize * n:
        raise FormatError(f"{name}: PLY data truncated ({len(data) - pos} of {dtype.itemsize * n} bytes)")
    rec = np.frombuffer(data, dtype=dtype, count=n, offset=pos)
    return {p: np.array(rec[p]).astype(rec[p].dtype.newbyteorder("=")) for p in names}


def _type(t: str, name: str) -> str:
    try:
        return _TYPES[t]
    except KeyError as exc:
        raise FormatError(f"{name}: unsupported PLY property type {t!r}") from exc
