"""MCAP recordings of the bus: writer, reader (with recovery of files cut short), replay, and
the line-data loader.

File layout (the Foxglove convention, so a recording opens in Foxglove as it is): one channel per
key expression (topic = key expression, no leading ``/``), ``message_encoding="json"``, each
channel's schema is the ``jsonschema`` of its pydantic model (``model_json_schema()``; a key with
no known model gets the schema ``{"type": "object"}`` named ``json_object``), ``log_time`` = plant
time ``t`` in ns, ``publish_time`` = wall-clock time of reception in ns, ``sequence`` = per-channel
message counter. Chunked (1 MiB), zstd compressed. The payload bytes are stored exactly as they
were received on the bus.
"""

from __future__ import annotations

import errno
import io
import json
import logging
import math
import threading
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import pandas as pd
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap.records import Channel, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer
from pydantic import BaseModel

from schemas import keys as keys_mod
from schemas.base import Message, json_schema

log = logging.getLogger(__name__)

UNKNOWN_SCHEMA_NAME = "json_object"
UNKNOWN_SCHEMA = {"type": "object", "title": UNKNOWN_SCHEMA_NAME}
NS = 1_000_000_000


def plant_time_ns(t: float) -> int:
    """Plant time in s -> MCAP log_time in ns (rounded to the nearest ns)."""
    if not math.isfinite(t) or t < 0:
        raise ValueError(f"t must be a finite plant time >= 0, got {t!r}")
    return int(round(t * NS))


def schema_name(model: type[BaseModel]) -> str:
    """Schema name stored in MCAP: the model's qualified name, e.g. ``schemas.messages.FeederFlow``."""
    return f"{model.__module__}.{model.__qualname__}"


# -------------------------------------------------------------------------------------------
# writer


class McapRecorder:
    """Writes bus messages to an MCAP file.

    ``write(key, payload, t)`` stores the payload bytes as they are on channel ``key``;
    ``write_message(key, msg)`` encodes a model. The file is finalized by :meth:`close` (or the
    ``with`` block); :meth:`flush` writes the open chunk to the file and is called every
    ``flush_every`` messages and every ``flush_period_s`` seconds (in :meth:`write`), so that a
    crash loses at most that much (see :func:`read_recording` for recovery).
    """

    def __init__(
        self,
        path: str | Path,
        *,
        flush_every: int = 1000,
        flush_period_s: float | None = 2.0,
        chunk_size: int = 1024 * 1024,
        compression: str = "zstd",
    ) -> None:
        if flush_every < 1:
            raise ValueError(f"flush_every must be >= 1, got {flush_every}")
        comp = {
            "zstd": CompressionType.ZSTD,
            "lz4": CompressionType.LZ4,
            "none": CompressionType.NONE,
        }
        if compression not in comp:
            raise ValueError(f"compression must be one of {sorted(comp)}, got {compression!r}")
        self.path = Path(path)
        self.flush_every = flush_every
        self.flush_period_s = flush_period_s
        self._file = open(self.path, "wb")  # noqa: SIM115 - closed in close()
        self._writer = Writer(self._file, chunk_size=chunk_size, compression=comp[compression])
        self._writer.start(profile="", library="powder-twin")
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: dict[str, int] = defaultdict(int)
        self.counts: Counter[str] = Counter()
        self._since_flush = 0
        self._last_flush = time.monotonic()
        self._closed = False

    def _schema_id(self, name: str, schema: dict[str, Any]) -> int:
        if name not in self._schemas:
            self._schemas[name] = self._writer.register_schema(
                name=name, encoding="jsonschema", data=json.dumps(schema).encode()
            )
        return self._schemas[name]

    def channel_id(self, key: str, model: type[BaseModel] | None = None) -> int:
        """Channel of a key (registered on first use; ``model`` defaults to the key's model)."""
        if key not in self._channels:
            model = model or keys_mod.model_for_key(key)
            if model is None:
                self.register_channel(key, UNKNOWN_SCHEMA_NAME, UNKNOWN_SCHEMA)
            else:
                self.register_channel(key, schema_name(model), json_schema(model))
        return self._channels[key]

    def register_channel(self, key: str, name: str, schema: dict[str, Any]) -> int:
        """Register the channel of ``key`` with the JSON schema ``schema`` named ``name`` (as a
        recording had it)."""
        self._channels[key] = self._writer.register_channel(
            topic=key, message_encoding="json", schema_id=self._schema_id(name, schema)
        )
        return self._channels[key]

    def write(
        self,
        key: str,
        payload: bytes,
        t: float,
        *,
        publish_time_ns: int | None = None,
        model: type[BaseModel] | None = None,
        sequence: int | None = None,
    ) -> None:
        if self._closed:
            raise ValueError(f"recorder for {self.path} is closed")
        cid = self.channel_id(key, model)
        log_time = plant_time_ns(t)
        self._writer.add_message(
            channel_id=cid,
            log_time=log_time,
            data=payload,
            publish_time=time.time_ns() if publish_time_ns is None else publish_time_ns,
            sequence=self._seq[key] if sequence is None else sequence,
        )
        self._seq[key] += 1
        self.counts[key] += 1
        self._since_flush += 1
        if self._since_flush >= self.flush_every or (
            self.flush_period_s is not None
            and time.monotonic() - self._last_flush >= self.flush_period_s
        ):
            self.flush()

    def write_message(self, key: str, msg: Message, *, publish_time_ns: int | None = None) -> None:
        self.write(
            key, msg.to_json_bytes(), msg.t, publish_time_ns=publish_time_ns, model=type(msg)
        )

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """An MCAP metadata record (e.g. provenance of a synthetic recording)."""
        self._writer.add_metadata(name=name, data={str(k): str(v) for k, v in data.items()})

    def flush(self) -> None:
        """Write the open chunk to the file (not fsync: covers a process crash)."""
        if self._since_flush:
            self._writer.flush()
        self._since_flush = 0
        self._last_flush = time.monotonic()

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> McapRecorder:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


# -------------------------------------------------------------------------------------------
# reader


@dataclass(slots=True)
class RecordedMessage:
    """One message of a recording: key, times (ns), per-channel sequence, raw payload bytes."""

    key: str
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    payload: bytes
    schema_name: str

    @property
    def t(self) -> float:
        """Plant time, s."""
        return self.log_time_ns / NS

    def decode(self) -> Message | dict[str, Any]:
        """The message model instance (validated) or, for an unknown key, the JSON dict."""
        model = keys_mod.model_for_key(self.key)
        if model is None:
            return json.loads(self.payload)
        return model.model_validate_json(self.payload)


@dataclass
class ChannelInfo:
    key: str
    schema_name: str
    schema: dict[str, Any]
    message_count: int = 0


@dataclass
class LostChunk:
    """A part of a recording that could not be read: a chunk that failed its CRC or did not
    decompress, bytes that are no record, or the tail cut off by a crash. ``start_ns`` /
    ``end_ns``: the plant time it covered, when its header says; ``messages``: how many it held,
    when its message index says (None: unknown)."""

    offset: int
    length: int
    reason: str
    start_ns: int | None = None
    end_ns: int | None = None
    messages: int | None = None
    #: messages it held per channel (key), when its message index says
    per_channel: dict[str, int] | None = None

    def describe(self) -> str:
        span = ""
        if self.start_ns is not None and self.end_ns is not None:
            span = f", plant time {self.start_ns / NS:.1f}-{self.end_ns / NS:.1f} s"
        n = "an unknown number of" if self.messages is None else str(self.messages)
        return f"{n} messages lost at byte {self.offset} ({self.length} bytes{span}: {self.reason})"


#: name of the MCAP metadata record in which ``twin recover`` lists the holes of its output
RECOVERY_METADATA = "recovery"


@dataclass
class Hole:
    """A stretch of plant time a recording lost (one or more adjacent unreadable chunks).

    ``start_s`` / ``end_s``: the plant time of the lost messages, from the lost chunks' headers
    (None where no header could be read); ``after_s`` / ``before_s``: the last message read
    before the hole and the first after it (``before_s`` None: the hole runs to the end of the
    recording); ``messages``: how many were lost (None: unknown), ``per_channel`` by key when
    the message indexes say; ``chunks``: the unreadable pieces; ``reason``: why.
    """

    start_s: float | None
    end_s: float | None
    after_s: float | None
    before_s: float | None
    messages: int | None
    chunks: int
    per_channel: dict[str, int] | None
    reason: str

    def describe(self) -> str:
        """One line: ``hole: plant time 999.000-1331.000 s (...): 1000 messages in 1 chunk
        lost (per channel): reason``."""
        after = "the start" if self.after_s is None else f"{self.after_s:.3f} s"
        before = "the end of the recording" if self.before_s is None else f"{self.before_s:.3f} s"
        if self.start_s is not None and self.end_s is not None:
            span = f"{self.start_s:.3f}-{self.end_s:.3f} s (after {after}, before {before})"
        else:
            span = f"after {after}, before {before}"
        n = "an unknown number of" if self.messages is None else str(self.messages)
        chunks = f"{self.chunks} chunk" + ("s" if self.chunks != 1 else "")
        per = ""
        if self.per_channel:
            per = " (" + ", ".join(f"{k} {v}" for k, v in sorted(self.per_channel.items())) + ")"
        return f"hole: plant time {span}: {n} messages in {chunks} lost{per}: {self.reason}"

    def brief(self) -> str:
        """The hole in a few words: its plant time and the messages lost."""
        if self.start_s is not None and self.end_s is not None:
            span = f"{self.start_s:.3f}-{self.end_s:.3f} s"
        else:
            before = "the end" if self.before_s is None else f"{self.before_s:.3f} s"
            span = f"after {self.after_s or 0.0:.3f} s, before {before}"
        n = "an unknown number of" if self.messages is None else str(self.messages)
        return f"plant time {span}, {n} messages lost"

    def as_dict(self) -> dict[str, Any]:
        """The hole as JSON-ready data."""
        return asdict(self)


def _holes(lost: list[LostChunk], read: list[tuple[int, int, int]]) -> list[Hole]:
    """The holes of a read: adjacent lost pieces (no chunk read between them, by file offset)
    merged, each bounded by the chunks read around it (``read``: offset, first and last
    message time in ns, of every chunk read)."""
    groups: list[list[LostChunk]] = []
    for c in sorted(lost, key=lambda c: c.offset):
        if groups and not any(groups[-1][-1].offset < o < c.offset for o, _, _ in read):
            groups[-1].append(c)
        else:
            groups.append([c])
    out = []
    for g in groups:
        first, last = g[0].offset, g[-1].offset
        ends = [e for o, _, e in read if o < first]
        starts = [s for o, s, _ in read if o > last]
        known = [c for c in g if c.start_ns is not None and c.end_ns is not None]
        counts = [c.messages for c in g]
        per: dict[str, int] | None = {}
        for c in g:
            if c.per_channel is None or per is None:
                per = None
                continue
            for k, v in c.per_channel.items():
                per[k] = per.get(k, 0) + v
        out.append(
            Hole(
                start_s=min(c.start_ns for c in known) / NS if len(known) == len(g) else None,
                end_s=max(c.end_ns for c in known) / NS if len(known) == len(g) else None,
                after_s=max(ends) / NS if ends else None,
                before_s=min(starts) / NS if starts else None,
                messages=None if any(n is None for n in counts) else sum(counts),
                chunks=len(g),
                per_channel=per or None,
                reason="; ".join(dict.fromkeys(c.reason for c in g)),
            )
        )
    return out


@dataclass
class Recording:
    """A recording read into memory.

    ``messages`` are in ``log_time`` order (file order among equal times). What could not be
    read is in ``lost`` (:class:`LostChunk`: corrupt chunks, skipped; the tail of a file cut
    short); ``truncated`` is True when the file was cut short (no data end, summary or footer).
    ``expected_messages``: the count the file's statistics declare (None if unknown).
    ``metadata``: the MCAP metadata records (e.g. ``provenance``) by name.
    """

    path: Path
    messages: list[RecordedMessage]
    channels: dict[str, ChannelInfo]
    truncated: bool = False
    error: str | None = None
    bytes_read: int = 0
    bytes_total: int = 0
    extra: dict[str, Any] = field(default_factory=dict)
    lost: list[LostChunk] = field(default_factory=list)
    expected_messages: int | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: chunks read: (file offset, first and last message time in ns), to bound the holes
    chunks_read: list[tuple[int, int, int]] = field(default_factory=list)

    @property
    def bytes_unread(self) -> int:
        return max(0, self.bytes_total - self.bytes_read)

    @property
    def complete(self) -> bool:
        """Whether every message of the file was read."""
        return not self.truncated and not self.lost

    @property
    def messages_lost(self) -> int | None:
        """Messages the file held that were not read (None: unknown, e.g. a cut tail)."""
        if self.complete:
            return 0
        if self.expected_messages is not None:
            return self.expected_messages - len(self.messages)
        counts = [c.messages for c in self.lost]
        return None if any(n is None for n in counts) else sum(counts)

    @property
    def start_ns(self) -> int | None:
        return self.messages[0].log_time_ns if self.messages else None

    @property
    def end_ns(self) -> int | None:
        return self.messages[-1].log_time_ns if self.messages else None

    @property
    def duration_s(self) -> float:
        if not self.messages:
            return 0.0
        return (self.messages[-1].log_time_ns - self.messages[0].log_time_ns) / NS

    @classmethod
    def from_messages(cls, messages: Iterable[tuple[str, Message]]) -> Recording:
        """An in-memory recording of (key, message) pairs in plant-time order (``log_time`` =
        plant time), e.g. a simulated run to replay."""
        msgs, channels = [], {}
        for key, msg in messages:
            model = type(msg)
            if key not in channels:
                channels[key] = ChannelInfo(key, schema_name(model), json_schema(model))
            channels[key].message_count += 1
            ns = plant_time_ns(msg.t)
            seq = channels[key].message_count - 1
            msgs.append(RecordedMessage(key, ns, ns, seq, msg.to_json_bytes(), schema_name(model)))
        msgs.sort(key=lambda m: m.log_time_ns)
        return cls(Path("<memory>"), msgs, channels)

    def holes(self) -> list[Hole]:
        """The holes of this read (:class:`Hole`; none when complete)."""
        return _holes(self.lost, self.chunks_read)

    @property
    def recovered_holes(self) -> list[Hole]:
        """The holes ``twin recover`` wrote into this file's ``recovery`` metadata (the file
        is a recovered copy of one that lost them)."""
        text = self.metadata.get(RECOVERY_METADATA, {}).get("holes")
        return [Hole(**h) for h in json.loads(text)] if text else []

    def recovery_metadata(self) -> dict[str, str]:
        """The ``recovery`` metadata record of a copy of this recording: its holes, those of
        an earlier recovery included, and what was read and lost."""
        holes = [*self.recovered_holes, *self.holes()]
        holes.sort(key=lambda h: (h.start_s if h.start_s is not None else h.after_s) or 0.0)
        lost = self.messages_lost
        return {
            "source": self.path.name,
            "messages_written": str(len(self.messages)),
            "messages_lost": "unknown" if lost is None else str(lost),
            "holes": json.dumps([h.as_dict() for h in holes]),
            "source_status": self.loss_report(),
        }

    def loss_report(self) -> str:
        """One line about completeness, e.g. for ``twin inspect``, replay and the reports; a
        recovered copy names the holes of the file it was recovered from."""
        if self.complete:
            holes = self.recovered_holes
            if not holes:
                return f"complete: {len(self.messages)} messages"
            n = len(holes)
            return (
                f"complete: {len(self.messages)} messages; a recovered copy with "
                f"{n} hole{'s' if n != 1 else ''} ({RECOVERY_METADATA!r} metadata): "
                + "; ".join(h.brief() for h in holes)
            )
        lost = self.messages_lost
        parts = []
        if self.truncated:
            parts.append(f"TRUNCATED at byte {self.bytes_read} of {self.bytes_total}")
        parts.append(
            f"INCOMPLETE: recovered {len(self.messages)} messages, lost "
            + ("an unknown number" if lost is None else str(lost))
        )
        parts += [c.describe() for c in self.lost]
        return "; ".join(parts)

    def loss_summary(self) -> dict[str, Any]:
        """The input's completeness for a report: messages read and lost, and each loss."""
        return {
            "complete": self.complete,
            "messages_read": len(self.messages),
            "messages_lost": self.messages_lost,
            "truncated": self.truncated,
            "lost": [asdict(c) for c in self.lost],
            "holes": [h.as_dict() for h in [*self.recovered_holes, *self.holes()]],
            "status": self.loss_report(),
        }

    def require_complete(self, allow_partial: bool = False) -> None:
        """Raise ValueError (naming the loss) for an empty or incomplete recording; with
        ``allow_partial`` an incomplete one with messages passes (the loss is logged)."""
        if not self.messages:
            raise ValueError(f"recording holds no message, {self.path}: {self.loss_report()}")
        if self.complete:
            return
        if not allow_partial:
            raise ValueError(
                f"recording is incomplete (--allow-partial reads what is left), {self.path}: "
                f"{self.loss_report()}"
            )
        log.warning("%s: %s", self.path, self.loss_report())


MAGIC = b"\x89MCAP0\r\n"
#: top-level record opcodes the scan accepts (MCAP spec)
_KNOWN = {int(op) for op in Opcode}
_RECORD_HEAD = 9  # opcode (1 byte) + length (8 bytes)


def _channel_info(channel: Channel, schema: Schema | None) -> ChannelInfo:
    if schema is None or not schema.data:
        return ChannelInfo(channel.topic, UNKNOWN_SCHEMA_NAME, dict(UNKNOWN_SCHEMA))
    return ChannelInfo(channel.topic, schema.name, json.loads(schema.data))


def _recorded(channel: Channel, schema: Schema | None, message: McapMessage) -> RecordedMessage:
    return RecordedMessage(
        key=channel.topic,
        log_time_ns=message.log_time,
        publish_time_ns=message.publish_time,
        sequence=message.sequence,
        payload=bytes(message.data),
        schema_name=schema.name if schema is not None else UNKNOWN_SCHEMA_NAME,
    )


def _parse(buf: bytes) -> Any:
    """The one top-level record in ``buf`` (opcode, length, content)."""
    return next(StreamReader(io.BytesIO(buf), skip_magic=True, emit_chunks=True).records)


def _error(exc: Exception) -> str:
    return f"{type(exc).__name__}: {exc}".strip().rstrip(":")


class _Collector:
    """Schemas, channels, messages and metadata gathered from records."""

    def __init__(self) -> None:
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.messages: list[RecordedMessage] = []
        self.metadata: dict[str, dict[str, str]] = {}
        self.chunks_read: list[tuple[int, int, int]] = []

    def add(self, record: Any) -> None:
        if isinstance(record, Schema):
            self.schemas[record.id] = record
        elif isinstance(record, Channel):
            self.channels[record.id] = record
        elif isinstance(record, McapMessage):
            ch = self.channels.get(record.channel_id)
            if ch is not None:
                self.messages.append(_recorded(ch, self.schemas.get(ch.schema_id), record))
        elif isinstance(record, Metadata):
            self.metadata[record.name] = dict(record.metadata)

    def add_chunk(self, buf: bytes, offset: int = -1) -> None:
        """The records of a chunk (CRC validated) at file ``offset``; raises if it is corrupt."""
        chunk = _parse(buf)
        records = breakup_chunk(chunk, validate_crc=True)
        for r in records:
            self.add(r)
        if any(isinstance(r, McapMessage) for r in records):
            self.chunks_read.append((offset, chunk.message_start_time, chunk.message_end_time))

    def name_channels(
        self, lost: list[LostChunk], counts: dict[int, dict[int, int] | None]
    ) -> None:
        """Each lost piece's messages per channel key (``counts``: by piece offset, channel
        id -> messages); a channel whose record was lost too is named by its id."""
        for c in lost:
            ids = counts.get(c.offset)
            if ids is not None:
                c.per_channel = {
                    (self.channels[i].topic if i in self.channels else f"channel {i}"): n
                    for i, n in ids.items()
                }

    def recording(self, path: Path, size: int, **fields: Any) -> Recording:
        infos = {
            ch.topic: _channel_info(ch, self.schemas.get(ch.schema_id))
            for ch in self.channels.values()
        }
        self.messages.sort(key=lambda m: m.log_time_ns)
        for m in self.messages:
            infos[m.key].message_count += 1
        return Recording(
            path,
            self.messages,
            infos,
            bytes_total=size,
            metadata=self.metadata,
            chunks_read=sorted(self.chunks_read),
            **fields,
        )


def _chunk_times(buf: bytes) -> tuple[int | None, int | None]:
    """Start and end times of a chunk record from its header (None if cut before them)."""
    head = buf[_RECORD_HEAD : _RECORD_HEAD + 16]
    if len(head) < 16:
        return None, None
    return int.from_bytes(head[:8], "little"), int.from_bytes(head[8:], "little")


def _index_counts(data: bytes, offsets: Iterable[int]) -> dict[int, int] | None:
    """Messages per channel id listed by the message-index records at ``offsets`` (None if
    unreadable)."""
    out: dict[int, int] = {}
    for off in offsets:
        try:
            length = int.from_bytes(data[off + 1 : off + _RECORD_HEAD], "little")
            index = _parse(data[off : off + _RECORD_HEAD + length])
        except Exception:  # noqa: BLE001 - a corrupt index: the count is unknown
            return None
        out[index.channel_id] = out.get(index.channel_id, 0) + len(index.records)
    return out


def _index_count(data: bytes, offsets: Iterable[int]) -> int | None:
    """Messages listed by the message-index records at ``offsets`` (None if unreadable)."""
    counts = _index_counts(data, offsets)
    return None if counts is None else sum(counts.values())


def _read_indexed(path: Path, data: bytes) -> Recording | None:
    """Read through the summary: every chunk its chunk index names, a corrupt one skipped with
    its time span and message count from the index; None without a usable summary."""
    try:
        with open(path, "rb") as f:
            summary = make_reader(f).get_summary()
    except Exception as exc:  # noqa: BLE001 - no usable summary: the caller scans
        log.debug("%s: no summary (%s)", path, _error(exc))
        return None
    if summary is None or not summary.chunk_indexes:
        return None
    got = _Collector()
    got.schemas.update(summary.schemas)
    got.channels.update(summary.channels)
    lost = []
    per_channel: dict[int, dict[int, int] | None] = {}
    for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
        buf = data[ci.chunk_start_offset : ci.chunk_start_offset + ci.chunk_length]
        try:
            got.add_chunk(buf, ci.chunk_start_offset)
        except Exception as exc:  # noqa: BLE001 - CRC, zstd, struct errors: skip this chunk
            counts = _index_counts(data, ci.message_index_offsets.values())
            per_channel[ci.chunk_start_offset] = counts
            n = None if counts is None else sum(counts.values())
            lost.append(
                LostChunk(
                    ci.chunk_start_offset,
                    ci.chunk_length,
                    f"corrupt chunk, skipped: {_error(exc)}",
                    ci.message_start_time,
                    ci.message_end_time,
                    n,
                )
            )
    for mi in summary.metadata_indexes:
        try:
            got.add(_parse(data[mi.offset : mi.offset + mi.length]))
        except Exception as exc:  # noqa: BLE001 - lose that metadata record only
            log.warning("%s: metadata %r unreadable: %s", path, mi.name, _error(exc))
    got.name_channels(lost, per_channel)
    stats = summary.statistics
    expected = stats.message_count if stats is not None else None
    size = len(data)
    return got.recording(path, size, bytes_read=size, lost=lost, expected_messages=expected)


def _resync(data: bytes, start: int) -> int | None:
    """The offset of the next chunk record at or after ``start`` that parses with a valid CRC
    (after bytes that are no record), or None."""
    pos = data.find(bytes([Opcode.CHUNK]), start)
    while pos != -1:
        length = int.from_bytes(data[pos + 1 : pos + _RECORD_HEAD], "little")
        end = pos + _RECORD_HEAD + length
        if end <= len(data):
            try:
                breakup_chunk(_parse(data[pos:end]), validate_crc=True)
                return pos
            except Exception:  # noqa: BLE001, S112 - not a chunk: keep looking
                pass
        pos = data.find(bytes([Opcode.CHUNK]), pos + 1)
    return None


def _scan(path: Path, data: bytes) -> Recording:
    """Read in file order: a corrupt chunk is skipped (its message count from the message index
    that follows it), bytes that are no record are skipped up to the next valid chunk, and a
    file cut short keeps every complete chunk before the cut."""
    got = _Collector()
    lost: list[LostChunk] = []
    size, pos, ended, error = len(data), len(MAGIC), False, None
    last_bad: LostChunk | None = None
    per_channel: dict[int, dict[int, int] | None] = {}
    while pos < size:
        opcode = data[pos]
        length = int.from_bytes(data[pos + 1 : pos + _RECORD_HEAD], "little")
        end = pos + _RECORD_HEAD + length
        if pos + _RECORD_HEAD > size or opcode not in _KNOWN or end > size:
            nxt = _resync(data, pos + 1)
            cut = nxt is None
            start, stop = _chunk_times(data[pos:]) if opcode == Opcode.CHUNK else (None, None)
            reason = "cut short" if cut else "bytes that are no MCAP record, skipped"
            lost.append(LostChunk(pos, (size if cut else nxt) - pos, reason, start, stop))
            if cut:
                error = f"the file ends inside a record at byte {pos}"
                break
            pos, last_bad = nxt, None
            continue
        buf = data[pos:end]
        if opcode == Opcode.CHUNK:
            try:
                got.add_chunk(buf, pos)
                last_bad = None
            except Exception as exc:  # noqa: BLE001 - skip the corrupt chunk
                start, stop = _chunk_times(buf)
                last_bad = LostChunk(
                    pos, len(buf), f"corrupt chunk, skipped: {_error(exc)}", start, stop, 0
                )
                lost.append(last_bad)
                per_channel[pos] = {}
        elif opcode == Opcode.MESSAGE_INDEX and last_bad is not None:
            counts = _index_counts(data, [pos])
            n = None if counts is None else sum(counts.values())
            last_bad.messages = (
                None if n is None or last_bad.messages is None else last_bad.messages + n
            )
            mine = per_channel.get(last_bad.offset)
            if counts is None or mine is None:
                per_channel[last_bad.offset] = None
            else:
                for i, k in counts.items():
                    mine[i] = mine.get(i, 0) + k
        elif opcode in (Opcode.DATA_END, Opcode.FOOTER):
            ended = data.endswith(MAGIC)
            if not ended:
                error = f"the file ends after its data, without summary and footer (byte {end})"
            pos = end
            break
        elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE, Opcode.METADATA):
            try:
                got.add(_parse(buf))
            except Exception as exc:  # noqa: BLE001
                lost.append(LostChunk(pos, len(buf), f"corrupt record, skipped: {_error(exc)}"))
        pos = end
    for c in lost:  # a chunk without a message index after it: its count is unknown
        if c.messages == 0 and c.reason.startswith("corrupt chunk"):
            c.messages = None
            per_channel.pop(c.offset, None)
    got.name_channels(lost, per_channel)
    truncated = not ended
    if truncated and error is None:
        error = "no data end, summary or footer"
    return got.recording(
        path,
        size,
        truncated=truncated,
        error=error,
        bytes_read=min(pos, size),
        lost=lost,
    )


def read_recording(path: str | Path, *, keys: Iterable[str] | None = None) -> Recording:
    """Read a recording, as much of it as can be read (see :class:`Recording`): through its
    summary and chunk index when it has them, else in file order; a corrupt chunk is skipped
    with a warning naming it, every other complete chunk is read.

    Raises FileNotFoundError for a missing file and ValueError for an empty file or one that is
    not MCAP. ``keys``: keep only these channels (exact keys).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(errno.ENOENT, "recording not found", str(path))
    data = path.read_bytes()
    if not data:
        raise ValueError(f"recording is empty (0 bytes), {path}")
    if not data.startswith(MAGIC):
        raise ValueError(f"not an MCAP file (no MCAP magic at its start), {path}")
    rec = _read_indexed(path, data) or _scan(path, data)
    if not rec.complete:
        log.warning("%s: %s", path, rec.loss_report())
    if keys is not None:
        wanted = set(keys)
        rec.messages = [m for m in rec.messages if m.key in wanted]
        rec.channels = {k: c for k, c in rec.channels.items() if k in wanted}
    return rec


def summarize(rec: Recording) -> str:
    """Human-readable summary: channels, schema names, message counts, time span, losses."""
    lines = [f"file: {rec.path} ({rec.bytes_total} bytes)", rec.loss_report()]
    if rec.messages:
        lines.append(
            f"plant time: {rec.start_ns / NS:.3f} s .. {rec.end_ns / NS:.3f} s "
            f"(span {rec.duration_s:.3f} s)"
        )
    lines.append(f"channels: {len(rec.channels)}")
    width = max((len(k) for k in rec.channels), default=10)
    for key in sorted(rec.channels):
        c = rec.channels[key]
        lines.append(f"  {key:<{width}}  {c.message_count:>8} msgs  schema {c.schema_name}")
    names = sorted({c.schema_name for c in rec.channels.values()})
    lines.append(f"schemas: {', '.join(names)}")
    if rec.metadata:
        lines.append(f"metadata: {', '.join(sorted(rec.metadata))}")
    lines += [h.describe() for h in [*rec.recovered_holes, *rec.holes()]]
    return "\n".join(lines)


# -------------------------------------------------------------------------------------------
# replay


@dataclass
class ReplayStats:
    published: int = 0
    passes: int = 0
    wall_s: float = 0.0
    plant_span_s: float = 0.0
    max_lag_s: float = 0.0
    stopped: bool = False
    acknowledged_by: list[str] = field(default_factory=list)

    @property
    def rate_msg_s(self) -> float:
        return self.published / self.wall_s if self.wall_s > 0 else math.inf


def _shift(payload: bytes, dt: float, dseq: int) -> bytes:
    data = json.loads(payload)
    data["t"] = float(data["t"]) + dt
    if "seq" in data:
        data["seq"] = int(data["seq"]) + dseq
    return json.dumps(data, separators=(",", ":")).encode()


def replay(
    rec: Recording,
    publish: Callable[[str, bytes], None],
    *,
    speed: float = 1.0,
    as_fast_as_possible: bool = False,
    loop: bool = False,
    max_passes: int | None = None,
    should_stop: Callable[[], bool] | None = None,
    hold: Callable[[float], None] | None = None,
) -> ReplayStats:
    """Publish the messages of a recording with their plant-time spacing divided by ``speed``.

    ``publish(key, payload)`` sends one message (e.g. a zenoh put). Message i is sent at
    ``wall_start + (t_i - t_0) / speed`` (or back to back with ``as_fast_as_possible``).
    The first pass sends the payloads byte for byte. With ``loop``, each later pass k shifts
    ``t`` by ``k * (span + dt)`` (dt: the smallest positive gap between successive messages, or
    1 s) and ``seq`` by ``k * (max seq + 1)`` per key, re-encoding the payload, so that plant time
    and sequence numbers keep increasing. ``should_stop()`` is polled between messages.
    ``hold(t)`` is called with each message's plant time (s) before it is sent and may block: a
    virtual plant paced by the twin (wait until a service has reacted before going on); the
    time spent in it shifts the rest of the schedule, so the replay resumes at ``speed``.
    """
    if not as_fast_as_possible and (not math.isfinite(speed) or speed <= 0):
        raise ValueError(f"speed must be a finite number > 0, got {speed!r}")
    stats = ReplayStats()
    msgs = rec.messages
    if not msgs:
        return stats
    t0 = msgs[0].log_time_ns
    span_ns = msgs[-1].log_time_ns - t0
    stats.plant_span_s = span_ns / NS
    gaps = [b.log_time_ns - a.log_time_ns for a, b in zip(msgs, msgs[1:], strict=False)]
    positive = [g for g in gaps if g > 0]
    step_ns = min(positive) if positive else NS
    max_seq: dict[str, int] = {}
    wall0 = time.perf_counter()
    passes = 0
    while True:
        shift_ns = passes * (span_ns + step_ns)
        for m in msgs:
            if should_stop is not None and should_stop():
                stats.stopped = True
                break
            if hold is not None:
                held_from = time.perf_counter()
                hold((m.log_time_ns + shift_ns) / NS)
                wall0 += time.perf_counter() - held_from
            if not as_fast_as_possible:
                due = (m.log_time_ns - t0 + shift_ns) / NS / speed
                now = time.perf_counter() - wall0
                if due > now:
                    time.sleep(due - now)
                else:
                    stats.max_lag_s = max(stats.max_lag_s, now - due)
            if passes == 0:
                payload = m.payload
                if loop:
                    try:
                        seq = int(json.loads(payload).get("seq", 0))
                    except (ValueError, AttributeError):
                        seq = 0
                    max_seq[m.key] = max(max_seq.get(m.key, 0), seq)
            else:
                payload = _shift(m.payload, shift_ns / NS, passes * (max_seq.get(m.key, 0) + 1))
            publish(m.key, payload)
            stats.published += 1
        passes += 1
        if stats.stopped or not loop or (max_passes is not None and passes >= max_passes):
            break
    stats.passes = passes
    stats.wall_s = time.perf_counter() - wall0
    return stats


# -------------------------------------------------------------------------------------------
# line data for analysis


class LineData(NamedTuple):
    """Return of :func:`load_line_data`.

    ``signals``: a DataFrame indexed by ``t_s`` (plant time, s, float, ascending, unique): one row
    per distinct plant time at which any of the signals below was recorded; a column is NaN where
    its signal has no sample at that time (align with ``.ffill()`` / ``.interpolate()`` as
    needed). Columns (one group per feeder id / sensor+component / model+component found; the
    feeder id is the ``<id>`` of ``twin/<line>/feeder/<id>/flow``, so two feeders of one
    component are two groups):

    - ``flow_<feeder>_kg_h`` (float): measured mass flow of that feeder;
    - ``setpoint_<feeder>_kg_h``, ``screw_speed_<feeder>_rpm``,
      ``hopper_mass_<feeder>_kg``, ``feed_factor_<feeder>_g_rev`` (float);
    - ``refilling_<feeder>`` (float 1.0/0.0, NaN where no sample);
    - ``total_flow_kg_h`` (float): sum of the ``flow_*`` columns where all are present;
    - ``conc_<sensor>_<component>_pct_w_w`` (float): measured concentration, % w/w;
    - ``quality_<sensor>_<component>`` (str 'good'/'suspect'/'bad', or NaN);
    - ``pred_<model>_<component>_pct_w_w`` (float): predicted concentration, if recorded.

    ``events``: a DataFrame with one row per :class:`schemas.messages.Event`, in time order,
    columns ``t_s`` (float), ``kind``, ``source``, ``component`` (str or None), ``mass_kg``,
    ``duration_s``, ``magnitude`` (float or NaN), ``detail`` (str), ``key`` (str).
    """

    signals: pd.DataFrame
    events: pd.DataFrame


EVENT_COLUMNS = [
    "t_s",
    "kind",
    "source",
    "component",
    "mass_kg",
    "duration_s",
    "magnitude",
    "detail",
    "key",
]


def load_line_data(path: str | Path) -> LineData:
    """Load feeder flows, measured (and predicted) concentrations and events of a recording.

    Reads an MCAP recording (a truncated one is recovered) and decodes the messages on
    ``twin/<line>/feeder/<id>/flow`` (FeederFlow), ``.../concentration`` (MeasuredConcentration),
    ``.../predicted`` (PredictedConcentration) and ``.../event`` (Event) into a
    :class:`LineData` ``(signals, events)``; see :class:`LineData` for the exact columns.
    Other channels are ignored. Raises FileNotFoundError for a missing file.
    """
    from schemas.messages import Event, FeederFlow, MeasuredConcentration, PredictedConcentration

    rec = read_recording(path)
    cols: dict[str, dict[float, Any]] = defaultdict(dict)
    events: list[dict[str, Any]] = []
    flow_cols: set[str] = set()
    for m in rec.messages:
        model = keys_mod.model_for_key(m.key)
        if model not in (FeederFlow, MeasuredConcentration, PredictedConcentration, Event):
            continue
        msg = model.model_validate_json(m.payload)
        t = msg.t
        if isinstance(msg, FeederFlow):
            c = keys_mod.parse_key(m.key).id
            cols[f"flow_{c}_kg_h"][t] = msg.mass_flow_kg_h
            flow_cols.add(f"flow_{c}_kg_h")
            if msg.setpoint_kg_h is not None:
                cols[f"setpoint_{c}_kg_h"][t] = msg.setpoint_kg_h
            cols[f"screw_speed_{c}_rpm"][t] = msg.screw_speed_rpm
            cols[f"hopper_mass_{c}_kg"][t] = msg.hopper_mass_kg
            cols[f"feed_factor_{c}_g_rev"][t] = msg.feed_factor_g_rev
            cols[f"refilling_{c}"][t] = 1.0 if msg.refilling else 0.0
        elif isinstance(msg, MeasuredConcentration):
            cols[f"conc_{msg.sensor}_{msg.component}_pct_w_w"][t] = msg.concentration_pct_w_w
            cols[f"quality_{msg.sensor}_{msg.component}"][t] = msg.quality
        elif isinstance(msg, PredictedConcentration):
            cols[f"pred_{msg.model}_{msg.component}_pct_w_w"][t] = msg.concentration_pct_w_w
        else:
            events.append(
                {
                    "t_s": t,
                    "kind": msg.kind,
                    "source": msg.source,
                    "component": msg.component,
                    "mass_kg": msg.mass_kg if msg.mass_kg is not None else math.nan,
                    "duration_s": msg.duration_s if msg.duration_s is not None else math.nan,
                    "magnitude": msg.magnitude if msg.magnitude is not None else math.nan,
                    "detail": msg.detail,
                    "key": m.key,
                }
            )
    signals = pd.DataFrame({name: pd.Series(values) for name, values in sorted(cols.items())})
    signals = signals.sort_index()
    signals.index = signals.index.astype(float)
    signals.index.name = "t_s"
    if flow_cols:
        signals["total_flow_kg_h"] = signals[sorted(flow_cols)].sum(axis=1, skipna=False)
    ev = pd.DataFrame(events, columns=EVENT_COLUMNS)
    if not ev.empty:
        ev = ev.sort_values("t_s", kind="stable").reset_index(drop=True)
    return LineData(signals, ev)


# -------------------------------------------------------------------------------------------
# bus side: record the bus, replay a recording onto it


@dataclass
class RecordStats:
    path: Path
    counts: dict[str, int]
    rejected: dict[str, int]
    wall_s: float
    reason: str

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def record_bus(
    path: str | Path,
    config: Any = None,
    *,
    key_expr: str = keys_mod.ALL_LINES,
    count: int | None = None,
    duration_s: float | None = None,
    idle_timeout_s: float | None = None,
    flush_every: int = 1000,
    service_name: str = "recorder",
    install_signal_handlers: bool = True,
    on_ready: Callable[[], None] | None = None,
    exclude_health: bool = False,
    twin: Any = None,
    say: Callable[[str], None] | None = None,
) -> RecordStats:
    """Record every valid message on ``key_expr`` to ``path`` until stopped.

    Stops on SIGINT/SIGTERM, after ``count`` messages, after ``duration_s`` seconds, or when no
    plant message (any key but the services' own ``twin/<line>/service/...`` keys: health of
    the services and tools) arrived for ``idle_timeout_s`` after the first one; the file is
    finalized in every case. Messages are validated against their key's model (time order is
    not checked: a recording keeps what was on the bus); invalid ones are counted and not
    written. A key without a model is recorded if its payload is a JSON object with a numeric
    ``t`` >= 0. The recorder's own health is not recorded; ``exclude_health``: skip every
    ``twin/<line>/service/...`` key (health of the services).

    ``twin``: the :class:`~schemas.line.LineSpec` of the running twin to record, followed
    across its restarts (``services.bus.TwinLink`` as the ``record`` identity; ``config`` is
    not used): when the twin goes away the recorder says so (``say``), and when it is back it
    connects with the new run's credentials and fetches what it missed from the publishers'
    history; a message recorded already (its key, ``t`` and ``seq`` seen again in the same
    run) is counted in ``duplicates`` and not written again.
    """
    from services.bus import MessageValidator, StopFlag, StreamOrder, TwinLink
    from services.service import Service

    stop = StopFlag(install=install_signal_handlers)
    lock = threading.Lock()
    recent = max(4096, int(getattr(twin, "history_samples", 0)) + 1024)
    state: dict[str, Any] = {
        "closed": False,
        "last": None,
        "order": StreamOrder(recent),
        "run": None,
    }
    recorder = McapRecorder(path, flush_every=flush_every)
    services: list[Any] = []

    def on_message(key: str, msg: Any, raw: bytes, svc: Any) -> None:
        service_key = keys_mod.is_service_key(key)
        if service_key and (exclude_health or key.split("/")[3:4] == [service_name]):
            return
        if isinstance(msg, dict):
            t = msg.get("t")
            if (
                not isinstance(t, (int, float))
                or isinstance(t, bool)
                or not math.isfinite(t)
                or t < 0
            ):
                svc.counters.inc("rejected_schema")
                svc.counters.last_error = f"{key}: unknown-model payload without a valid 't'"
                return
            seq = msg.get("seq", 0)
        else:
            t, seq = msg.t, msg.seq
        with lock:
            if state["closed"]:
                return
            if twin is not None and state["order"].check(key, float(t), int(seq)) == "duplicate":
                svc.counters.inc("duplicates")
                return
            recorder.write(key, raw, float(t))
            if not service_key:
                state["last"] = time.monotonic()
            if count is not None and recorder.total >= count:
                stop.set()

    def connect(cfg: Any, again: bool) -> tuple[Any, Callable[[], None]]:
        """A session recording on ``cfg``; ``again``: a reconnection, history included."""
        from services.bus import HistoryFeed

        svc = Service(service_name, cfg, install_signal_handlers=False)
        svc.open()
        if not again:
            svc.subscribe(
                key_expr,
                lambda k, m, raw: on_message(k, m, raw, svc),
                check_time=False,
                allow_unknown=True,
                with_payload=True,
            )
        else:
            from services.common import running_twin

            info = running_twin(twin)
            run = info.run_dir if info else None
            with lock:
                if run != state["run"]:  # a new run: its plant session starts over
                    state["order"] = StreamOrder(recent)
                state["run"] = run
            check = MessageValidator(
                svc.counters, check_time=False, allow_unknown=True, name=service_name
            )

            def on_payload(key: str, payload: bytes) -> None:
                svc.key_counts.inc(key)
                msg = check.check(key, payload)
                if msg is not None:
                    svc.counters.inc("received")
                    on_message(key, msg, payload, svc)

            feed = HistoryFeed(svc.session, key_expr, on_payload)

            def close() -> None:
                feed.undeclare()
                svc.close()

            services.append(svc)
            return svc.session, close
        services.append(svc)
        return svc.session, svc.close

    t0 = time.monotonic()
    reason = "signal"
    link = None
    try:
        if twin is not None:
            from services.common import running_twin

            info = running_twin(twin)
            state["run"] = info.run_dir if info else None
            link = TwinLink(twin, "record", connect, name="twin record", say=say).open()
        else:
            connect(config, False)
        if on_ready is not None:
            on_ready()
        while not stop.wait(0.05):
            now = time.monotonic()
            if duration_s is not None and now - t0 >= duration_s:
                reason = "duration"
                break
            last = state["last"]
            if idle_timeout_s is not None and last is not None and now - last >= idle_timeout_s:
                reason = "idle"
                break
        else:
            if count is not None and recorder.total >= count:
                reason = "count"
    finally:
        if link is not None:
            link.close()
        elif services:
            services[-1].close()
        stop.restore()
        with lock:
            state["closed"] = True
            recorder.close()
    rejected: dict[str, int] = {}
    for svc in services:
        for k, v in svc.counters.snapshot().items():
            if k.startswith("rejected"):
                rejected[k] = rejected.get(k, 0) + v
    return RecordStats(Path(path), dict(recorder.counts), rejected, time.monotonic() - t0, reason)


def recording_mismatches(rec: Recording, line: Any) -> list[Any]:
    """What differs between a recording and the declared line (a ``schemas.line.LineConfig``):
    the line configuration of its ``provenance`` metadata and its first messages (each feeder's
    first flow, the first measurement), by ``twin_core.online.feed``; each difference once."""
    from schemas.messages import FeederFlow, MeasuredConcentration
    from twin_core.online.feed import FeedCheck, line_mismatches

    found = []
    recorded = rec.metadata.get("provenance", {}).get("line_config")
    if recorded:
        try:
            found += line_mismatches(line, json.loads(recorded))
        except (ValueError, TypeError, KeyError, AttributeError) as exc:
            log.warning("%s: provenance line_config unreadable: %s", rec.path, exc)
    check = FeedCheck(line)
    wanted = {f"feeder:{f.id}" for f in line.feeders} | {"sensor"}
    seen: set[str] = set()
    for m in rec.messages:
        k = keys_mod.parse_key(m.key)
        if k.signal == FeederFlow.SIGNAL:
            f = FeederFlow.model_validate_json(m.payload)
            found += check.flow(k.id, f.component, f.setpoint_kg_h)
            seen.add(f"feeder:{k.id}")
        elif k.signal == MeasuredConcentration.SIGNAL:
            c = MeasuredConcentration.model_validate_json(m.payload)
            found += check.measured(c.sensor, c.component)
            seen.add("sensor")
        if wanted <= seen:
            break
    unique: dict[str, Any] = {}
    for x in found:
        unique.setdefault(x.field, x)
    return list(unique.values())


def validate_messages(rec: Recording) -> tuple[list[RecordedMessage], dict[str, int]]:
    """Split a recording's messages into the valid ones (in order) and counts of rejections
    by reason (``rejected_json``, ``rejected_schema``); keys without a model pass if JSON."""
    from services.bus import Counters, MessageValidator

    counters = Counters()
    validator = MessageValidator(counters, check_time=False, allow_unknown=True, name="replay")
    valid = [m for m in rec.messages if validator.check(m.key, m.payload) is not None]
    return valid, {k: v for k, v in counters.snapshot().items() if k.startswith("rejected")}


class BusReplay:
    """Publishes a recording onto the bus, as recorded: the one replay of the twin (``twin
    replay``, the demo's record/replay check, the virtual plant feeding the live twin).

    Use as a context manager: entering opens a :class:`~services.service.Service` session and
    declares a publisher for every recorded key before the first sample (a publisher declared on
    first use reaches subscribers only through late-publisher detection), then waits up to
    ``wait_for_subscribers_s`` until every plain publisher has a matching subscriber and
    ``settle_s`` more; :meth:`replay` publishes (:func:`replay`, the payloads byte for byte);
    leaving waits (up to ``drain_timeout_s``, ``services.bus.barrier``) until every service
    that received any message of a replayed key received all of them (zenoh drops a closing
    session's queued messages), ``linger_s`` more for subscribers that are not services, and
    closes. The publishers' history caches live until then.

    With ``spec`` (a :class:`~schemas.line.LineSpec`: the virtual plant of a live twin) the
    session is the line's client bus, the publishers keep the line's history (late or restarted
    services fetch it) and the replay ends with an ``END_OF_STREAM`` event on
    ``keys.replay_event(line)`` at the plant time of the last sample. Recorded messages that do
    not validate are skipped (counted in :attr:`rejected`). It refuses (ValueError) a recording
    that does not match the line (:func:`recording_mismatches`; ``allow_mismatch`` replays it
    anyway), and (RuntimeError) a running twin that has already seen later plant time than the
    recording starts at: its messages would go back in time on the twin's keys and be rejected
    (``rejected_time``), a second plant session needs a fresh twin.
    """

    def __init__(
        self,
        rec: Recording,
        config: Any = None,
        *,
        spec: Any = None,
        wait_for_subscribers_s: float = 0.0,
        settle_s: float = 0.0,
        drain_timeout_s: float = 10.0,
        linger_s: float = 0.0,
        service_name: str = "replay",
        install_signal_handlers: bool = True,
        allow_mismatch: bool = False,
    ) -> None:
        from services.service import Service

        if spec is not None:
            found = recording_mismatches(rec, spec)
            if found and not allow_mismatch:
                raise ValueError(
                    f"the recording does not match the twin's line configuration "
                    f"(--allow-mismatch replays it anyway), {'; '.join(str(x) for x in found)}"
                )
            if found:
                log.warning("replay: the recording does not match the line: %s", found)
        valid, self.rejected = validate_messages(rec)
        if any(self.rejected.values()):
            log.warning("replay: skipping invalid recorded messages: %s", self.rejected)
        self.rec = Recording(rec.path, valid, rec.channels, rec.truncated, rec.error)
        self.spec = spec
        self.wait_for_subscribers_s = wait_for_subscribers_s
        self.settle_s = settle_s
        self.drain_timeout_s = drain_timeout_s
        self.linger_s = linger_s
        self.svc = Service(
            service_name, config, spec=spec, install_signal_handlers=install_signal_handlers
        )
        self.sent: Counter[str] = Counter()
        self.acknowledged_by: list[str] = []
        self.pubs: dict[str, Any] = {}
        self._baseline: Any = None

    @classmethod
    def as_plant(cls, rec: Recording, config: Any, spec: Any) -> BusReplay:
        """The virtual plant replaying ``rec`` into a running twin of ``spec`` as the ``plant``
        identity (``config``: its client configuration, e.g. ``Supervisor.client_config
        ("plant")``), half a second after its publishers are up, no signal handlers (a tool or
        test drives it): ``with BusReplay.as_plant(rec, cfg, spec) as rp: rp.replay(...)``."""
        return cls(
            rec,
            config,
            spec=spec,
            settle_s=0.5,
            service_name="plant",
            install_signal_handlers=False,
        )

    @property
    def _line(self) -> str:
        """The line whose services are pinged: the twin's (a secured bus lets a tool query its
        own line's keys only), any line without one."""
        return self.spec.name if self.spec is not None else "*"

    def __enter__(self) -> BusReplay:
        from services.bus import ping

        svc = self.svc.open()
        svc.state = "running"  # a tool publishing, no inputs to catch up on
        history = self.spec is not None
        try:
            recorded = sorted({m.key for m in self.rec.messages})
            if history:
                recorded.append(keys_mod.replay_event(self.spec.name))
            self.pubs = {key: svc.publisher(key, history=history) for key in recorded}
            deadline = time.monotonic() + self.wait_for_subscribers_s
            while not history and time.monotonic() < deadline and not svc.stopping:
                if all(p.has_subscribers() for p in self.pubs.values()):
                    break
                time.sleep(0.02)
            if self.settle_s > 0:
                svc.stop_flag.wait(self.settle_s)
            self._baseline = ping(svc.session, self._line)
            if history:
                self._refuse_past()
        except BaseException:
            svc.close()
            raise
        return self

    def _refuse_past(self) -> None:
        """Refuse to replay into a twin that has already seen later plant time (see above).
        Recorders (the ``recorder`` service, the ``twin record`` tool) do not count: they record
        what goes back in time as it was on the bus."""
        if not self.rec.messages:
            return
        t0 = self.rec.messages[0].t
        seen = {
            name: r.health.t
            for name, r in self._baseline.items()
            if name not in (self.svc.name, "supervisor", "recorder", "record") and r.health.t > t0
        }
        if seen:
            name = max(seen, key=seen.get)
            raise RuntimeError(
                f"the running twin has already seen plant time {seen[name]:.1f} s ({name}) and "
                f"the recording starts at {t0:.1f} s: its messages would go back in time and be "
                "rejected; stop `twin up` and start it again to replay another plant session"
            )

    def _publish(self, key: str, payload: bytes) -> None:
        self.pubs[key].put_raw(payload)
        self.sent[key] += 1

    def replay(
        self,
        *,
        speed: float = 1.0,
        as_fast_as_possible: bool = False,
        loop: bool = False,
        max_passes: int | None = None,
        hold: Callable[[float], None] | None = None,
    ) -> ReplayStats:
        """Publish the recording (:func:`replay`, ``hold`` included); with a line spec, then the
        end of stream."""
        stats = replay(
            self.rec,
            self._publish,
            speed=speed,
            as_fast_as_possible=as_fast_as_possible,
            loop=loop,
            max_passes=max_passes,
            should_stop=self.svc.stop_flag.is_set,
            hold=hold,
        )
        if self.spec is not None:
            from schemas.messages import END_OF_STREAM, Event

            msgs = self.rec.messages
            end = Event(
                t=msgs[-1].t if msgs else 0.0,
                seq=0,
                kind="note",
                source="replay",
                detail=END_OF_STREAM,
            )
            self._publish(keys_mod.replay_event(self.spec.name), end.to_json_bytes())
        return stats

    def __exit__(self, *exc: Any) -> None:
        from services.bus import barrier

        try:
            if self.svc.session is not None and not self.svc.stopping:
                health = barrier(
                    self.svc.session,
                    self._line,
                    timeout_s=self.drain_timeout_s,
                    sent=dict(self.sent),
                    baseline=self._baseline,
                )
                self.acknowledged_by = sorted(h.service for h in health)
                if self.linger_s > 0:
                    time.sleep(self.linger_s)
        finally:
            self.svc.close()


def replay_to_bus(
    rec: Recording,
    config: Any = None,
    *,
    speed: float = 1.0,
    as_fast_as_possible: bool = False,
    loop: bool = False,
    max_passes: int | None = None,
    **options: Any,
) -> ReplayStats:
    """Publish a recording onto the bus and drain (:class:`BusReplay`; ``options`` are its
    keyword arguments); return the replay's statistics."""
    with BusReplay(rec, config, **options) as r:
        stats = r.replay(
            speed=speed, as_fast_as_possible=as_fast_as_possible, loop=loop, max_passes=max_passes
        )
    stats.acknowledged_by = r.acknowledged_by
    return stats


def write_recording(rec: Recording, path: str | Path) -> int:
    """Write what a recording holds (channels with their schemas, messages with their times and
    sequence numbers, metadata) to a new, complete MCAP file (footer, summary, chunk index):
    ``twin recover``. A recording that lost messages (or a recovered copy of one) gets the
    ``recovery`` metadata record naming every hole (:meth:`Recording.recovery_metadata`), so
    that the copy's readers see what it lacks. Returns the messages written."""
    metadata = dict(rec.metadata)
    if not rec.complete or rec.recovered_holes:
        metadata[RECOVERY_METADATA] = rec.recovery_metadata()
    with McapRecorder(path, flush_period_s=None, flush_every=10**9) as out:
        for key, c in sorted(rec.channels.items()):
            out.register_channel(key, c.schema_name, c.schema)
        for name, data in sorted(metadata.items()):
            out.add_metadata(name, data)
        for m in rec.messages:
            out.write(
                m.key,
                m.payload,
                m.log_time_ns / NS,
                publish_time_ns=m.publish_time_ns,
                sequence=m.sequence,
            )
        return out.total


def write_messages(path: str | Path, messages: Iterable[tuple[str, Message]]) -> int:
    """Write (key, message) pairs to an MCAP recording (:class:`McapRecorder`, ``log_time`` =
    plant time); return how many."""
    n = 0
    with McapRecorder(path) as rec:
        for k, msg in messages:
            rec.write_message(k, msg, publish_time_ns=int(msg.t * 1e9))
            n += 1
    return n
