"""``.tlog`` recording: each frame as an 8-byte big-endian UNIX time in microseconds, then the raw MAVLink frame.

This is the format MAVProxy, Mission Planner, MAVExplorer and pymavlink's ``mavlogdump.py`` read.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path
from types import TracebackType
from typing import BinaryIO

_STAMP = struct.Struct(">Q")


class TlogWriter:
    """Appends frames to a ``.tlog`` file. Writes are buffered; ``close`` flushes."""

    def __init__(self, path: Path | str) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._file: BinaryIO | None = self.path.open("ab")
        self.frames_written = 0

    def write(self, frame: bytes, *, unix_time_us: int | None = None) -> None:
        if self._file is None:
            return
        stamp = unix_time_us if unix_time_us is not None else time.time_ns() // 1000
        self._file.write(_STAMP.pack(stamp) + frame)
        self.frames_written += 1

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()
