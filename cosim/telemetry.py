"""Telemetry: one JSON object per SUMO step, one line each (JSONL).

Fields: t, lat, lon, alt_m (the ego's height above the elevation source's datum), x, y,
yaw_deg (0 = east, counter-clockwise), speed_mps, edge (SUMO edge or null), lane,
lateral_offset_m (from the followed lane's centreline, left positive), on_road, vehicles,
persons (mirrored counts), chunks_loaded, tiles_loaded, frame_ms, plus control and
planning fields (throttle, brake, steer, target_speed_mps, reason: what sets the autopilot's
target speed, e.g. "cruise", "lead vehicle", "red light", "crossing"; mode: auto or manual) and
SUMO's own counts (sumo_vehicles, sumo_persons).
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

from netgen.errors import BuildError


class Telemetry:
    """The rows go to the file in blocks of about 64 KB, each block whole or not at all:
    when a write fails (a full disk, a file size limit), the file is cut back to the end
    of its last whole row and the run stops with one line that says how many rows the
    file keeps. So the file never ends inside a row."""

    BLOCK_BYTES = 1 << 16

    def __init__(self, path: str | Path | None):
        self.path = Path(path) if path else None
        self.f = None               # the file descriptor (None when there is no file)
        self.rows = 0               # rows given to write()
        self.rows_written = 0       # rows in the file
        self._size = 0              # the file's length: its whole rows
        self._block: list[bytes] = []
        self._block_bytes = 0

    def setup(self):
        if self.path:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self.f = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            except OSError as e:
                raise BuildError(f"cannot write telemetry {self.path}: {e.strerror or e}") from None
        return self

    def write(self, row: dict):
        if self.f is None:
            return
        line = (json.dumps(row, separators=(",", ":"), default=_num) + "\n").encode()
        self._block.append(line)
        self._block_bytes += len(line)
        self.rows += 1
        if self._block_bytes >= self.BLOCK_BYTES:
            self.flush()

    def flush(self):
        """Write the rows held so far; on failure cut the file back and raise BuildError."""
        if self.f is None or not self._block:
            return
        data = b"".join(self._block)
        n_rows = len(self._block)
        self._block, self._block_bytes = [], 0
        view = memoryview(data)
        try:
            while view:
                view = view[os.write(self.f, view):]
        except OSError as e:
            try:
                os.ftruncate(self.f, self._size)
            except OSError:
                pass
            fd, self.f = self.f, None
            os.close(fd)
            raise BuildError(f"cannot write telemetry {self.path}: {e.strerror or e} "
                             f"(it keeps its first {self.rows_written} rows)") from None
        self._size += len(data)
        self.rows_written += n_rows

    def teardown(self):
        if self.f is not None:
            try:
                self.flush()
            finally:
                if self.f is not None:
                    os.close(self.f)
                    self.f = None


def _num(o):
    try:
        v = float(o)
        return None if math.isnan(v) else v
    except (TypeError, ValueError):
        return str(o)
