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
from pathlib import Path

from netgen.errors import BuildError


class Telemetry:
    def __init__(self, path: str | Path | None):
        self.path = Path(path) if path else None
        self.f = None
        self.rows = 0

    def setup(self):
        if self.path:
            try:
                self.path.parent.mkdir(parents=True, exist_ok=True)
                self.f = open(self.path, "w", buffering=1 << 16)
            except OSError as e:
                raise BuildError(f"cannot write telemetry {self.path}: {e.strerror or e}") from None
        return self

    def write(self, row: dict):
        if self.f is None:
            return
        try:
            self.f.write(json.dumps(row, separators=(",", ":"), default=_num) + "\n")
        except OSError as e:
            raise BuildError(f"cannot write telemetry {self.path}: {e.strerror or e}") from None
        self.rows += 1

    def teardown(self):
        if self.f is not None:
            self.f.close()
            self.f = None


def _num(o):
    try:
        v = float(o)
        return None if math.isnan(v) else v
    except (TypeError, ValueError):
        return str(o)
