"""Bad requests, table-driven: each gets a 4xx with a clear ``{"detail": ...}`` and stores nothing.

"Nothing" is checked after every case: no new row in any table, no new file or folder in the
data directory (uploads, their temporary folder, results, logs).
"""

from __future__ import annotations

import asyncio
import gzip
import io
import json
import tarfile
import time
import zipfile
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from app.core.config import InsecureSettings, Settings
from app.main import create_app

UPLOAD_LIMIT = 256 * 1024
INFLATE_LIMIT = 1024 * 1024
POINT_LIMIT = 5000
FRAMES = 8


# ---- inputs ----------------------------------------------------------------------------------


def npz_bytes(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def sequence_arrays(frames: int = FRAMES, points: int = 32, dims: int = 2) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    poses = np.repeat(np.eye(dims + 1)[None], frames, axis=0)
    poses[:, :dims, dims] = rng.normal(size=(frames, dims))
    return {
        "points": rng.normal(size=(frames * points, dims)) * 10,
        "counts": np.full(frames, points),
        "poses": poses,
    }


def with_value(arrays: dict[str, np.ndarray], value: float) -> dict[str, np.ndarray]:
    out = dict(arrays)
    out["points"] = arrays["points"].copy()
    out["points"][5, 0] = value
    return out


def with_poses(arrays: dict[str, np.ndarray], pose: np.ndarray) -> dict[str, np.ndarray]:
    """``arrays`` with the first ground-truth pose replaced by ``pose``."""
    out = dict(arrays)
    out["poses"] = arrays["poses"].copy()
    out["poses"][0] = pose
    return out


def ply_bytes(points: np.ndarray) -> bytes:
    header = f"ply\nformat ascii 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
    header += "property float z\nend_header\n"
    return (header + "".join(f"{x} {y} {z}\n" for x, y, z in points)).encode()


def zip_bytes(entries: dict[str, bytes], *, compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, data in entries.items():
            zf.writestr(zipfile.ZipInfo(name), data, compress_type=compression)
    return buf.getvalue()


def ply_frames(frames: int = 4, points: int = 40) -> dict[str, bytes]:
    rng = np.random.default_rng(1)
    return {f"frame_{i:03d}.ply": ply_bytes(rng.uniform(0, 2, size=(points, 3))) for i in range(frames)}


def tum_lines(count: int) -> bytes:
    return "".join(f"{i} {0.1 * i} 0 0 0 0 0 1\n" for i in range(count)).encode()


GOOD = sequence_arrays()
GOOD_NPZ = npz_bytes(**GOOD)
GOOD_ZIP = zip_bytes({**ply_frames(), "poses.tum": tum_lines(4)})


def tar_bytes(entries: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, data in entries.items():
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def tgz_bytes(entries: dict[str, bytes]) -> bytes:
    """A gzip-compressed tar (what a ``.tar`` upload may really be)."""
    return gzip.compress(tar_bytes(entries))


def pcd_bytes(points: np.ndarray) -> bytes:
    from strep_core.io.pcd import format_pcd

    return format_pcd(points)


def depth_png(size: int = 8) -> bytes:
    """A 16-bit grayscale PNG depth image (millimetres)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.full((size, size), 1000, dtype=np.uint16)).save(buf, format="PNG")
    return buf.getvalue()


def deepmapping_frames(frames: int = 4, points: int = 20) -> dict[str, bytes]:
    rng = np.random.default_rng(2)
    return {f"{i:03d}.pcd": pcd_bytes(rng.uniform(0, 1, size=(points, 2))) for i in range(frames)}


def flaser_lines(scans: int, beams: int = 30) -> bytes:
    ranges = " ".join(f"{1 + 0.01 * b:.2f}" for b in range(beams))
    return "".join(
        f"FLASER {beams} {ranges} {0.1 * i} 0 0 {0.1 * i} 0 0 {i}.0 host {i}.0\n" for i in range(scans)
    ).encode()


def compressed_npz(**arrays: Any) -> bytes:
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def chunked_upload(filename: str, size: int) -> list[bytes]:
    """A multipart body as a list of chunks: sent without Content-Length (chunked)."""
    head = f'--XyZ\r\nContent-Disposition: form-data; name="file"; filename="{filename}"\r\n\r\n'.encode()
    chunk = bytes(64 * 1024)
    body = [head] + [chunk] * (size // len(chunk)) + [bytes(size % len(chunk)), b"\r\n--XyZ--\r\n"]
    return body


# ---- the table ---------------------------------------------------------------------------------


@dataclass
class Bad:
    """One bad request and what it must answer."""

    id: str
    method: str
    url: str
    status: int
    message: str
    kwargs: dict[str, Any] = field(default_factory=dict)


def upload(filename: str, data: bytes, **form: str) -> dict[str, Any]:
    return {"files": {"file": (filename, data)}, "data": form}


def job(**body: Any) -> dict[str, Any]:
    return {"json": {"sequence_id": "$SEQ", "method": "identity", **body}}


CASES: list[Bad] = [
    # ---- uploads: the file
    Bad(
        "broken zip",
        "POST",
        "/api/sequences",
        400,
        "x.zip: not a readable zip archive",
        upload("x.zip", b"PK\x03\x04junk" * 50),
    ),
    Bad(
        "truncated zip",
        "POST",
        "/api/sequences",
        400,
        "not a readable zip archive",
        upload("frames.zip", GOOD_ZIP[: len(GOOD_ZIP) * 2 // 3]),
    ),
    Bad(
        "zip entry with ..",
        "POST",
        "/api/sequences",
        400,
        "unsafe entry '../evil.ply'",
        upload("evil.zip", zip_bytes({**ply_frames(), "../evil.ply": b"x"})),
    ),
    Bad(
        "zip entry with absolute path",
        "POST",
        "/api/sequences",
        400,
        "unsafe entry '/etc/evil.ply'",
        upload("abs.zip", zip_bytes({**ply_frames(), "/etc/evil.ply": b"x"})),
    ),
    Bad(
        "zip inflating past the limit",
        "POST",
        "/api/sequences",
        400,
        f"over the limit of {INFLATE_LIMIT}",
        upload("bomb.zip", zip_bytes({**ply_frames(), "zeros.ply": bytes(2 * INFLATE_LIMIT)})),
    ),
    Bad(
        "zip of a zip",
        "POST",
        "/api/sequences",
        400,
        "a zip inside a zip is not supported",
        upload("nested.zip", zip_bytes({"inner.zip": GOOD_ZIP})),
    ),
    Bad(
        "zip of unknown files",
        "POST",
        "/api/sequences",
        400,
        "the archive's content has an unknown format",
        upload("notes.zip", zip_bytes({"a.txt": b"hello", "b.txt": b"world"})),
    ),
    Bad(
        "file over the size limit",
        "POST",
        "/api/sequences",
        413,
        f"larger than the limit of {UPLOAD_LIMIT} bytes",
        upload("big.npz", bytes(UPLOAD_LIMIT + 1)),
    ),
    Bad(
        "streamed file over the size limit",
        "POST",
        "/api/sequences",
        413,
        "larger than the limit",
        {
            "content": chunked_upload("big.npz", UPLOAD_LIMIT + 1),
            "headers": {"Content-Type": "multipart/form-data; boundary=XyZ"},
        },
    ),
    Bad(
        "unknown format", "POST", "/api/sequences", 400, "unknown format of 'scan.txt'", upload("scan.txt", b"1 2 3\n")
    ),
    Bad("no extension", "POST", "/api/sequences", 400, "unknown format of 'sequence'", upload("sequence", GOOD_NPZ)),
    Bad(
        "corrupt npz",
        "POST",
        "/api/sequences",
        400,
        "bad.npz: not a readable .npz file",
        upload("bad.npz", b"\x00" * 64),
    ),
    Bad("empty npz", "POST", "/api/sequences", 400, "not a readable .npz file", upload("empty.npz", b"")),
    Bad(
        "npz without points",
        "POST",
        "/api/sequences",
        400,
        "needs keys 'points' and 'counts', or 'frames'",
        upload("keys.npz", npz_bytes(values=np.zeros(3))),
    ),
    Bad(
        "NaN values",
        "POST",
        "/api/sequences",
        400,
        "frame 0 contains non-finite values (NaN or inf)",
        upload("nan.npz", npz_bytes(**with_value(GOOD, np.nan))),
    ),
    Bad(
        "inf values",
        "POST",
        "/api/sequences",
        400,
        "frame 0 contains non-finite values (NaN or inf)",
        upload("inf.npz", npz_bytes(**with_value(GOOD, np.inf))),
    ),
    Bad(
        "empty frame",
        "POST",
        "/api/sequences",
        400,
        "frame 3 has 0 points; at least 3 are needed",
        upload(
            "hole.npz",
            npz_bytes(
                points=GOOD["points"][:-32], counts=np.array([32, 32, 32, 0, 32, 32, 32, 32]), poses=GOOD["poses"]
            ),
        ),
    ),
    Bad(
        "counts not matching points",
        "POST",
        "/api/sequences",
        400,
        "'counts' must be non-negative and sum to",
        upload("counts.npz", npz_bytes(points=GOOD["points"], counts=np.full(FRAMES, 31))),
    ),
    Bad(
        "4D points",
        "POST",
        "/api/sequences",
        400,
        "expected (N, 2) or (N, 3)",
        upload("dims.npz", npz_bytes(frames=np.zeros((FRAMES, 10, 4)))),
    ),
    Bad(
        "pose count not matching frames",
        "POST",
        "/api/sequences",
        400,
        "7 poses for 8 frames",
        upload("poses.npz", npz_bytes(points=GOOD["points"], counts=GOOD["counts"], poses=GOOD["poses"][:7])),
    ),
    Bad(
        "pose shape of the other dimension",
        "POST",
        "/api/sequences",
        400,
        "poses have shape (8, 4, 4)",
        upload(
            "poses3d.npz",
            npz_bytes(points=GOOD["points"], counts=GOOD["counts"], poses=np.repeat(np.eye(4)[None], FRAMES, axis=0)),
        ),
    ),
    Bad(
        "one frame only",
        "POST",
        "/api/sequences",
        400,
        "a sequence needs at least 2 frames, got 1",
        upload("one.npz", npz_bytes(points=GOOD["points"][:32], counts=np.array([32]))),
    ),
    # ---- issue 17, item 12: messages that say what is wrong
    Bad(
        "npz with no frames",
        "POST",
        "/api/sequences",
        400,
        "a sequence needs at least 2 frames, got 0",
        upload("none.npz", npz_bytes(points=np.zeros((0, 2)), counts=np.zeros(0, dtype=np.int64))),
    ),
    Bad(
        "depth images at a zip's root without intrinsics",
        "POST",
        "/api/sequences",
        400,
        "depth.zip: no intrinsics file (camera-intrinsics.txt, intrinsics.txt, intrinsics.json); pass intrinsics",
        upload("depth.zip", zip_bytes({f"depth/{i:03d}.png": depth_png() for i in range(3)})),
    ),
    # ---- issue 17, item 7: rigid poses, finite real points within range
    Bad(
        "scaled poses",
        "POST",
        "/api/sequences",
        400,
        "poses: pose 0 is not rigid: its rotation block is not orthonormal (R R^T differs from the identity by 3)",
        upload("scaled.npz", npz_bytes(**with_poses(GOOD, np.diag([2.0, 2.0, 1.0])))),
    ),
    Bad(
        "all-zero poses",
        "POST",
        "/api/sequences",
        400,
        "poses: pose 0 is not rigid: its last row is not 0 0 1",
        upload("zeros.npz", npz_bytes(**with_poses(GOOD, np.zeros((3, 3))))),
    ),
    Bad(
        "singular rotation",
        "POST",
        "/api/sequences",
        400,
        "poses: pose 0 is not rigid: its rotation block is not orthonormal",
        upload("singular.npz", npz_bytes(**with_poses(GOOD, np.diag([0.0, 0.0, 1.0])))),
    ),
    Bad(
        "mirrored poses",
        "POST",
        "/api/sequences",
        400,
        "poses: pose 0 is not rigid: its rotation block is a reflection (det -1)",
        upload("mirror.npz", npz_bytes(**with_poses(GOOD, np.diag([-1.0, 1.0, 1.0])))),
    ),
    Bad(
        "non-rigid initial guess",
        "POST",
        "/api/sequences",
        400,
        "initial poses: pose 0 is not rigid",
        upload(
            "odom.npz",
            npz_bytes(**GOOD, initial_poses=with_poses(GOOD, np.diag([1.0, 3.0, 1.0]))["poses"]),
        ),
    ),
    Bad(
        "pose translation of 1e300",
        "POST",
        "/api/sequences",
        400,
        "poses has a coordinate of 1e+300; coordinates must lie within +-1e+09",
        upload("far.npz", npz_bytes(**with_poses(GOOD, np.array([[1.0, 0, 1e300], [0, 1, 0], [0, 0, 1]])))),
    ),
    Bad(
        "complex points",
        "POST",
        "/api/sequences",
        400,
        "frame 0 has values of type complex128; real numbers are needed",
        upload("complex.npz", npz_bytes(**{**GOOD, "points": GOOD["points"] * (1 + 1j)})),
    ),
    Bad(
        "points given as text",
        "POST",
        "/api/sequences",
        400,
        "frame 0 has values of type <U",
        upload("text.npz", npz_bytes(**{**GOOD, "points": GOOD["points"].astype(str)})),
    ),
    Bad(
        "coordinates of 1e300",
        "POST",
        "/api/sequences",
        400,
        "frame 0 has a coordinate of 1e+300; coordinates must lie within +-1e+09",
        upload("huge.npz", npz_bytes(**with_value(GOOD, 1e300))),
    ),
    Bad(
        "broken tar",
        "POST",
        "/api/sequences",
        400,
        "broken.tar: not a readable tar archive",
        upload("broken.tar", b"not a tar" * 100),
    ),
    Bad(
        "tar without frames",
        "POST",
        "/api/sequences",
        400,
        "empty.tar",
        upload("empty.tar", tar_bytes({"readme.txt": b"nothing here"})),
    ),
    Bad(
        "garbage CARMEN log",
        "POST",
        "/api/sequences",
        400,
        "no FLASER lines",
        upload("robot.log", b"# not a laser log\nODOM 0 0 0\n"),
    ),
    Bad(
        "gzip that is not gzip",
        "POST",
        "/api/sequences",
        400,
        "robot.log.gz",
        upload("robot.log.gz", b"plain text, not gzip"),
    ),
    Bad(
        "binary CARMEN log",
        "POST",
        "/api/sequences",
        400,
        "not a text CARMEN log",
        upload("bin.log.gz", gzip.compress(bytes(range(256)) * 4)),
    ),
    # ---- uploads: one budget for every container and compressed format (issue 17 item 2)
    Bad(
        "npz array inflating past the limit",
        "POST",
        "/api/sequences",
        400,
        f"points.npy: declares more than the limit of {INFLATE_LIMIT} bytes",
        upload(
            "bomb.npz",
            compressed_npz(
                **{**GOOD, "points": np.zeros((INFLATE_LIMIT // 8, 2)), "counts": np.full(8, INFLATE_LIMIT // 64)}
            ),
        ),
    ),
    Bad(
        "npz with too many points",
        "POST",
        "/api/sequences",
        400,
        f"points.npy: holds more than the limit of {POINT_LIMIT} points",
        upload(
            "many.npz",
            compressed_npz(**{**GOOD, "points": np.zeros((8 * 1000, 2)), "counts": np.full(8, 1000)}),
        ),
    ),
    Bad(
        "npz of a npz in a zip past the limit",
        "POST",
        "/api/sequences",
        400,
        f"the limit of {INFLATE_LIMIT} bytes",
        upload(
            "inner.zip",
            zip_bytes(
                {"seq.npz": compressed_npz(**{**GOOD, "extra": np.zeros(INFLATE_LIMIT // 8 + 1000)})},
                compression=zipfile.ZIP_STORED,
            ),
        ),
    ),
    Bad(
        "gzip tar named .tar inflating past the limit",
        "POST",
        "/api/sequences",
        400,
        f"inflates to more than the limit of {INFLATE_LIMIT} bytes",
        upload("frames.tar", tgz_bytes({**deepmapping_frames(), "junk.bin": bytes(2 * INFLATE_LIMIT)})),
    ),
    Bad(
        "tar frame declaring too many points",
        "POST",
        "/api/sequences",
        400,
        f"holds more than the limit of {POINT_LIMIT} points",
        upload("dense.tar", tgz_bytes(deepmapping_frames(frames=2, points=POINT_LIMIT // 2 + 100))),
    ),
    Bad(
        "CARMEN log.gz inflating past the limit",
        "POST",
        "/api/sequences",
        400,
        f"inflates to more than the limit of {INFLATE_LIMIT} bytes",
        upload("bomb.log.gz", gzip.compress(flaser_lines(5) + b"\n" * (2 * INFLATE_LIMIT))),
    ),
    Bad(
        "CARMEN log with too many readings",
        "POST",
        "/api/sequences",
        400,
        f"holds more than the limit of {POINT_LIMIT} points",
        upload("long.log.gz", gzip.compress(flaser_lines(2 * POINT_LIMIT // 30))),
    ),
    # ---- uploads: the form
    Bad("not multipart", "POST", "/api/sequences", 415, "multipart/form-data", {"json": {"file": "x"}}),
    Bad(
        "no file part",
        "POST",
        "/api/sequences",
        422,
        "no file: send the sequence in a form part named 'file'",
        {"files": {"frames": (None, "0:4")}},
    ),
    Bad(
        "file part without a file name",
        "POST",
        "/api/sequences",
        422,
        "'file' part must be a file",
        {"files": {"file": (None, "just text")}},
    ),
    Bad(
        "unexpected form field",
        "POST",
        "/api/sequences",
        422,
        "unexpected form field 'colour'",
        {"files": {"file": ("ok.npz", GOOD_NPZ)}, "data": {"colour": "red"}},
    ),
    Bad(
        "two files",
        "POST",
        "/api/sequences",
        422,
        "exactly one file",
        {"files": [("file", ("a.npz", GOOD_NPZ)), ("file", ("b.npz", GOOD_NPZ))]},
    ),
    Bad(
        "malformed frame selection",
        "POST",
        "/api/sequences",
        422,
        "frames: frame selection 'every' is not",
        upload("ok.npz", GOOD_NPZ, frames="every"),
    ),
    Bad(
        "frame selection keeping one frame",
        "POST",
        "/api/sequences",
        422,
        "frame selection 0:1 keeps 1 of 8 frames; at least 2 are needed",
        upload("ok.npz", GOOD_NPZ, frames="0:1"),
    ),
    Bad(
        "frame selection keeping no frame of a tar",
        "POST",
        "/api/sequences",
        422,
        "frame selection 9: keeps 0 of 4 frames",
        upload("frames.tar", tar_bytes(deepmapping_frames()), frames="9:"),
    ),
    Bad(
        "name too long",
        "POST",
        "/api/sequences",
        422,
        "name: at most 200 printable characters",
        upload("ok.npz", GOOD_NPZ, name="n" * 201),
    ),
    Bad(
        "truncated multipart body",
        "POST",
        "/api/sequences",
        400,
        "truncated",
        {
            "content": b'--XyZ\r\nContent-Disposition: form-data; name="file"; filename="a.npz"\r\n\r\n'
            + GOOD_NPZ[:100],
            "headers": {"Content-Type": "multipart/form-data; boundary=XyZ"},
        },
    ),
    # ---- jobs
    Bad("unknown method", "POST", "/api/jobs", 422, "unknown method 'teleport'", job(method="teleport")),
    Bad(
        "unknown sequence",
        "POST",
        "/api/jobs",
        404,
        "sequence 'seq_missing' not found",
        {"json": {"sequence_id": "seq_missing", "method": "identity"}},
    ),
    Bad(
        "negative iterations",
        "POST",
        "/api/jobs",
        422,
        "optim.iterations: Input should be greater than or equal to 0",
        job(optim={"iterations": -1}),
    ),
    Bad(
        "too many iterations",
        "POST",
        "/api/jobs",
        422,
        "optim.iterations: Input should be less than or equal to",
        job(optim={"iterations": 10**9}),
    ),
    Bad("seed out of range", "POST", "/api/jobs", 422, "seed: Input should be less than or equal to", job(seed=2**40)),
    Bad("unknown config field", "POST", "/api/jobs", 422, "colour: Extra inputs are not permitted", job(colour="red")),
    Bad(
        "unknown nested field",
        "POST",
        "/api/jobs",
        422,
        "optim.lr: Extra inputs are not permitted",
        job(optim={"lr": 1}),
    ),
    Bad(
        "unknown device", "POST", "/api/jobs", 422, "device: Input should be 'cpu', 'cuda' or 'auto'", job(device="tpu")
    ),
    Bad(
        "NaN learning rate",
        "POST",
        "/api/jobs",
        422,
        "optim.lr_network",
        {
            "content": b'{"sequence_id": "$SEQ", "method": "identity", "optim": {"lr_network": NaN}}',
            "headers": {"Content-Type": "application/json"},
        },
    ),
    Bad("bad frame selection", "POST", "/api/jobs", 422, "frames: frame selection 'half' is not", job(frames="half")),
    Bad(
        "frame selection too short",
        "POST",
        "/api/jobs",
        422,
        "frames: '7:' keeps fewer than 2 of the sequence's 8 frames",
        job(frames="7:"),
    ),
    # ---- issue 17, item 4: strings are bounded and integer parsing cannot raise
    Bad(
        "frames value of 5000 digits",
        "POST",
        "/api/jobs",
        422,
        "frames: String should have at most 64 characters",
        job(frames="0:" + "9" * 5000),
    ),
    Bad(
        "comparison frames value of 5000 digits",
        "POST",
        "/api/comparisons",
        422,
        "config.frames: String should have at most 64 characters",
        {"json": {"sequence_id": "$SEQ", "methods": ["icp"], "config": {"frames": "0:" + "9" * 5000}}},
    ),
    Bad(
        "frame index past int64",
        "POST",
        "/api/jobs",
        422,
        "frames: frame selection '0:99999999999999999999': indices have at most 18 digits",
        job(frames="0:" + "9" * 20),
    ),
    Bad(
        "method name of 5000 characters",
        "POST",
        "/api/jobs",
        422,
        "method: String should have at most 64",
        job(method="m" * 5000),
    ),
    Bad(
        "comparison method name of 5000 characters",
        "POST",
        "/api/comparisons",
        422,
        "methods.0: String should have at most 64",
        {"json": {"sequence_id": "$SEQ", "methods": ["m" * 5000]}},
    ),
    Bad(
        "from_model of 5000 characters",
        "POST",
        "/api/jobs",
        422,
        "from_model: String should have at most 300",
        job(from_model="job:" + "x" * 5000),
    ),
    # ---- item 8: finite config values, bounded widths and point counts
    Bad(
        "infinite loss threshold",
        "POST",
        "/api/jobs",
        422,
        "loss.threshold: Input should be a finite number",
        {
            "content": b'{"sequence_id": "$SEQ", "method": "identity", "loss": {"threshold": Infinity}}',
            "headers": {"Content-Type": "application/json"},
        },
    ),
    Bad(
        "infinite correspondence distance",
        "POST",
        "/api/jobs",
        422,
        "classical.icp.max_correspondence: Input should be a finite number",
        {
            "content": b'{"sequence_id": "$SEQ", "method": "icp", '
            b'"classical": {"icp": {"max_correspondence": Infinity}}}',
            "headers": {"Content-Type": "application/json"},
        },
    ),
    Bad(
        "layer width of a billion",
        "POST",
        "/api/jobs",
        422,
        "model.head_layers.0: Input should be less than or equal to 4096",
        job(model={"head_layers": [1_000_000_000]}),
    ),
    Bad(
        "a thousand layers",
        "POST",
        "/api/jobs",
        422,
        "model.point_layers: List should have at most 16 items",
        job(model={"point_layers": [8] * 1000}),
    ),
    Bad(
        "a billion points per frame",
        "POST",
        "/api/jobs",
        422,
        "optim.points_per_frame: Input should be less than or equal to 1000000",
        job(optim={"points_per_frame": 10**9}),
    ),
    Bad(
        "a billion decoder points",
        "POST",
        "/api/jobs",
        422,
        "model.decoder_points: Input should be less than or equal to 1000000",
        job(model={"decoder_points": 10**9}),
    ),
    Bad(
        "model from a server path",
        "POST",
        "/api/jobs",
        422,
        "server paths are not accepted",
        job(from_model="/etc/passwd"),
    ),
    Bad("freeze without a model", "POST", "/api/jobs", 422, "freeze needs from_model", job(freeze=True)),
    Bad(
        "missing sequence id", "POST", "/api/jobs", 422, "sequence_id: Field required", {"json": {"method": "identity"}}
    ),
    Bad(
        "malformed JSON",
        "POST",
        "/api/jobs",
        422,
        "body: the body is not valid JSON (Expecting property name",
        {"content": b"{not json", "headers": {"Content-Type": "application/json"}},
    ),
    Bad(
        "duplicate methods",
        "POST",
        "/api/comparisons",
        422,
        "methods must be distinct",
        {"json": {"sequence_id": "$SEQ", "methods": ["icp", "icp"]}},
    ),
    Bad(
        "no methods",
        "POST",
        "/api/comparisons",
        422,
        "methods: List should have at least 1 item",
        {"json": {"sequence_id": "$SEQ", "methods": []}},
    ),
    Bad(
        "comparison with an unknown method",
        "POST",
        "/api/comparisons",
        422,
        "unknown method 'teleport'",
        {"json": {"sequence_id": "$SEQ", "methods": ["icp", "teleport"]}},
    ),
    Bad(
        "comparison with config.method",
        "POST",
        "/api/comparisons",
        422,
        "give the methods in 'methods'",
        {"json": {"sequence_id": "$SEQ", "methods": ["icp"], "config": {"method": "icp"}}},
    ),
    # ---- unknown ids and bad queries
    Bad("unknown job", "GET", "/api/jobs/job_missing", 404, "job 'job_missing' not found"),
    Bad("cancel unknown job", "DELETE", "/api/jobs/job_missing", 404, "job 'job_missing' not found"),
    Bad("events of unknown job", "GET", "/api/jobs/job_missing/events", 404, "job 'job_missing' not found"),
    Bad("file of unknown job", "GET", "/api/jobs/job_missing/files/map.ply", 404, "job 'job_missing' not found"),
    Bad("unknown sequence id", "GET", "/api/sequences/seq_missing", 404, "sequence 'seq_missing' not found"),
    Bad("delete unknown sequence", "DELETE", "/api/sequences/seq_missing", 404, "sequence 'seq_missing' not found"),
    Bad("delete unknown sample", "DELETE", "/api/sequences/sample:nope", 404, "sequence 'sample:nope' not found"),
    Bad("unknown comparison", "GET", "/api/comparisons/cmp_missing", 404, "comparison 'cmp_missing' not found"),
    Bad("unknown result file", "GET", "/api/jobs/$JOB/files/strep.db", 404, "no result file named 'strep.db'"),
    Bad(
        "bad Last-Event-ID",
        "GET",
        "/api/jobs/$JOB/events",
        400,
        "Last-Event-ID must be a non-negative integer",
        {"headers": {"Last-Event-ID": "soon"}},
    ),
    # ---- item 9: the event-id parser is bounded
    Bad(
        "Last-Event-ID above 2^63",
        "GET",
        "/api/jobs/$JOB/events",
        400,
        "Last-Event-ID must be a non-negative integer of at most 18 digits",
        {"headers": {"Last-Event-ID": str(2**64)}},
    ),
    Bad(
        "after= of 19 digits",
        "GET",
        "/api/jobs/$JOB/events?after=1000000000000000000",
        422,
        "query.after: Input should be less than or equal to 999999999999999999",
    ),
    Bad(
        "Last-Event-ID of 5000 digits",
        "GET",
        "/api/jobs/$JOB/events",
        400,
        "Last-Event-ID must be a non-negative integer",
        {"headers": {"Last-Event-ID": "9" * 5000}},
    ),
    Bad(
        "negative Last-Event-ID",
        "GET",
        "/api/jobs/$JOB/events",
        400,
        "Last-Event-ID must be a non-negative integer",
        {"headers": {"Last-Event-ID": "-1"}},
    ),
    # ---- item 3: a body limit before parsing
    Bad(
        "JSON body over the limit",
        "POST",
        "/api/jobs",
        413,
        "the request body is larger than the limit of 1048576 bytes",
        {"content": b" " * (2 * 1024 * 1024), "headers": {"Content-Type": "application/json"}},
    ),
    # ---- item 5: loopback mode refuses foreign Hosts and cross-site Origins
    Bad(
        "foreign Host (DNS rebinding)",
        "GET",
        "/api/health",
        421,
        "Host 'evil.example' is not this machine",
        {"headers": {"Host": "evil.example"}},
    ),
    Bad("foreign Host on the page", "GET", "/", 421, "is not this machine", {"headers": {"Host": "evil.example:8000"}}),
    Bad(
        "cross-site upload",
        "POST",
        "/api/sequences",
        403,
        "cross-site request from origin 'http://evil.example' refused",
        {**upload("ok.npz", GOOD_NPZ), "headers": {"Origin": "http://evil.example"}},
    ),
    Bad(
        "cross-site job",
        "POST",
        "/api/jobs",
        403,
        "cross-site request from origin 'http://localhost.evil.example' refused",
        {**job(), "headers": {"Origin": "http://localhost.evil.example"}},
    ),
    Bad(
        "opaque origin",
        "POST",
        "/api/jobs",
        403,
        "cross-site request from origin 'null' refused",
        {**job(), "headers": {"Origin": "null"}},
    ),
    Bad("page size zero", "GET", "/api/jobs?limit=0", 422, "query.limit: Input should be greater than or equal to 1"),
    Bad("unknown status filter", "GET", "/api/jobs?status=sleeping", 422, "query.status: Input should be 'queued'"),
    Bad("unknown route", "GET", "/api/nothing", 404, "Not Found"),
]


# ---- the test ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def env(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Path, dict[str, str]]]:
    data_dir = tmp_path_factory.mktemp("bad")
    settings = Settings(
        data_dir=data_dir, max_upload_bytes=UPLOAD_LIMIT, max_inflated_bytes=INFLATE_LIMIT, max_points=POINT_LIMIT
    )
    with TestClient(create_app(settings)) as client:
        seq = client.post("/api/sequences", files={"file": ("good.npz", GOOD_NPZ)})
        assert seq.status_code == 201, seq.text
        job = client.post("/api/jobs", json={"sequence_id": seq.json()["id"], "method": "identity"})
        assert job.status_code == 201, job.text
        deadline = time.monotonic() + 120
        while client.get(f"/api/jobs/{job.json()['id']}").json()["status"] != "succeeded":
            assert time.monotonic() < deadline, "the baseline job did not finish"
            time.sleep(0.05)
        yield client, data_dir, {"$SEQ": seq.json()["id"], "$JOB": job.json()["id"]}


def snapshot(client: TestClient, data_dir: Path) -> tuple[dict[str, int], list[str]]:
    counts = client.app.state.service.store.counts()  # type: ignore[attr-defined]
    files = sorted(
        str(p.relative_to(data_dir))
        for p in data_dir.rglob("*")
        if p.name not in ("strep.db", "strep.db-wal", "strep.db-shm")
    )
    return counts, files


def substitute(value: Any, ids: dict[str, str]) -> Any:
    if isinstance(value, str):
        for key, real in ids.items():
            value = value.replace(key, real)
        return value
    if isinstance(value, bytes):
        for key, real in ids.items():
            value = value.replace(key.encode(), real.encode())
        return value
    if isinstance(value, dict):
        return {k: substitute(v, ids) for k, v in value.items()}
    return value


def test_the_table_is_large_enough() -> None:
    assert len(CASES) >= 20
    assert len({c.id for c in CASES}) == len(CASES)


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_request(case: Bad, env: tuple[TestClient, Path, dict[str, str]]) -> None:
    client, data_dir, ids = env
    before = snapshot(client, data_dir)
    kwargs = {k: substitute(v, ids) for k, v in case.kwargs.items()}
    r = client.request(case.method, substitute(case.url, ids), **kwargs)
    assert r.status_code == case.status, r.text
    body = r.json()
    assert isinstance(body["detail"], str), body
    assert case.message in body["detail"], body["detail"]
    assert str(data_dir) not in json.dumps(body), "server paths leak into the message"
    assert snapshot(client, data_dir) == before, "a bad request left something behind"


# ---- issue 17: checks before any route reads the request ------------------------------------


def asgi_post(app: Any, path: str, *, chunks: int, chunk: bytes, headers: dict[str, str]) -> tuple[int, int]:
    """POST ``chunks`` copies of ``chunk`` straight to the ASGI ``app`` (no lifespan).

    Returns the answer's status and how many chunks the application read.
    """
    read = 0

    async def receive() -> dict[str, Any]:
        nonlocal read
        if read < chunks:
            read += 1
            return {"type": "http.request", "body": chunk, "more_body": read < chunks}
        return {"type": "http.disconnect"}

    statuses: list[int] = []

    async def send(message: dict[str, Any]) -> None:
        if message["type"] == "http.response.start":
            statuses.append(message["status"])

    scope = {
        "type": "http",
        "asgi": {"version": "3.0"},
        "http_version": "1.1",
        "method": "POST",
        "scheme": "http",
        "path": path,
        "raw_path": path.encode(),
        "query_string": b"",
        "root_path": "",
        "headers": [(k.lower().encode(), v.encode()) for k, v in {"Host": "127.0.0.1:8000", **headers}.items()],
        "client": ("127.0.0.1", 40000),
        "server": ("127.0.0.1", 8000),
    }
    asyncio.run(app(scope, receive, send))
    return statuses[0], read


CHUNK = bytes(64 * 1024)
JSON = {"Content-Type": "application/json"}


def test_token_is_checked_before_the_body_is_read(tmp_path: Path) -> None:
    app = create_app(Settings(data_dir=tmp_path, api_token="s3cret"))
    status, read = asgi_post(app, "/api/jobs", chunks=64, chunk=CHUNK, headers=JSON)
    assert (status, read) == (401, 0)
    status, read = asgi_post(app, "/api/sequences", chunks=64, chunk=CHUNK, headers={"Content-Type": "multipart/x"})
    assert (status, read) == (401, 0)


def test_body_limit_applies_before_parsing(tmp_path: Path) -> None:
    app = create_app(Settings(data_dir=tmp_path, max_body_bytes=256 * 1024))
    declared = {**JSON, "Content-Length": str(300 * 1024 * 1024)}
    assert asgi_post(app, "/api/jobs", chunks=64, chunk=CHUNK, headers=declared) == (413, 0)
    status, read = asgi_post(app, "/api/jobs", chunks=64, chunk=CHUNK, headers=JSON)  # chunked, no length
    assert status == 413
    assert read == 256 * 1024 // len(CHUNK) + 1  # stopped at the limit, not at the end of the body
    bogus = {**JSON, "Content-Length": "9" * 5000}
    assert asgi_post(app, "/api/jobs", chunks=1, chunk=b"{}", headers=bogus) == (400, 0)


def test_factory_refuses_like_strep_serve(tmp_path: Path) -> None:
    with pytest.raises(InsecureSettings, match=r"refusing to listen on 0\.0\.0\.0: set STREP_API_TOKEN"):
        create_app(Settings(data_dir=tmp_path, host="0.0.0.0"))
    create_app(Settings(data_dir=tmp_path, host="0.0.0.0", api_token="t"))  # with a token it is allowed


def test_without_a_token_only_this_machine_is_answered(tmp_path: Path) -> None:
    """``uvicorn --factory app.main:create_app --host 0.0.0.0`` binds off loopback: requests from
    other machines are refused per connection, with a token they are served."""
    app = create_app(Settings(data_dir=tmp_path / "open"))
    with TestClient(app, client=("203.0.113.7", 40000)) as remote:
        for url in ("/api/health", "/", "/openapi.json"):
            r = remote.get(url)
            assert r.status_code == 403, (url, r.text)
            assert "has no STREP_API_TOKEN, so it answers only on this machine" in r.json()["detail"]
    with TestClient(app, client=("::ffff:198.51.100.2", 40000)) as mapped:
        assert mapped.get("/api/health").status_code == 403
    with TestClient(app, client=("127.0.0.1", 40000)) as local:
        assert local.get("/api/health").status_code == 200
    with TestClient(app, client=("::1", 40000)) as local6:
        assert local6.get("/api/health").status_code == 200
    secured = create_app(Settings(data_dir=tmp_path / "secured", host="0.0.0.0", api_token="s3cret"))
    with TestClient(secured, client=("203.0.113.7", 40000)) as remote:
        assert remote.get("/api/health").status_code == 401
        assert remote.get("/api/health", headers={"Authorization": "Bearer s3cret"}).status_code == 200


def test_loopback_hosts_and_origins_are_accepted(env: tuple[TestClient, Path, dict[str, str]]) -> None:
    client, _, _ = env
    for host in ("localhost:8000", "127.0.0.1", "127.0.0.1:8000", "[::1]:8000", "LOCALHOST"):
        assert client.get("/api/health", headers={"Host": host}).status_code == 200, host
    for origin in ("http://localhost:8000", "http://127.0.0.1:5173", "http://[::1]:8000"):
        r = client.get("/api/health", headers={"Origin": origin})
        assert r.status_code == 200, origin


def test_viewer_websocket_refuses_cross_site_origins(tmp_path: Path) -> None:
    import viser
    import websockets.exceptions
    import websockets.sync.client as wsc

    settings = Settings(data_dir=tmp_path, viewer_enabled=True, viewer_port=0)
    with TestClient(create_app(settings)) as client:
        port = client.get("/api/health").json()["viewer_port"]
        url = f"ws://127.0.0.1:{port}"
        protocol = [f"viser-v{viser.__version__}"]

        def received(origin: str) -> tuple[int, int | None]:
            """Bytes the viewer sent a client from ``origin``, and its close code (None: still open)."""
            got = 0
            with wsc.connect(url, subprotocols=protocol, additional_headers={"Origin": origin}) as ws:
                try:
                    while True:
                        got += len(ws.recv(timeout=2))
                except TimeoutError:
                    return got, None
                except websockets.exceptions.ConnectionClosed as exc:
                    return got, exc.rcvd.code if exc.rcvd else None

        assert received("http://evil.example") == (0, 1008)
        got, code = received(f"http://127.0.0.1:{port}")
        assert code is None and got > 0  # the viewer's own page is served


def test_a_killed_reader_leaves_no_extraction_behind(tmp_path: Path) -> None:
    """Archives are extracted in the data directory's swept folder, emptied when the reader is
    killed (its timeout) and at start-up; never in the system's temporary folder."""
    import multiprocessing
    import threading

    from app.services.sequences import ReaderProcess

    ascii_ply = ply_bytes(np.zeros((3_000_000, 3)))  # about 20 MB, slow to parse: the reader is busy
    archive = tmp_path / "slow.zip"
    archive.write_bytes(zip_bytes({"a.ply": ascii_ply, "b.ply": ascii_ply}))
    extract_dir = tmp_path / "data" / "uploads" / ".extract" / "reader"
    extract_dir.mkdir(parents=True)
    reader = ReaderProcess(multiprocessing.get_context("spawn"), plugins=[], timeout=600, extract_dir=extract_dir)
    errors: list[Exception] = []

    def read() -> None:
        try:
            reader.read(archive, None, 1 << 30)
        except Exception as exc:
            errors.append(exc)

    thread = threading.Thread(target=read)
    thread.start()
    try:
        deadline = time.monotonic() + 120
        while not list(extract_dir.glob("strep-zip-*/*")):
            assert thread.is_alive(), "the read ended before its extraction was seen in the data directory"
            assert time.monotonic() < deadline, "no extraction appeared in the data directory"
            time.sleep(0.01)
        assert reader._proc is not None
        reader._proc.kill()  # what the read timeout does
        thread.join(60)
    finally:
        reader.close()
    assert errors and "the reader process was killed by signal SIGKILL" in str(errors[0])
    assert list(extract_dir.iterdir()) == []


def test_startup_sweeps_leftover_extractions(tmp_path: Path) -> None:
    leftover = tmp_path / "uploads" / ".extract" / "reader" / "strep-zip-old"
    leftover.mkdir(parents=True)
    (leftover / "frame.ply").write_bytes(b"x" * 1000)
    with TestClient(create_app(Settings(data_dir=tmp_path))) as client:
        assert client.get("/api/health").status_code == 200
        assert not leftover.exists()


# ---- issue 17 item 1: uploads wait for the reader off the server's threads -------------------


def test_a_full_upload_queue_answers_429_and_health_never_waits(tmp_path: Path) -> None:
    """The reader blocks on an event: one upload is being read, one waits in the queue; a third
    is refused at once (429, Retry-After) while health and reads still answer. Once the reader
    is released both uploads are kept and the queue has room again."""
    import threading

    settings = Settings(data_dir=tmp_path, max_pending_uploads=2, viewer_enabled=False)
    entered, release = threading.Event(), threading.Event()

    def blocked_read(path: Path, selection: str | None, *limits: Any) -> dict[str, Any]:
        entered.set()
        assert release.wait(120), "the test never released the reader"
        return {"name": "x", "frames": FRAMES, "dims": 2, "points": FRAMES * 32, "unit": "m", "has_ground_truth": True}

    with TestClient(create_app(settings)) as client:
        sequences = client.app.state.service.sequences  # type: ignore[attr-defined]
        sequences.reader.read = blocked_read
        answers: dict[str, int] = {}

        def post(name: str) -> None:
            answers[name] = client.post("/api/sequences", files={"file": (f"{name}.npz", GOOD_NPZ)}).status_code

        first = threading.Thread(target=post, args=("first",))
        first.start()
        assert entered.wait(60), "the first upload never reached the reader"
        second = threading.Thread(target=post, args=("second",))
        second.start()
        deadline = time.monotonic() + 60
        while sequences.pending_uploads < 2:
            assert time.monotonic() < deadline, "the second upload was never queued"
            time.sleep(0.01)
        try:
            refused = client.post("/api/sequences", files={"file": ("third.npz", GOOD_NPZ)})
            assert refused.status_code == 429, refused.text
            assert "too many uploads at once: 2 are being received or read" in refused.json()["detail"]
            assert int(refused.headers["Retry-After"]) > 0
            assert client.get("/api/health").status_code == 200
            assert client.get("/api/methods").status_code == 200
            assert client.get("/api/sequences").status_code == 200
            assert first.is_alive() and second.is_alive()
        finally:
            release.set()
            first.join(60)
            second.join(60)
        assert answers == {"first": 201, "second": 201}
        assert sequences.pending_uploads == 0
        assert client.post("/api/sequences", files={"file": ("fourth.npz", GOOD_NPZ)}).status_code == 201
        assert not list(sequences.tmp_dir.iterdir()), "a temporary upload was left behind"


# ---- issue 17 item 10: downloads with a token ---------------------------------------------------


def test_result_files_need_the_token_and_name_themselves(tmp_path: Path) -> None:
    """What the page's token-aware download relies on: the file needs the bearer header (a plain
    link gets 401) and the answer names the file (Content-Disposition), read by the page's fetch."""
    settings = Settings(data_dir=tmp_path, api_token="s3cret", viewer_enabled=False)
    auth = {"Authorization": "Bearer s3cret"}
    with TestClient(create_app(settings)) as client:
        job = client.post("/api/jobs", json={"sequence_id": "sample:sim2d-small", "method": "identity"}, headers=auth)
        assert job.status_code == 201, job.text
        url = f"/api/jobs/{job.json()['id']}"
        deadline = time.monotonic() + 120
        while client.get(url, headers=auth).json()["status"] != "succeeded":
            assert time.monotonic() < deadline, "the job did not finish"
            time.sleep(0.05)
        for name in ("metrics.json", "trajectory.tum"):
            plain = client.get(f"{url}/files/{name}")
            assert plain.status_code == 401, plain.text
            assert plain.headers["www-authenticate"].startswith("Bearer")
            assert client.get(f"{url}/files/{name}?token=s3cret").status_code == 401  # never in a URL
            got = client.get(f"{url}/files/{name}", headers=auth)
            assert got.status_code == 200, got.text
            assert got.headers["content-disposition"] == f'attachment; filename="{name}"'


# ---- issue 17 item 12: the schema says what the service does -----------------------------------


def test_error_answers_are_documented_as_json(env: tuple[TestClient, Path, dict[str, str]]) -> None:
    """Every documented 4xx/5xx of every operation is JSON, the event stream's included (FastAPI
    gave its 400 and 404 the stream's media type), and the stream's 404 is what it documents."""
    client, _, ids = env
    schema = client.get("/openapi.json").json()
    for path, operations in schema["paths"].items():
        for method, op in operations.items():
            for status, answer in op["responses"].items():
                if status[0] in "45":
                    assert list(answer.get("content", {})) == ["application/json"], (method, path, status)
    missing = client.get("/api/jobs/job_missing/events")
    assert missing.status_code == 404
    assert missing.headers["content-type"] == "application/json"
    assert missing.json() == {"detail": "job 'job_missing' not found"}
    header = schema["paths"]["/api/jobs/{job_id}/events"]["get"]["parameters"][2]
    assert header["in"] == "header" and header["schema"]["type"] == "string"  # not nullable: no "null" sent
    assert client.get(f"/api/jobs/{ids['$JOB']}/events", headers={"Last-Event-ID": "9" * 18}).status_code == 200


def test_method_not_allowed_names_every_method(env: tuple[TestClient, Path, dict[str, str]]) -> None:
    """A 405's Allow lists every method of the path, not only the first route's."""
    client, _, _ = env
    for method, url, allow in (
        ("OPTIONS", "/api/sequences", "GET, POST"),
        ("PUT", "/api/jobs/job_x", "DELETE, GET"),
        ("PATCH", "/api/jobs", "GET, POST"),
        ("POST", "/api/health", "GET"),
    ):
        r = client.request(method, url)
        assert r.status_code == 405, (method, url, r.text)
        assert r.headers["allow"] == allow, (method, url)


# ---- issue 17 item 13: nothing that can wait runs on the event loop ------------------------------


def test_the_store_is_never_called_on_the_event_loop(tmp_path: Path) -> None:
    """Every SQLite call of the routes runs on a worker thread, never on the event loop that
    serves all requests and event streams (the latencies themselves are measured by
    benchmarks/load_api.py, not asserted here)."""
    import functools
    import inspect

    on_loop: list[str] = []

    def off_the_loop(name: str, method: Any) -> Any:
        @functools.wraps(method)
        def wrapper(*args: Any, **kwargs: Any) -> Any:
            try:
                asyncio.get_running_loop()
                on_loop.append(name)
            except RuntimeError:  # no loop running in this thread
                pass
            return method(*args, **kwargs)

        return wrapper

    settings = Settings(data_dir=tmp_path, viewer_enabled=False)
    with TestClient(create_app(settings)) as client:
        store = client.app.state.service.store  # type: ignore[attr-defined]
        for name, method in inspect.getmembers(store, inspect.ismethod):
            if not name.startswith("_"):
                setattr(store, name, off_the_loop(name, method))
        seq = client.post("/api/sequences", files={"file": ("good.npz", GOOD_NPZ)})
        assert seq.status_code == 201, seq.text
        job = client.post("/api/jobs", json={"sequence_id": seq.json()["id"], "method": "identity"})
        assert job.status_code == 201, job.text
        url = f"/api/jobs/{job.json()['id']}"
        events = client.get(f"{url}/events")  # follows the job live to its end, then returns
        assert events.status_code == 200 and "succeeded" in events.text
        for path in ("/api/health", "/api/methods", "/api/sequences", "/api/jobs", url, f"{url}/events"):
            assert client.get(path).status_code == 200, path
        assert client.get(f"{url}/files/metrics.json").status_code == 200
        cmp = client.post("/api/comparisons", json={"sequence_id": seq.json()["id"], "methods": ["identity"]})
        assert cmp.status_code == 201, cmp.text
        assert client.get(f"/api/comparisons/{cmp.json()['id']}").status_code == 200
        assert client.delete(f"/api/sequences/{seq.json()['id']}").status_code in (204, 409)
    assert on_loop == []


def test_a_read_takes_at_most_one_thread(
    env: tuple[TestClient, Path, dict[str, str]], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The read routes hand at most one call to the thread pool (their store read): on a busy
    machine every hop waits for a thread to be scheduled, and a plain ``def`` dependency or
    route costs one or two each (a request took up to five before)."""
    import anyio.to_thread

    client, _, ids = env
    hops: list[str] = []
    run_sync = anyio.to_thread.run_sync

    async def counted(func: Any, *args: Any, **kwargs: Any) -> Any:
        hops.append(getattr(func, "__qualname__", None) or repr(func))
        return await run_sync(func, *args, **kwargs)

    monkeypatch.setattr(anyio.to_thread, "run_sync", counted)
    for path, most in (
        ("/api/health", 1),
        ("/api/methods", 0),
        ("/api/sequences", 1),
        ("/api/sequences/$SEQ", 1),
        ("/api/jobs?limit=20", 1),
        ("/api/jobs/$JOB", 1),
    ):
        hops.clear()
        r = client.get(substitute(path, ids))
        assert r.status_code == 200, (path, r.text)
        assert len(hops) <= most, (path, hops)
