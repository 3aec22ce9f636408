"""Reading run logs back (complete, or cut short by a killed process).

:func:`read_log` reads an MCAP run log record by record and stops at the first byte that
does not make a whole record (a truncated or damaged file), keeping everything before
it and flagging ``complete=False``. Protobuf messages (Foxglove schemas) are decoded with
mcap-protobuf-support, JSON messages into Python values;
:meth:`RunLogContents.documents` reads the engine's documents back typed
(:mod:`nanoasm.executor.documents`). :func:`last_checkpoint` gives the last procedure
state a run logged, for resuming it.

Chunks are decompressed here, not by the mcap library: a chunk's record states its
uncompressed size, which is checked against :data:`MAX_CHUNK_BYTES` (and the log's running
total against :data:`MAX_LOG_BYTES`) before anything is decompressed, and decompression
stops at the stated size. A chunk beyond a limit is an InputError naming the file (a zstd
bomb of a few hundred kB claiming 6 GB ends in one line, not in 6 GB of memory); a chunk
whose data do not match its stated size or CRC is damage, and ends the readable prefix.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nanoasm.errors import InputError

from .documents import CHANNELS, CHECKPOINT, CheckpointDoc, DocumentError, document_from_dict

MAGIC = b"\x89MCAP0\r\n"
#: Largest uncompressed size of one chunk read (128 MiB). The run log's writer closes a
#: chunk at about 1 MiB, or holds one larger message in it: the largest is a full scan's
#: ``/scan`` grid, 64 MiB for 4096 x 4096 pixels (float32), the most an image may have.
MAX_CHUNK_BYTES = 128 * 1024 * 1024
#: Largest uncompressed size of all chunks of one log together (1 GiB): about a
#: thousand times a bundled example's dry-run log, and a few seconds of decompression.
MAX_LOG_BYTES = 1024 * 1024 * 1024
#: Read from a decompressor at a time (bytes), so that what is held is what came out.
_PIECE = 1024 * 1024


@dataclass(frozen=True)
class LogMessage:
    """One logged message: topic, schema name, instrument time (s) and decoded data (a
    dict for JSON channels, a protobuf message for Foxglove schemas)."""

    topic: str
    schema: str
    t: float
    data: Any


@dataclass
class RunLogContents:
    """What a run log holds, as far as it could be read."""

    path: str
    messages: list[LogMessage] = field(default_factory=list)
    channels: dict[str, str] = field(default_factory=dict)        # topic -> schema name
    attachments: dict[str, bytes] = field(default_factory=dict)   # name -> data (the last of a name)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False
    problem: str | None = None          # why reading stopped early (None when complete)
    size: int = 0                       # bytes in the file
    read_bytes: int = 0                 # bytes up to the last whole record

    def topic(self, name: str) -> list[LogMessage]:
        """The messages of a topic, in log order."""
        return [m for m in self.messages if m.topic == name]

    def last(self, name: str) -> LogMessage | None:
        found = self.topic(name)
        return found[-1] if found else None

    def documents(self, *topics: str, notes: list[str] | None = None) -> list[tuple[str, Any]]:
        """The documents of the engine's ``topics`` (on their channels,
        :data:`~nanoasm.executor.documents.CHANNELS`) read back typed, as (topic, document)
        in log order. A message that is not its topic's document is an InputError naming
        the file, the channel and the key; with ``notes``, it is skipped and told there."""
        unknown = [t for t in topics if t not in CHANNELS]
        if unknown:
            raise ValueError(f"no JSON channel keeps {', '.join(unknown)}; one of {', '.join(CHANNELS)}")
        by_channel = {CHANNELS[t]: t for t in topics}
        out = []
        for m in self.messages:
            topic = by_channel.get(m.topic)
            if topic is None:
                continue
            try:
                out.append((topic, document_from_dict(topic, m.data)))
            except DocumentError as err:
                if notes is None:
                    raise InputError(self.path, m.topic, f"at t = {m.t:.3f} s: {err}") from None
                notes.append(f"{m.topic} at t = {m.t:.3f} s skipped: {err}")
        return out

    def attachment_json(self, name: str) -> Any:
        """An attachment parsed as JSON, or None (missing or unreadable)."""
        raw = self.attachments.get(name)
        if raw is None:
            return None
        try:
            return json.loads(raw)
        except ValueError:
            return None

    @property
    def end_time(self) -> float | None:
        """Latest instrument time of any message (s)."""
        return max((m.t for m in self.messages), default=None)


class _Counting:
    """A binary file wrapper counting the bytes read (where reading stopped)."""

    def __init__(self, fh):
        self.fh = fh
        self.count = 0

    def read(self, n: int = -1) -> bytes:
        data = self.fh.read(n)
        self.count += len(data)
        return data

    def readinto(self, b) -> int:  # pragma: no cover - StreamReader uses read()
        n = self.fh.readinto(b)
        self.count += n or 0
        return n


def _records(fh: _Counting, size: int, src: str) -> Iterator[Any]:
    """The log's records in order, the records of each chunk in place of the chunk."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    # a record cannot be longer than the file: a garbled length stops the reading
    records = StreamReader(fh, validate_crcs=True, record_size_limit=max(size, 1), emit_chunks=True).records
    total = 0
    while True:
        start = fh.count
        try:
            rec = next(records)
        except StopIteration:
            return
        if not isinstance(rec, Chunk):
            yield rec
            continue
        claim = rec.uncompressed_size
        if claim > MAX_CHUNK_BYTES:
            raise InputError(src, None, f"the chunk at byte {start} claims {claim} bytes uncompressed; at most "
                                        f"{MAX_CHUNK_BYTES} (MAX_CHUNK_BYTES, 128 MiB) are read")
        total += claim
        if total > MAX_LOG_BYTES:
            raise InputError(src, None, f"the chunks up to byte {fh.count} hold {total} bytes uncompressed; at "
                                        f"most {MAX_LOG_BYTES} (MAX_LOG_BYTES, 1 GiB) are read")
        data = _decompress(rec)
        if rec.uncompressed_crc != 0 and zlib.crc32(data) != rec.uncompressed_crc:
            raise ValueError(f"crc validation failed in Chunk, expected: {rec.uncompressed_crc}, "
                             f"calculated: {zlib.crc32(data)}")
        yield from _chunk_records(data)


def _chunk_records(data: bytes) -> Iterator[Any]:
    """The records of a decompressed chunk. Only schemas, channels and messages may be
    in a chunk (the MCAP specification): anything else is damage, which also stops a
    chunk of zeros (opcode 0, reserved) from being read as millions of empty records."""
    import io

    from mcap.data_stream import ReadDataStream
    from mcap.opcode import Opcode
    from mcap.records import Channel, Message, Schema

    stream = ReadDataStream(io.BytesIO(data))
    end = len(data)
    while stream.count < end:
        opcode = stream.read1()
        length = stream.read8()
        start = stream.count
        if length > end - start:
            raise ValueError(f"a record in a chunk runs {length - (end - start)} byte(s) past the chunk's end")
        if opcode == Opcode.MESSAGE:
            rec = Message.read(stream, length)
        elif opcode == Opcode.CHANNEL:
            rec = Channel.read(stream)
        elif opcode == Opcode.SCHEMA:
            rec = Schema.read(stream)
        else:
            raise ValueError(f"a record of opcode 0x{opcode:02x} in a chunk (only schemas, channels and "
                             "messages may be there)")
        padding = length - (stream.count - start)
        if padding < 0:
            raise ValueError("a record in a chunk is longer than its stated length")
        stream.read(padding)
        yield rec


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
                piece = reader.read(min(_PIECE, expected + 1 - len(out)))
                if not piece:
                    break
                out += piece
    elif chunk.compression == "lz4":
        import lz4.frame

        dec = lz4.frame.LZ4FrameDecompressor()
        piece = dec.decompress(chunk.data, max_length=min(_PIECE, expected + 1))
        while piece:
            out += piece
            if len(out) > expected or dec.eof:
                break
            piece = dec.decompress(b"", max_length=min(_PIECE, expected + 1 - len(out)))
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression[:20]!r}")
    if len(out) != expected:
        more = "more" if len(out) > expected else f"{len(out)}"
        raise ValueError(f"a chunk decompresses to {more} bytes, not the {expected} it states")
    return bytes(out)


def read_log(path: str | os.PathLike, *, topics: set[str] | None = None) -> RunLogContents:
    """Read ``path`` as far as it goes; ``topics`` limits which messages are decoded.

    Raises :class:`InputError` when the file is missing, empty or not an MCAP file at all,
    or holds a chunk beyond :data:`MAX_CHUNK_BYTES` (or chunks beyond :data:`MAX_LOG_BYTES`);
    a file cut short anywhere after its first bytes is read up to the cut.
    """
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
    from mcap_protobuf.decoder import DecoderFactory

    src = str(path)
    p = Path(path)
    if not p.exists():
        raise InputError(src, None, "no such file")
    if p.is_dir():
        raise InputError(src, None, "is a directory, not a file")
    out = RunLogContents(src)
    try:
        out.size = p.stat().st_size
        fh = open(p, "rb")
    except OSError as exc:
        raise InputError(src, None, f"cannot read: {exc.strerror or exc}") from None
    with fh:
        head = fh.read(len(MAGIC))
        if not head:
            raise InputError(src, None, "file is empty (the run wrote nothing)")
        if not MAGIC.startswith(head):
            raise InputError(src, None, "not an MCAP run log (bad magic bytes)")
        if len(head) < len(MAGIC):
            out.problem = "the log ends inside its first bytes"
            out.read_bytes = len(head)
            return out
        fh.seek(0)
        counting = _Counting(fh)
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        decoders: dict[int, Any] = {}
        protobuf = DecoderFactory()
        try:
            for rec in _records(counting, out.size, src):
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                    schema = schemas.get(rec.schema_id)
                    out.channels[rec.topic] = schema.name if schema is not None else ""
                elif isinstance(rec, Message):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        raise ValueError(f"message on unknown channel {rec.channel_id}")
                    if topics is not None and ch.topic not in topics:
                        continue
                    schema = schemas.get(ch.schema_id)
                    out.messages.append(LogMessage(ch.topic, schema.name if schema else "", rec.log_time / 1e9,
                                                   _decode(ch, schema, rec.data, decoders, protobuf)))
                elif isinstance(rec, Attachment):
                    out.attachments[rec.name] = bytes(rec.data)
                elif isinstance(rec, Metadata):
                    out.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    out.complete = True
                out.read_bytes = counting.count
            out.read_bytes = counting.count      # the closing magic bytes
        except InputError:
            raise                                # a limit passed: refused, not read in part
        except Exception as exc:  # noqa: BLE001 - any bad byte ends the readable prefix
            out.complete = False
            out.problem = _problem(exc, counting.count, out.size)
    if out.complete and out.read_bytes < out.size:
        out.complete, out.problem = False, f"{out.size - out.read_bytes} stray byte(s) after the footer"
    return out


def _problem(exc: Exception, at: int, size: int) -> str:
    if at >= size:
        return f"the log ends mid-record at byte {size}"
    return f"unreadable from byte {at} of {size}: {type(exc).__name__}: {exc}"[:300]


def _decode(channel, schema, data: bytes, decoders: dict, protobuf) -> Any:
    enc = channel.message_encoding
    if enc == "json":
        return json.loads(bytes(data))
    if enc == "protobuf":
        fn = decoders.get(channel.id)
        if fn is None:
            fn = decoders[channel.id] = protobuf.decoder_for(enc, schema)
        if fn is None:
            raise ValueError(f"no protobuf schema for {channel.topic}")
        return fn(bytes(data))
    return bytes(data)


def last_checkpoint(path: str | os.PathLike) -> CheckpointDoc | None:
    """The last checkpoint a run logged (the procedure's state, as it was), or None;
    InputError when a logged checkpoint is not one."""
    docs = read_log(path, topics={CHANNELS[CHECKPOINT]}).documents(CHECKPOINT)
    return docs[-1][1] if docs else None
