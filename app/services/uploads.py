"""Uploads (survey videos and images, training images) streamed to their place once.

A multipart/form-data body is parsed as it arrives (`StreamedForm`): each file part is
written straight into the job's upload folder by the part's writer, which the job's
service chooses (`UploadTarget`) and which checks what it can as the bytes come (the
size limits, a file's first bytes, an image's declared size) and the rest when the part
is whole (the decode, the video's probe). Nothing is spooled to a temporary file first;
text fields are kept in memory, within small limits. `UploadsInFlight` bounds the bytes
of all the uploads this process reads at once.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from pathlib import Path
from typing import Protocol

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header

from app.core.imagecodec import PNG_MAGIC, ImageError, peek_size
from app.services import images
from app.services.errors import Busy, Invalid, ServiceError, TooLarge, UnsupportedMedia
from app.settings import Settings

#: Text fields a form may have, and the longest one (the survey's intrinsics are < 1 KiB).
MAX_TEXT_FIELDS = 32
MAX_TEXT_FIELD_BYTES = 64 * 1024
#: How many of an image's first bytes are kept to read its declared size from as it arrives.
IMAGE_HEAD_BYTES = 256 * 1024


class UploadsInFlight:
    """The bytes of the uploads this process is reading at once, each counted from its
    Content-Length when it declares one, else as its bytes arrive. A new upload is
    refused (Busy, 503) when it would take the total past `limit`; an upload alone is
    always let in (its own limit is `max_upload_bytes`)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._held = 0
        self._lock = threading.Lock()

    @property
    def held(self) -> int:
        with self._lock:
            return self._held

    def admit(self, declared: int | None) -> UploadLease:
        """A lease of `declared` bytes (0 when unknown: it grows as they arrive)."""
        lease = UploadLease(self, 0)
        lease.grow(declared or 0)
        return lease

    def _take(self, nbytes: int, held_by_lease: int) -> None:
        with self._lock:
            others = self._held - held_by_lease
            if others > 0 and self._held + nbytes > self.limit:
                raise Busy(f"uploads of {self._held} bytes are being received (the limit is {self.limit} bytes "
                           "in flight); try again shortly")
            self._held += nbytes

    def _give_back(self, nbytes: int) -> None:
        with self._lock:
            self._held -= nbytes


class UploadLease:
    """One upload's share of `UploadsInFlight`, released once when the upload is done."""

    def __init__(self, pool: UploadsInFlight, held: int) -> None:
        self._pool = pool
        self.held = held

    def grow(self, nbytes: int) -> None:
        if nbytes > 0:
            self._pool._take(nbytes, self.held)
            self.held += nbytes

    def grow_to(self, total: int) -> None:
        """Hold at least `total` bytes (a body without Content-Length, as it arrives)."""
        self.grow(total - self.held)

    def release(self) -> None:
        held, self.held = self.held, 0
        self._pool._give_back(held)


class FilePart(Protocol):
    """Where one file part of a form goes, as its bytes arrive."""

    def write(self, data: bytes) -> None: ...

    def close(self) -> None:
        """The part is whole: check it (raises a ServiceError to refuse the upload)."""

    def abort(self) -> None:
        """The upload failed while this part was open: let go of the file."""


class UploadTarget(Protocol):
    """What a route does with the file parts of its form."""

    def open_file(self, field: str) -> FilePart | None:
        """A writer for the next file part named `field`, None to skip it (an unknown
        field), or a ServiceError to refuse the upload (one file too many)."""


class StreamedForm:
    """A multipart/form-data body parsed as it arrives: file parts go to `target`'s
    writers, text fields (at most `MAX_TEXT_FIELDS` of `MAX_TEXT_FIELD_BYTES`) into
    `fields` (the last of a repeated name wins). Not thread-safe: feed it from one
    thread at a time."""

    def __init__(self, content_type: str, target: UploadTarget, max_bytes: int) -> None:
        media, options = parse_options_header(content_type)
        boundary = options.get(b"boundary")
        if media != b"multipart/form-data" or not boundary:
            raise Invalid("the body must be multipart/form-data (with a boundary)")
        self.target = target
        self.max_bytes = max_bytes
        self.received = 0
        self.fields: dict[str, str] = {}
        self._text_fields = 0
        self._disposition = b""
        self._header_name = b""
        self._header_value = b""
        self._name = ""
        self._file: FilePart | None = None
        self._is_file = False
        self._text = bytearray()
        self._ended = False
        self._parser = MultipartParser(boundary, {
            "on_part_begin": self._part_begin, "on_part_data": self._part_data, "on_part_end": self._part_end,
            "on_header_field": self._header_field, "on_header_value": self._header_value_part,
            "on_header_end": self._header_end, "on_headers_finished": self._headers_finished,
            "on_end": self._end,
        })

    def feed(self, data: bytes) -> None:
        """Parse the next bytes of the body (TooLarge past `max_bytes`)."""
        self.received += len(data)
        if self.received > self.max_bytes:
            raise TooLarge(f"upload exceeds the limit of {self.max_bytes} bytes")
        try:
            self._parser.write(data)
        except FormParserError as exc:
            raise Invalid(f"malformed multipart/form-data body: {exc}") from None

    def finish(self) -> dict[str, str]:
        """After the last byte: the text fields (Invalid if the form did not end)."""
        try:
            self._parser.finalize()
        except FormParserError as exc:
            raise Invalid(f"malformed multipart/form-data body: {exc}") from None
        if not self._ended:
            raise Invalid("the multipart/form-data body ends before its closing boundary")
        return self.fields

    def abort(self) -> None:
        """Let go of the part being written, when the upload fails."""
        if self._file is not None:
            self._file.abort()
            self._file = None

    def _part_begin(self) -> None:
        self._disposition, self._name, self._file, self._is_file = b"", "", None, False
        self._text.clear()

    def _header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def _header_value_part(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def _header_end(self) -> None:
        if self._header_name.strip().lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name, self._header_value = b"", b""

    def _headers_finished(self) -> None:
        _, options = parse_options_header(self._disposition)
        if b"name" not in options:
            raise Invalid('a form part has no name (Content-Disposition: form-data; name="...")')
        self._name = options[b"name"].decode("utf-8", "replace")
        self._is_file = b"filename" in options
        if self._is_file:
            self._file = self.target.open_file(self._name)
        else:
            self._text_fields += 1
            if self._text_fields > MAX_TEXT_FIELDS:
                raise Invalid(f"the form has more than {MAX_TEXT_FIELDS} text fields")

    def _part_data(self, data: bytes, start: int, end: int) -> None:
        if self._is_file:
            if self._file is not None:
                self._file.write(data[start:end])
            return
        self._text += data[start:end]
        if len(self._text) > MAX_TEXT_FIELD_BYTES:
            raise TooLarge(f"form field {self._name!r} exceeds {MAX_TEXT_FIELD_BYTES} bytes")

    def _part_end(self) -> None:
        if self._is_file:
            if self._file is not None:
                self._file.close()
            self._file = None
            return
        self.fields[self._name] = self._text.decode("utf-8", "replace")

    def _end(self) -> None:
        self._ended = True


class StoredFile:
    """A file part written to `path` as it arrives, within `max_bytes`; `check_head`
    sees its first `head_bytes` once they are in (or the whole file, when shorter)."""

    head_bytes = 16

    def __init__(self, path: Path, what: str, max_bytes: int) -> None:
        self.path = path
        self.what = what
        self.max_bytes = max_bytes
        self.size = 0
        self._head = bytearray()
        self._head_checked = False
        self._out = path.open("xb")

    def write(self, data: bytes) -> None:
        self.size += len(data)
        if self.size > self.max_bytes:
            raise TooLarge(f"{self.what}: exceeds the limit of {self.max_bytes} bytes")
        if not self._head_checked:
            self._head += data[: self.head_bytes - len(self._head)]
            if len(self._head) >= self.head_bytes:
                self._head_checked = True
                self.check_head(bytes(self._head), final=False)
        self._out.write(data)

    def abort(self) -> None:
        self._out.close()

    def close(self) -> None:
        self._out.close()
        if not self._head_checked:
            self._head_checked = True
            self.check_head(bytes(self._head), final=True)
        self.check_whole()

    def check_head(self, head: bytes, *, final: bool) -> None:
        """Refuse the file from its first bytes (`final`: they are all of it)."""

    def check_whole(self) -> None:
        """Refuse the file once it is whole."""


class ImagePart(StoredFile):
    """A JPEG or PNG: its signature and declared size checked as soon as they arrive,
    within `max_image_bytes`, then decoded whole (`images.decoded`, within the memory
    budget) and renamed with its format's suffix. `done` gets its (width, height)."""

    head_bytes = IMAGE_HEAD_BYTES

    def __init__(self, path: Path, what: str, settings: Settings, memory: images.MemoryBudget,
                 done: Callable[[Path, int, int], None]) -> None:
        super().__init__(path, what, settings.max_image_bytes)
        self.settings = settings
        self.memory = memory
        self.done = done
        self._size_checked = False

    def write(self, data: bytes) -> None:
        super().write(data)
        if not self._size_checked and (len(self._head) >= 8 or self._head_checked):
            self._peek(bytes(self._head))

    def _peek(self, head: bytes) -> None:
        try:
            size = peek_size(head)
        except ImageError as exc:
            raise self._refusal(exc) from None
        if size is not None:
            self._size_checked = True
            width, height = size
            if width * height > self.settings.max_image_pixels:
                raise TooLarge(f"{self.what}: the image declares {width}x{height} pixels; the limit is "
                               f"{self.settings.max_image_pixels} pixels")

    def check_head(self, head: bytes, *, final: bool) -> None:
        if not self._size_checked:
            self._peek(head)

    def check_whole(self) -> None:
        data = self.path.read_bytes()
        try:
            with images.decoded(data, self.settings, self.memory, detect=False) as gray:
                height, width = gray.shape
        except ServiceError as exc:
            exc.detail = f"{self.what}: {exc.detail}"
            raise
        final = self.path.with_suffix(".png" if data.startswith(PNG_MAGIC) else ".jpg")
        self.path.rename(final)
        self.done(final, int(width), int(height))

    def _refusal(self, exc: ImageError) -> ServiceError:
        error = UnsupportedMedia if exc.kind == "unsupported" else Invalid
        return error(f"{self.what}: {exc}")

