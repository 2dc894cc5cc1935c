"""Streaming ``multipart/form-data`` uploads, size-limited while they arrive.

The file part goes straight to a temporary file in the data directory (same file system as
its final place, so the later rename is atomic); the upload is refused as soon as it passes
the limit, without reading the rest.
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, TYPE_CHECKING

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect, Request

from strep_core.errors import FormatError
from strep_core.io import FORMATS

if TYPE_CHECKING:
    from python_multipart.multipart import MultipartCallbacks

# (suffix, format) pairs of the one-file formats (`strep_core.io.FORMATS`), longest suffix first;
# folders of frames come zipped
UPLOAD_FORMATS: tuple[tuple[str, str], ...] = tuple(
    sorted(((s, f.name) for f in FORMATS if f.one_file for s in f.files), key=lambda pair: -len(pair[0]))
)
FIELD_MAX_BYTES = 1024
MAX_PARTS = 8
TEXT_FIELDS = ("frames", "name")


class UploadError(Exception):
    """A malformed or oversized upload request (not a problem of the file's content)."""

    def __init__(self, status_code: int, detail: str, headers: dict[str, str] | None = None) -> None:
        super().__init__(detail)
        self.status_code = status_code
        self.detail = detail
        self.headers = headers


def upload_format(filename: str) -> tuple[str, str]:
    """``(suffix, format)`` of an uploaded file name; raises `FormatError` for others."""
    lower = filename.lower()
    for suffix, fmt in UPLOAD_FORMATS:
        if lower.endswith(suffix):
            return suffix, fmt
    accepted = ", ".join(s for s, _ in UPLOAD_FORMATS)
    raise FormatError(f"unknown format of {filename!r}: upload one of {accepted} (folders of PLY/PCD frames as a .zip)")


def display_name(filename: str) -> str:
    """The file name without folders, control characters or the format suffix (for listings)."""
    base = filename.replace("\\", "/").rsplit("/", 1)[-1]
    base = "".join(ch for ch in base if ch.isprintable())[:200]
    lower = base.lower()
    for suffix, _ in UPLOAD_FORMATS:
        if lower.endswith(suffix):
            return base[: -len(suffix)] or "sequence"
    return base or "sequence"


@dataclass
class ReceivedUpload:
    """An upload stored in a temporary file: the caller renames or deletes it."""

    path: Path
    filename: str
    suffix: str
    format: str
    size: int
    fields: dict[str, str] = field(default_factory=dict)


class _Parser:
    def __init__(self, tmp_dir: Path, token: str, max_bytes: int) -> None:
        self.tmp_dir = tmp_dir
        self.token = token
        self.max_bytes = max_bytes
        self.fields: dict[str, str] = {}
        self.upload: ReceivedUpload | None = None
        self.file: IO[bytes] | None = None
        self.parts = 0
        self.ended = False
        self._header_name = b""
        self._header_value = b""
        self._disposition = b""
        self._name = ""
        self._is_file = False
        self._data = bytearray()

    # python-multipart callbacks
    def on_part_begin(self) -> None:
        self.parts += 1
        if self.parts > MAX_PARTS:
            raise UploadError(422, f"too many form parts (at most {MAX_PARTS})")
        self._disposition = b""
        self._name = ""
        self._is_file = False
        self._data = bytearray()

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        name = options.get(b"name")
        if name is None:
            raise UploadError(422, "a form part has no name (Content-Disposition: form-data; name=...)")
        self._name = name.decode("utf-8", "replace")
        filename = options.get(b"filename")
        if self._name == "file":
            if filename is None:
                raise UploadError(422, "the 'file' part must be a file (with a filename)")
            if self.upload is not None:
                raise UploadError(422, "upload exactly one file in the 'file' part")
            fname = filename.decode("utf-8", "replace")
            suffix, fmt = upload_format(fname)
            path = self.tmp_dir / f"{self.token}{suffix}"
            self.file = open(path, "wb")  # noqa: SIM115 - closed in finish()/abort()
            self.upload = ReceivedUpload(
                path=path, filename=display_name(fname) + suffix, suffix=suffix, format=fmt, size=0
            )
            self._is_file = True
        elif self._name in TEXT_FIELDS:
            if filename is not None:
                raise UploadError(422, f"form field {self._name!r} must be text, not a file")
            if self._name in self.fields:
                raise UploadError(422, f"form field {self._name!r} is given twice")
        else:
            raise UploadError(422, f"unexpected form field {self._name!r}; expected 'file', 'frames' or 'name'")

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        chunk = data[start:end]
        if self._is_file:
            assert self.upload is not None and self.file is not None
            self.upload.size += len(chunk)
            if self.upload.size > self.max_bytes:
                raise UploadError(413, f"the file is larger than the limit of {self.max_bytes} bytes")
            self.file.write(chunk)
        else:
            self._data += chunk
            if len(self._data) > FIELD_MAX_BYTES:
                raise UploadError(422, f"form field {self._name!r} is longer than {FIELD_MAX_BYTES} bytes")

    def on_part_end(self) -> None:
        if self._is_file:
            assert self.file is not None
            self.file.close()
        else:
            try:
                self.fields[self._name] = self._data.decode("utf-8")
            except UnicodeDecodeError as exc:
                raise UploadError(422, f"form field {self._name!r} is not UTF-8 text") from exc

    def on_end(self) -> None:
        self.ended = True

    def callbacks(self) -> MultipartCallbacks:
        return {
            "on_part_begin": self.on_part_begin,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
            "on_end": self.on_end,
        }

    def abort(self) -> None:
        if self.file is not None:
            self.file.close()
        if self.upload is not None:
            self.upload.path.unlink(missing_ok=True)


async def receive_upload(request: Request, tmp_dir: Path, token: str, *, max_bytes: int) -> ReceivedUpload:
    """Stream the request's multipart body: the ``file`` part to ``tmp_dir``, text fields in memory.

    Raises `UploadError` (4xx) or `FormatError` (unknown file suffix); nothing is left behind.
    """
    content_type = request.headers.get("content-type", "")
    ctype, params = parse_options_header(content_type)
    if ctype != b"multipart/form-data":
        raise UploadError(415, "send the sequence as multipart/form-data with a 'file' part")
    boundary = params.get(b"boundary")
    if not boundary:
        raise UploadError(400, "the multipart Content-Type has no boundary")
    length = request.headers.get("content-length")
    if length is not None:
        try:
            declared = int(length)
        except ValueError:
            raise UploadError(400, "invalid Content-Length header") from None
        if declared > max_bytes + 64 * 1024:  # room for the multipart envelope and text fields
            raise UploadError(413, f"the upload is larger than the limit of {max_bytes} bytes")
    tmp_dir.mkdir(parents=True, exist_ok=True)
    parser = _Parser(tmp_dir, token, max_bytes)
    try:
        mp = MultipartParser(boundary, parser.callbacks())
        async for chunk in request.stream():
            if chunk:
                mp.write(chunk)
                await asyncio.sleep(0)  # a fast client's body must not hold the event loop between chunks
        mp.finalize()
        if not parser.ended:
            raise UploadError(400, "the multipart body is truncated (no closing boundary)")
        if parser.upload is None:
            raise UploadError(422, "no file: send the sequence in a form part named 'file'")
        parser.upload.fields = parser.fields
        return parser.upload
    except FormParserError as exc:
        parser.abort()
        raise UploadError(400, f"malformed multipart body ({exc})") from exc
    except ClientDisconnect:
        parser.abort()
        raise UploadError(400, "the client went away during the upload") from None
    except BaseException:
        parser.abort()
        raise
