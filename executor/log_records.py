"""The records of an MCAP run log, one by one, reading on past a damaged part.

:class:`RecordReader` frames the file itself: a record is its opcode, its length and that
many bytes, parsed by the ``mcap`` library's record classes from those bytes alone, so a
field garbled inside a record cannot make the reading run on into the next. A record that
does not read (a chunk whose data do not decompress to its stated size or CRC, an
attachment whose CRC does not match, a field that runs past its record, an opcode no MCAP
writer uses) is :class:`Damage`: the reader reports it in place of the record and goes on

- at the end the damaged record states for itself, when a record starts there;
- else at the next record found by scanning forward that proves to be one: a chunk or an
  attachment whose lengths agree with each other to the byte and whose CRC matches, or
  the data end (opcode and its fixed length).

A run killed mid-write leaves a file without a summary section, so the reader never
relies on one (its chunk index would only say again where the chunks are). A record
stating more bytes than the file holds, with no record found after it, is where the file
was cut: the reading ends there (:attr:`RecordReader.cut`).

Chunks are decompressed here, not by the mcap library: a chunk's record states its
uncompressed size, which is checked against ``max_chunk`` (and the running total against
``max_total``) before anything is decompressed, and decompression stops at the stated
size; a chunk beyond a limit is an InputError naming the file. Candidates tried while
scanning count towards ``max_total`` too, so a file of forged chunk headers costs no
more than a log of that size.
"""

from __future__ import annotations

import io
import re
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

from nanoasm.errors import InputError

MAGIC = b"\x89MCAP0\r\n"
#: Read from a file or a decompressor at a time (bytes), so that what is held is what came out.
PIECE = 1024 * 1024
_HEAD = 9                                    # opcode (1) and length (8)
#: Compressions a chunk may state (the MCAP specification's).
_COMPRESSIONS = ("", "zstd", "lz4")
#: Opcodes where a scan for the next whole record may land: chunk, attachment, data end.
_LANDINGS = re.compile(rb"[\x06\x09\x0f]")


@dataclass
class Damage:
    """A part of a log that could not be read, skipped: bytes ``start`` to ``end`` of the
    file and why. ``after`` and ``before`` are the instrument times (s) of the last
    message read before it and the first one after it (None: there is none)."""

    start: int
    end: int
    why: str
    after: float | None = None
    before: float | None = None

    def line(self) -> str:
        """What was lost, in one line (without the file's name)."""
        if self.after is None and self.before is None:
            span = "what it held is lost"
        elif self.before is None:
            span = f"what was logged after t = {self.after:.3f} s there is lost"
        elif self.after is None:
            span = f"what was logged before t = {self.before:.3f} s there is lost"
        else:
            span = f"what was logged between t = {self.after:.3f} s and t = {self.before:.3f} s is lost"
        return f"bytes {self.start}-{self.end} unreadable ({self.why}), skipped: {span}"


class _Exact:
    """A record's bytes to parse: a read past their end is damage, never a short read."""

    def __init__(self, data: bytes):
        self._buf = io.BytesIO(data)

    def read(self, n: int = -1) -> bytes:
        out = self._buf.read(n)
        if n >= 0 and len(out) != n:
            raise ValueError("a field runs past the end of its record")
        return out


def _stream(data: bytes):
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(_Exact(data))


def _chunk_records(data: bytes) -> list[Any]:
    """The records of a decompressed chunk. Only schemas, channels and messages may be
    in a chunk (the MCAP specification): anything else is damage, which also stops a
    chunk of zeros (opcode 0, reserved) from being read as millions of empty records."""
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    out, pos, end = [], 0, len(data)
    while pos < end:
        if end - pos < _HEAD:
            raise ValueError("a chunk ends inside a record's opcode and length")
        opcode, length = data[pos], int.from_bytes(data[pos + 1:pos + _HEAD], "little")
        if length > end - pos - _HEAD:
            raise ValueError(f"a record in a chunk runs {length - (end - pos - _HEAD)} byte(s) past the chunk's end")
        body = data[pos + _HEAD:pos + _HEAD + length]
        if opcode == Opcode.MESSAGE:
            out.append(Message.read(_stream(body), length))
        elif opcode == Opcode.CHANNEL:
            out.append(Channel.read(_stream(body)))
        elif opcode == Opcode.SCHEMA:
            out.append(Schema.read(_stream(body)))
        else:
            raise ValueError(f"a record of opcode 0x{opcode:02x} in a chunk (only schemas, channels and "
                             "messages may be there)")
        pos += _HEAD + length
    return out


def _decompress(chunk) -> bytes:
    """A chunk's data decompressed, never beyond the size its record states (ValueError
    when they do not come to exactly that size)."""
    expected = chunk.uncompressed_size
    out = bytearray()
    if chunk.compression == "":
        out += chunk.data
    elif chunk.compression == "zstd":
        import zstandard

        with zstandard.ZstdDecompressor().stream_reader(chunk.data, read_across_frames=True) as reader:
            while len(out) <= expected:
                piece = reader.read(min(PIECE, expected + 1 - len(out)))
                if not piece:
                    break
                out += piece
    elif chunk.compression == "lz4":
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
        piece = dec.decompress(chunk.data, max_length=min(PIECE, expected + 1))
        while piece:
            out += piece
            if len(out) > expected or dec.eof:
                break
            piece = dec.decompress(b"", max_length=min(PIECE, expected + 1 - len(out)))
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression[:20]!r}")
    if len(out) != expected:
        more = "more" if len(out) > expected else f"{len(out)}"
        raise ValueError(f"a chunk decompresses to {more} bytes, not the {expected} it states")
    return bytes(out)


def _attachment_ok(body: bytes) -> bool:
    """Whether an attachment's lengths add up to its record's and its CRC matches."""
    try:
        name_len = struct.unpack_from("<I", body, 16)[0]
        media_len = struct.unpack_from("<I", body, 20 + name_len)[0]
        data_len = struct.unpack_from("<Q", body, 24 + name_len + media_len)[0]
    except struct.error:
        return False
    if 36 + name_len + media_len + data_len != len(body):
        return False
    crc = struct.unpack_from("<I", body, len(body) - 4)[0]
    return crc == 0 or zlib.crc32(body[:-4]) == crc


class RecordReader:
    """The records of the MCAP file open as ``fh`` (``size`` bytes, named ``src`` in
    errors), in file order: a chunk's records in place of the chunk, and a
    :class:`Damage` in place of every part that does not read. After the reading,
    :attr:`cut` says why it stopped before the footer (None: it did not), and
    :attr:`mismatch` whether the data end's CRC disagrees with bytes that every other
    check passed (an index changed, say: nothing lost, but the file is not as written)."""

    def __init__(self, fh, size: int, src: str, *, max_chunk: int, max_total: int):
        self.fh, self.size, self.src = fh, size, src
        self.max_chunk, self.max_total = max_chunk, max_total
        self.total = 0                   # bytes decompressed, or claimed by candidates tried
        self.cut: str | None = None
        self.footer_end: int | None = None   # where the footer record ends, once read
        self.read_to = len(MAGIC)            # where the last record that read ends
        self.mismatch: str | None = None
        self.damaged = False

    def _read_at(self, pos: int, n: int) -> bytes:
        self.fh.seek(pos)
        return self.fh.read(n)

    def _head(self, pos: int) -> tuple[int, int] | None:
        """(opcode, length) of the record at ``pos``, or None when the file ends first."""
        head = self._read_at(pos, _HEAD)
        return (head[0], int.from_bytes(head[1:], "little")) if len(head) == _HEAD else None

    def records(self) -> Iterator[Any]:
        from mcap.records import Footer

        pos = len(MAGIC)
        while self.footer_end is None:
            head = self._head(pos)
            if head is None:
                self.cut = (f"the log ends at byte {self.size}, after a whole record but before its footer"
                            if pos == self.size else f"the log ends mid-record at byte {self.size}")
                return
            opcode, length = head
            end = pos + _HEAD + length
            if end > self.size:
                nxt = self._next_record(pos + 1)
                if nxt is None:
                    self.cut = f"the log ends mid-record at byte {self.size}"
                    return
                yield self._damage(pos, nxt, f"a record states {length} bytes, past the end of the file")
                pos = nxt
                continue
            try:
                found = self._parse(opcode, self._read_at(pos + _HEAD, length), pos)
            except InputError:
                raise                        # a limit passed: refused, not read in part
            except Exception as exc:  # noqa: BLE001 - any bad byte is damage
                nxt = end if self._framed(end) else self._next_record(pos + 1)
                yield self._damage(pos, self.size if nxt is None else nxt, f"{type(exc).__name__}: {exc}"[:200])
                if nxt is None:
                    self.cut = f"nothing readable after byte {pos} of {self.size}"
                    return
                pos = nxt
                continue
            yield from found
            if found and isinstance(found[-1], Footer):
                self.footer_end = end
            pos = self.read_to = end

    def _damage(self, start: int, end: int, why: str) -> Damage:
        self.damaged = True
        return Damage(start, end, why)

    def _framed(self, pos: int) -> bool:
        """Whether a record of a known opcode, within the file, starts at ``pos``."""
        head = self._head(pos)
        return head is not None and 0x01 <= head[0] <= 0x0F and pos + _HEAD + head[1] <= self.size

    def _parse(self, opcode: int, body: bytes, pos: int) -> list[Any]:
        """The record(s) of one record's bytes: a chunk's records, one record, or none (an
        index or statistics, which the reader does without)."""
        from mcap.opcode import Opcode
        from mcap.records import Attachment, Channel, DataEnd, Footer, Message, Metadata, Schema

        if opcode == Opcode.CHUNK:
            return self._chunk(body, pos)
        if opcode == Opcode.ATTACHMENT:
            if not _attachment_ok(body):
                raise ValueError("the attachment's CRC or lengths do not match")
            return [Attachment.read(_stream(body))]
        if opcode == Opcode.DATA_END:
            self._check_data_section(DataEnd.read(_stream(body)), pos)
            return []
        readers = {Opcode.SCHEMA: Schema.read, Opcode.CHANNEL: Channel.read, Opcode.METADATA: Metadata.read,
                   Opcode.FOOTER: Footer.read, Opcode.MESSAGE: lambda s: Message.read(s, len(body))}
        if opcode in readers:
            rec = readers[opcode](_stream(body))
            if opcode == Opcode.FOOTER and self._read_at(pos + _HEAD + len(body), len(MAGIC)) != MAGIC:
                raise ValueError("the footer is not followed by the closing magic bytes")
            return [rec]
        if not 0x01 <= opcode <= 0x0F:
            raise ValueError(f"opcode 0x{opcode:02x}, which no MCAP record has")
        return []

    def _chunk(self, body: bytes, pos: int, *, trial: bool = False) -> list[Any]:
        from mcap.records import Chunk

        rec = Chunk.read(_stream(body))
        if len(rec.compression) + 40 + len(rec.data) != len(body):
            raise ValueError("the chunk's lengths do not add up to its record's")
        claim = rec.uncompressed_size
        if claim > self.max_chunk:
            if trial:
                raise ValueError("claims too much")
            raise InputError(self.src, None, f"the chunk at byte {pos} claims {claim} bytes uncompressed; at most "
                                             f"{self.max_chunk} (MAX_CHUNK_BYTES, 128 MiB) are read")
        self.total += claim
        if self.total > self.max_total:
            raise InputError(self.src, None, f"the chunks up to byte {pos + _HEAD + len(body)} hold {self.total} "
                                             f"bytes uncompressed; at most {self.max_total} (MAX_LOG_BYTES, 1 GiB) "
                                             "are read")
        data = _decompress(rec)
        if rec.uncompressed_crc != 0 and zlib.crc32(data) != rec.uncompressed_crc:
            raise ValueError(f"crc validation failed in Chunk, expected: {rec.uncompressed_crc}, "
                             f"calculated: {zlib.crc32(data)}")
        return _chunk_records(data)

    def _check_data_section(self, rec, pos: int) -> None:
        """The data end's CRC of everything before it (:attr:`mismatch`), when nothing
        found damaged so far explains a mismatch."""
        if rec.data_section_crc == 0 or self.damaged:
            return
        crc, at = 0, 0
        while at < pos:
            piece = self._read_at(at, min(PIECE, pos - at))
            crc, at = zlib.crc32(piece, crc), at + len(piece)
        if crc != rec.data_section_crc:
            self.mismatch = (f"the data section's CRC does not match: a byte before byte {pos} changed that "
                             "no other check caught")

    def _next_record(self, frm: int) -> int | None:
        """The first position at or after ``frm`` where a chunk or attachment that reads
        whole (lengths and CRC), or the data end, starts; None if there is none."""
        at = frm
        while at < self.size:
            window = self._read_at(at, PIECE)
            for m in _LANDINGS.finditer(window):
                if self._lands(at + m.start()):
                    return at + m.start()
            at += max(len(window), 1)
        return None

    def _lands(self, pos: int) -> bool:
        from mcap.opcode import Opcode

        head = self._head(pos)
        if head is None:
            return False
        opcode, length = head
        if pos + _HEAD + length > self.size:
            return False
        if opcode == Opcode.DATA_END:
            return length == 4
        if opcode == Opcode.ATTACHMENT:
            return length >= 36 and _attachment_ok(self._read_at(pos + _HEAD, length))
        if length < 40:
            return False
        fields = self._read_at(pos + _HEAD + 24, 8)
        comp_len = int.from_bytes(fields[4:8], "little")
        if comp_len > 4 or length < 40 + comp_len:
            return False
        body = self._read_at(pos + _HEAD, length)
        if body[32:32 + comp_len].decode("latin-1") not in _COMPRESSIONS:
            return False
        try:
            self._chunk(body, pos, trial=True)
        except InputError:
            raise
        except Exception:  # noqa: BLE001 - not a chunk after all
            return False
        return True
