"""An MCAP file written a block of messages at a time (the records of the MCAP specification, version 0).

Why our own writer and not ``mcap.writer.Writer``: that one takes one message per Python
call (about 4 µs each), which capped run.mcap at about 240,000 timing records per second.
Here a block of messages whose payloads all have the same size (a task's timing records, the
signal rows) becomes one numpy structured array of Message records, appended to the open
chunk; a chunk is compressed (zstd) when it reaches ``chunk_size`` bytes. Reading stays with
the ``mcap`` package, Foxglove, rosbags and ``ros2 bag``, which the tests use to check these
files.

Layout written (all integers little-endian): magic, Header, Metadata, Schemas and Channels
(outside chunks, so a chunk holds only messages and can be copied into another file with the
same channels: :meth:`McapFile.add_chunk`), Chunks each followed by its Message Indexes, Data End,
then the summary section (Schemas, Channels, Statistics, Metadata Indexes, Chunk Indexes, one
Summary Offset per group), Footer, magic. CRCs are computed for chunks, the data section and
the summary.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import BinaryIO

import numpy as np

MAGIC = b"\x89MCAP0\r\n"
# record opcodes
HEADER, FOOTER, SCHEMA, CHANNEL, MESSAGE, CHUNK, MESSAGE_INDEX, CHUNK_INDEX = range(0x01, 0x09)
STATISTICS, METADATA, METADATA_INDEX, SUMMARY_OFFSET, DATA_END = range(0x0B, 0x10)
MESSAGE_HEAD_BYTES = 2 + 4 + 8 + 8
"""channel_id u16, sequence u32, log_time u64, publish_time u64: then the payload."""
CHUNK_SIZE = 1 << 20
ZSTD_LEVEL = 1
"""zstd's fastest level: timing records still shrink about 6× (measured), at a fifth of level 3's cost."""


def _string(text: str) -> bytes:
    data = text.encode()
    return struct.pack("<I", len(data)) + data


def _string_map(mapping: Mapping[str, str]) -> bytes:
    body = b"".join(_string(k) + _string(v) for k, v in mapping.items())
    return struct.pack("<I", len(body)) + body


def _record(opcode: int, body: bytes) -> bytes:
    return struct.pack("<BQ", opcode, len(body)) + body


def message_dtype(payload_bytes: int) -> np.dtype:
    """One Message record with a payload of ``payload_bytes``, packed as the file holds it."""
    return np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel_id", "<u2"), ("sequence", "<u4"),
                     ("log_time", "<u8"), ("publish_time", "<u8"), ("data", "u1", (payload_bytes,))])


@dataclass
class ChunkPlace:
    """Where a chunk and its message indexes lie in a file, and what its Chunk Index record says."""

    start_ns: int
    end_ns: int
    offset: int
    length: int
    message_index_offsets: dict[int, int]
    message_index_length: int
    compressed_size: int
    uncompressed_size: int
    compression: str = "zstd"

    def record(self) -> bytes:
        offsets = b"".join(struct.pack("<HQ", c, o) for c, o in self.message_index_offsets.items())
        return _record(CHUNK_INDEX, struct.pack("<QQQQ", self.start_ns, self.end_ns, self.offset, self.length)
                       + struct.pack("<I", len(offsets)) + offsets + struct.pack("<Q", self.message_index_length)
                       + _string(self.compression) + struct.pack("<QQ", self.compressed_size, self.uncompressed_size))


@dataclass
class _OpenChunk:
    records: bytearray = field(default_factory=bytearray)
    start_ns: int = 0
    end_ns: int = 0
    index: dict[int, list[np.ndarray]] = field(default_factory=dict)
    """Per channel, blocks of (log_time, offset in the chunk) pairs."""


class McapFile:
    """Writes one MCAP file to ``stream`` (binary, positioned at its start); :meth:`finish` completes it."""

    def __init__(self, stream: BinaryIO, *, profile: str, library: str, chunk_size: int = CHUNK_SIZE) -> None:
        import zstandard

        self._stream = stream
        self._compressor = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self.chunk_size = chunk_size
        self._position = 0
        self._data_crc = 0
        self._schemas: list[bytes] = []
        self._channels: list[bytes] = []
        self.channel_message_counts: dict[int, int] = {}
        self._metadata_indexes: list[bytes] = []
        self._chunk_indexes: list[ChunkPlace] = []
        self._chunk = _OpenChunk()
        self.message_start_ns: int | None = None
        self.message_end_ns: int | None = None
        self._write(MAGIC + _record(HEADER, _string(profile) + _string(library)))

    def _write(self, data: bytes) -> None:
        self._stream.write(data)
        self._data_crc = zlib.crc32(data, self._data_crc)
        self._position += len(data)

    # --- definitions -------------------------------------------------------------------------
    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema_id = len(self._schemas) + 1  # 0 means "no schema"
        record = _record(SCHEMA, struct.pack("<H", schema_id) + _string(name) + _string(encoding)
                         + struct.pack("<I", len(data)) + data)
        self._schemas.append(record)
        self._write(record)
        return schema_id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int, metadata: Mapping[str, str]) -> int:
        channel_id = len(self._channels) + 1
        record = _record(CHANNEL, struct.pack("<HH", channel_id, schema_id) + _string(topic)
                         + _string(message_encoding) + _string_map(metadata))
        self._channels.append(record)
        self.channel_message_counts[channel_id] = 0
        self._write(record)
        return channel_id

    def add_metadata(self, name: str, metadata: Mapping[str, str]) -> None:
        record = _record(METADATA, _string(name) + _string_map(metadata))
        self._metadata_indexes.append(_record(METADATA_INDEX, struct.pack("<QQ", self._position, len(record))
                                              + _string(name)))
        self._write(record)

    # --- messages ------------------------------------------------------------------------------
    def add_messages(self, channel_id: int, log_times_ns: np.ndarray, payloads: np.ndarray | Sequence[bytes],
                     first_sequence: int = 0) -> None:
        """Messages of one channel in time order: ``payloads`` an (n, size) uint8 array (one numpy
        block) or n bytes objects of any sizes; log time and publish time are ``log_times_ns``."""
        times = np.asarray(log_times_ns, dtype=np.uint64).reshape(-1)
        count = len(times)
        if not count:
            return
        if isinstance(payloads, np.ndarray):
            block = np.empty(count, dtype=message_dtype(payloads.shape[1]))
            block["opcode"] = MESSAGE
            block["length"] = MESSAGE_HEAD_BYTES + payloads.shape[1]
            block["channel_id"] = channel_id
            block["sequence"] = np.arange(first_sequence, first_sequence + count, dtype=np.uint64) & 0xFFFFFFFF
            block["log_time"] = times
            block["publish_time"] = times
            block["data"] = payloads
            data: bytes | memoryview = block.data.cast("B")
            offsets = np.arange(count, dtype=np.uint64) * np.uint64(block.itemsize)
        else:
            records = [_record(MESSAGE, struct.pack("<HIQQ", channel_id, (first_sequence + i) & 0xFFFFFFFF, t, t)
                               + payload) for i, (t, payload) in enumerate(zip(times.tolist(), payloads, strict=True))]
            data = b"".join(records)
            offsets = np.cumsum([0] + [len(r) for r in records[:-1]], dtype=np.uint64)
        chunk = self._chunk
        pairs = np.empty((count, 2), dtype="<u8")
        pairs[:, 0] = times
        pairs[:, 1] = offsets + np.uint64(len(chunk.records))
        first, last = int(times.min()), int(times.max())
        if not chunk.records:
            chunk.start_ns, chunk.end_ns = first, last
        chunk.start_ns, chunk.end_ns = min(chunk.start_ns, first), max(chunk.end_ns, last)
        chunk.records += data
        chunk.index.setdefault(channel_id, []).append(pairs)
        self.channel_message_counts[channel_id] += count
        self.message_start_ns = first if self.message_start_ns is None else min(self.message_start_ns, first)
        self.message_end_ns = last if self.message_end_ns is None else max(self.message_end_ns, last)
        if len(chunk.records) >= self.chunk_size:
            self._close_chunk()

    def _close_chunk(self) -> None:
        chunk, self._chunk = self._chunk, _OpenChunk()
        records = chunk.records
        if not records:
            return
        compressed = self._compressor.compress(records)
        head = (struct.pack("<QQQI", chunk.start_ns, chunk.end_ns, len(records), zlib.crc32(records))
                + _string("zstd") + struct.pack("<Q", len(compressed)))
        chunk_offset = self._position
        self._write(struct.pack("<BQ", CHUNK, len(head) + len(compressed)) + head)
        self._write(compressed)
        chunk_length = self._position - chunk_offset
        index_offsets: dict[int, int] = {}
        indexes: list[bytes] = []
        for channel_id, blocks in chunk.index.items():
            pairs = np.concatenate(blocks) if len(blocks) > 1 else blocks[0]
            index_offsets[channel_id] = self._position + sum(len(i) for i in indexes)
            indexes.append(_record(MESSAGE_INDEX, struct.pack("<HI", channel_id, pairs.nbytes) + pairs.tobytes()))
        self._write(b"".join(indexes))
        self._chunk_indexes.append(ChunkPlace(chunk.start_ns, chunk.end_ns, chunk_offset, chunk_length,
                                               index_offsets, self._position - chunk_offset - chunk_length,
                                               len(compressed), len(records)))

    def add_chunk(self, chunk_and_indexes: bytes, place: ChunkPlace) -> None:
        """Append a chunk and its message indexes, copied as they are from ``place`` in another file
        with the same channel ids (their counts: :meth:`add_counts`)."""
        self._close_chunk()
        delta = self._position - place.offset
        self._write(chunk_and_indexes)
        self._chunk_indexes.append(ChunkPlace(
            place.start_ns, place.end_ns, place.offset + delta, place.length,
            {c: o + delta for c, o in place.message_index_offsets.items()}, place.message_index_length,
            place.compressed_size, place.uncompressed_size, place.compression))

    def add_counts(self, channel_message_counts: Mapping[int, int], start_ns: int, end_ns: int) -> None:
        """Messages of copied chunks, per channel, and their time span (for the statistics)."""
        for channel_id, count in channel_message_counts.items():
            self.channel_message_counts[channel_id] += count
        if sum(channel_message_counts.values()):
            self.message_start_ns = start_ns if self.message_start_ns is None else min(self.message_start_ns,
                                                                                        start_ns)
            self.message_end_ns = end_ns if self.message_end_ns is None else max(self.message_end_ns, end_ns)

    # --- the end -------------------------------------------------------------------------------
    def finish(self) -> None:
        """Close the open chunk, write Data End, the summary section and the footer."""
        self._close_chunk()
        self._write(_record(DATA_END, struct.pack("<I", self._data_crc)))
        summary_start = self._position
        groups: list[tuple[int, bytes]] = []
        start_ns, end_ns = self.message_start_ns or 0, self.message_end_ns or 0
        counts = b"".join(struct.pack("<HQ", c, n) for c, n in self.channel_message_counts.items())
        statistics = _record(STATISTICS, struct.pack(
            "<QHIIIIQQ", sum(self.channel_message_counts.values()), len(self._schemas), len(self._channels), 0,
            len(self._metadata_indexes), len(self._chunk_indexes), start_ns, end_ns)
            + struct.pack("<I", len(counts)) + counts)
        for opcode, records in ((SCHEMA, self._schemas), (CHANNEL, self._channels), (STATISTICS, [statistics]),
                                (METADATA_INDEX, self._metadata_indexes),
                                (CHUNK_INDEX, [index.record() for index in self._chunk_indexes])):
            if records:
                groups.append((opcode, b"".join(records)))
        summary = b""
        offsets = b""
        for opcode, data in groups:
            offsets += _record(SUMMARY_OFFSET, struct.pack("<BQQ", opcode, summary_start + len(summary), len(data)))
            summary += data
        summary_offset_start = summary_start + len(summary)
        footer_head = struct.pack("<BQQQ", FOOTER, 8 + 8 + 4, summary_start, summary_offset_start)
        crc = zlib.crc32(summary + offsets + footer_head)
        self._stream.write(summary + offsets + footer_head + struct.pack("<I", crc) + MAGIC)
