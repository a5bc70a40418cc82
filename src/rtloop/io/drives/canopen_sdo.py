"""SDO transfers of any length (CiA 301 §7.2.4.3): expedited up to 4 bytes, segmented beyond, both
sides. Plain objects on bytes, no socket: the drive device (``io/drives/canopen.py``) runs a client
transfer over its CAN socket before T0, the emulated node (``io/drives/canopen_node.py``) answers
with :class:`SdoServer`.

A client transfer gives the request to send (:attr:`SdoTransfer.request`) and takes each answer
(:meth:`SdoTransfer.take`): ``None`` for an answer that is not its own, ``False`` when the next
request is ready, ``True`` when the transfer is done; an abort from the node is
:class:`~rtloop.io.drives.canopen_wire.SdoAbort`. One segment carries 7 bytes, its first byte the
toggle bit (alternating from 0), how many of the 7 carry no data, and whether it is the last.
"""

from __future__ import annotations

import struct

from rtloop.io.drives.canopen_wire import SdoAbort

__all__ = ["ABORT_TOGGLE", "SdoDownload", "SdoServer", "SdoUpload"]

ABORT_TOGGLE, ABORT_COMMAND = 0x05030000, 0x05040001
"""Abort codes: toggle bit not alternated; command specifier not valid or unknown."""
SEGMENT_BYTES = 7


class SdoTransfer:
    """One client transfer on ``index:subindex``."""

    def __init__(self, index: int, subindex: int) -> None:
        self.index, self.subindex = index, subindex
        self.request = b""
        self.toggle = 0
        self.segmented = False

    def _abort_or_other(self, data: bytes) -> bool:
        """True when ``data`` is not this transfer's answer; an abort of it raises."""
        if len(data) < 8:
            return True
        if data[0] == 0x80:
            index, subindex = struct.unpack_from("<HB", data, 1)
            if (index, subindex) == (self.index, self.subindex):
                raise SdoAbort(index, subindex, struct.unpack_from("<I", data, 4)[0])
            return True
        return False

    def _toggled(self, data: bytes) -> None:
        if data[0] >> 4 & 1 != self.toggle:
            raise SdoAbort(self.index, self.subindex, ABORT_TOGGLE)
        self.toggle ^= 1

    def take(self, data: bytes) -> bool | None:
        raise NotImplementedError


class SdoUpload(SdoTransfer):
    """Read ``index:subindex``: :attr:`value` once done."""

    def __init__(self, index: int, subindex: int) -> None:
        super().__init__(index, subindex)
        self.request = struct.pack("<BHB4x", 0x40, index, subindex)
        self.value = b""
        self.size: int | None = None

    def take(self, data: bytes) -> bool | None:
        if self._abort_or_other(data):
            return None
        command = data[0]
        if not self.segmented:
            if command & 0xE0 != 0x40 or struct.unpack_from("<HB", data, 1) != (self.index, self.subindex):
                return None
            if command & 0x02:  # expedited: the value is in this answer
                self.value = bytes(data[4:8 - (command >> 2 & 3)]) if command & 0x01 else bytes(data[4:8])
                return True
            self.size = struct.unpack_from("<I", data, 4)[0] if command & 0x01 else None
            self.segmented = True
        else:
            if command & 0xE0 != 0x00:
                return None
            self._toggled(data)
            self.value += bytes(data[1:8 - (command >> 1 & 7)])
            if command & 0x01:  # the last segment
                if self.size is not None and len(self.value) != self.size:
                    raise SdoAbort(self.index, self.subindex, 0x06070010)  # length does not match
                return True
        self.request = bytes([0x60 | self.toggle << 4]) + bytes(7)
        return False


class SdoDownload(SdoTransfer):
    """Write ``value`` (bytes, little-endian for a number) to ``index:subindex``."""

    def __init__(self, index: int, subindex: int, value: bytes) -> None:
        super().__init__(index, subindex)
        self.value = value
        self.sent = 0
        if 0 < len(value) <= 4:  # expedited, size indicated
            self.request = struct.pack("<BHB", 0x23 | (4 - len(value)) << 2, index, subindex) + value.ljust(4, b"\0")
        else:  # segmented, size indicated
            self.request = struct.pack("<BHBI", 0x21, index, subindex, len(value))
            self.segmented = True

    def take(self, data: bytes) -> bool | None:
        if self._abort_or_other(data):
            return None
        command = data[0]
        if self.sent == 0 and command == 0x60 and struct.unpack_from("<HB", data, 1) == (self.index, self.subindex):
            if not self.segmented:
                return True
        elif self.segmented and command & 0xE0 == 0x20:
            self._toggled(data)
            if self.sent >= len(self.value):
                return True
        else:
            return None
        chunk = self.value[self.sent:self.sent + SEGMENT_BYTES]
        self.sent += len(chunk)
        last = 1 if self.sent >= len(self.value) else 0
        self.request = bytes([self.toggle << 4 | (SEGMENT_BYTES - len(chunk)) << 1 | last]) + chunk.ljust(7, b"\0")
        return False


class SdoServer:
    """The node's side of segmented transfers (one at a time, as CiA 301 has it per SDO channel).

    ``read(index, sub)`` gives an object's bytes, ``write(index, sub, data)`` stores them; each
    returns an abort code instead (an int) when it refuses."""

    def __init__(self) -> None:
        self.upload: bytes | None = None  # the rest of the value being read
        self.download: bytearray | None = None
        self.key = (0, 0)
        self.size = 0
        self.toggle = 0

    def initiate_upload(self, index: int, subindex: int, value: bytes) -> bytes:
        if 0 < len(value) <= 4:  # expedited (an empty value goes as one empty segment)
            self.upload = None
            return struct.pack("<BHB", 0x43 | (4 - len(value)) << 2, index, subindex) + value.ljust(4, b"\0")
        self.upload, self.key, self.toggle = value, (index, subindex), 0
        return struct.pack("<BHBI", 0x41, index, subindex, len(value))

    def upload_segment(self, data: bytes) -> bytes:
        if self.upload is None:
            return self._abort(ABORT_COMMAND)
        if data[0] >> 4 & 1 != self.toggle:
            self.upload = None
            return self._abort(ABORT_TOGGLE)
        chunk, self.upload = self.upload[:SEGMENT_BYTES], self.upload[SEGMENT_BYTES:]
        last = 0 if self.upload else 1
        answer = bytes([self.toggle << 4 | (SEGMENT_BYTES - len(chunk)) << 1 | last]) + chunk.ljust(7, b"\0")
        self.toggle ^= 1
        if last:
            self.upload = None
        return answer

    def initiate_download(self, index: int, subindex: int, data: bytes) -> bytes:
        self.download, self.key, self.toggle = bytearray(), (index, subindex), 0
        self.size = struct.unpack_from("<I", data, 4)[0] if data[0] & 0x01 else -1
        return struct.pack("<BHB4x", 0x60, index, subindex)

    def download_segment(self, data: bytes) -> tuple[bytes, bytes | None]:
        """(the answer, the whole value once the last segment came)."""
        if self.download is None:
            return self._abort(ABORT_COMMAND), None
        if data[0] >> 4 & 1 != self.toggle:
            self.download = None
            return self._abort(ABORT_TOGGLE), None
        self.download += data[1:8 - (data[0] >> 1 & 7)]
        answer = bytes([0x20 | self.toggle << 4]) + bytes(7)
        self.toggle ^= 1
        if not data[0] & 0x01:
            return answer, None
        value, self.download = bytes(self.download), None
        if self.size >= 0 and len(value) != self.size:
            return self._abort(0x06070010), None
        return answer, value

    def _abort(self, code: int) -> bytes:
        return struct.pack("<BHBI", 0x80, *self.key, code)
