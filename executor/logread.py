"""Reading run logs back (complete, cut short by a killed process, or damaged).

:func:`read_log` reads an MCAP run log record by record (:mod:`.log_records`): it keeps
everything up to where the file was cut (a killed run), and reads on past a damaged part
(a chunk whose data do not match its stated size or CRC, a garbled length), which it
skips and tells in :attr:`RunLogContents.damage`: the bytes, and the instrument times
between which what was logged is lost. Either way ``complete`` is False. Protobuf
messages (Foxglove schemas) are decoded with mcap-protobuf-support, JSON messages into
Python values; :meth:`RunLogContents.documents` reads the engine's documents back typed
(:mod:`nanoasm.executor.documents`). :func:`last_checkpoint` gives the last procedure
state a run logged, for resuming it.

A chunk's record states its uncompressed size, which is checked against
:data:`MAX_CHUNK_BYTES` (and the log's running total against :data:`MAX_LOG_BYTES`)
before anything is decompressed, and decompression stops at the stated size. A chunk
beyond a limit is an InputError naming the file (a zstd bomb of a few hundred kB
claiming 6 GB ends in one line, not in 6 GB of memory).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from nanoasm.errors import InputError

from .documents import CHANNELS, CHECKPOINT, CheckpointDoc, DocumentError, document_from_dict
from .log_records import MAGIC, Damage, RecordReader

#: Largest uncompressed size of one chunk read (128 MiB). The run log's writer closes a
#: chunk at about 1 MiB, or holds one larger message in it: the largest is a full scan's
#: ``/scan`` grid, 64 MiB for 4096 x 4096 pixels (float32), the most an image may have.
MAX_CHUNK_BYTES = 128 * 1024 * 1024
#: Largest uncompressed size of all chunks of one log together (1 GiB): about a
#: thousand times a bundled example's dry-run log, and a few seconds of decompression.
MAX_LOG_BYTES = 1024 * 1024 * 1024


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
    complete: bool = False              # the whole file read, footer and all, nothing damaged
    problem: str | None = None          # what is not whole: damage, the cut (None when complete)
    size: int = 0                       # bytes in the file
    read_bytes: int = 0                 # bytes up to the last whole record read (the closing magic)
    damage: list[Damage] = field(default_factory=list)    # parts skipped, in file order
    skipped: list[str] = field(default_factory=list)      # messages that did not decode, and why
    cut: str | None = None              # why the reading ended before the footer (None: it did not)

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

    def warnings(self) -> list[str]:
        """One line per damaged part skipped, naming the file: its bytes and what is lost."""
        return [f"{self.path}: {d.line()}" for d in self.damage]

    @property
    def end_time(self) -> float | None:
        """Latest instrument time of any message (s)."""
        return max((m.t for m in self.messages), default=None)


def read_log(path: str | os.PathLike, *, topics: set[str] | None = None) -> RunLogContents:
    """Read ``path`` as far as it goes; ``topics`` limits which messages are decoded.

    Raises :class:`InputError` when the file is missing, empty or not an MCAP file at all,
    or holds a chunk beyond :data:`MAX_CHUNK_BYTES` (or chunks beyond :data:`MAX_LOG_BYTES`);
    a file cut short anywhere after its first bytes is read up to the cut, and a damaged
    part is skipped (:attr:`RunLogContents.damage`) and the reading goes on after it.
    """
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
            out.problem = out.cut = "the log ends inside its first bytes"
            out.read_bytes = len(head)
            return out
        reader = RecordReader(fh, out.size, src, max_chunk=MAX_CHUNK_BYTES, max_total=MAX_LOG_BYTES)
        _gather(out, reader, topics)
    out.read_bytes = reader.read_to if reader.footer_end is None else reader.footer_end + len(MAGIC)
    _finish(out, reader.cut, reader.mismatch)
    return out


def _gather(out: RunLogContents, reader: RecordReader, topics: set[str] | None) -> None:
    """The reader's records into ``out``; each damaged part stamped with the times of
    the messages either side of it."""
    from mcap.records import Attachment, Channel, Footer, Message, Metadata, Schema
    from mcap_protobuf.decoder import DecoderFactory

    schemas: dict[int, Any] = {}
    channels: dict[int, Any] = {}
    decoders: dict[int, Any] = {}
    protobuf = DecoderFactory()
    last_t, waiting = None, []        # the latest message's time; damage awaiting the next one's
    for rec in reader.records():
        if isinstance(rec, Damage):
            rec.after = last_t
            out.damage.append(rec)
            waiting.append(rec)
        elif isinstance(rec, Schema):
            schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            channels[rec.id] = rec
            schema = schemas.get(rec.schema_id)
            out.channels[rec.topic] = schema.name if schema is not None else ""
        elif isinstance(rec, Message):
            last_t = rec.log_time / 1e9
            for d in waiting:
                d.before = last_t
            waiting = []
            _message(out, rec, channels, schemas, topics, decoders, protobuf)
        elif isinstance(rec, Attachment):
            out.attachments[rec.name] = bytes(rec.data)
        elif isinstance(rec, Metadata):
            out.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Footer):
            out.complete = True


def _message(out: RunLogContents, rec, channels: dict, schemas: dict, topics: set[str] | None,
             decoders: dict, protobuf) -> None:
    """A message kept, decoded, if its topic is asked for; one that does not decode (or
    names no channel) is skipped and told in :attr:`RunLogContents.skipped`."""
    ch = channels.get(rec.channel_id)
    t = rec.log_time / 1e9
    if ch is None:
        out.skipped.append(f"a message at t = {t:.3f} s on unknown channel {rec.channel_id}")
        return
    if topics is not None and ch.topic not in topics:
        return
    schema = schemas.get(ch.schema_id)
    try:
        data = _decode(ch, schema, rec.data, decoders, protobuf)
    except Exception as exc:  # noqa: BLE001 - one message's bytes, not the log's
        out.skipped.append(f"{ch.topic} at t = {t:.3f} s: {type(exc).__name__}: {exc}"[:200])
        return
    out.messages.append(LogMessage(ch.topic, schema.name if schema else "", t, data))


def _finish(out: RunLogContents, cut: str | None, mismatch: str | None) -> None:
    """``complete`` only for a whole, undamaged file; ``problem`` says what is not."""
    parts = [f"{len(out.damage)} damaged part(s) skipped, the first: {out.damage[0].line()}"] if out.damage else []
    if mismatch is not None:
        parts.append(mismatch)
    if out.skipped:
        parts.append(f"{len(out.skipped)} message(s) that do not decode skipped, the first: {out.skipped[0]}")
    if out.complete and out.read_bytes < out.size:
        parts.append(f"{out.size - out.read_bytes} stray byte(s) after the footer")
    if cut is not None:
        parts.append(cut)
    out.cut = cut
    out.complete = out.complete and not parts
    out.problem = "; ".join(parts) or None


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
