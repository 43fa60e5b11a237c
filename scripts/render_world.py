"""Render a built world to PNG with PyBullet's camera (TinyRenderer, no display needed).

    python scripts/render_world.py WORLD_DIR OUT.png [--x X --y Y] [--top]

A perspective view from above the given point (default: the world's centre), looking north.
"""
from __future__ import annotations

import argparse
import math
import sys

import numpy as np


def save_png(path, rgb: np.ndarray):
    import zlib, struct

    h, w, _ = rgb.shape
    raw = b"".join(b"\x00" + rgb[r].tobytes() for r in range(h))

    def chunk(t, d):
        return struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)

    data = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)) + \
        chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b"")
    with open(path, "wb") as f:
        f.write(data)


def main(argv=None):
    from cosim.physics import PhysicsWorld
    from cosim.world import World

    ap = argparse.ArgumentParser()
    ap.add_argument("world")
    ap.add_argument("out")
    ap.add_argument("--x", type=float, default=0.0)
    ap.add_argument("--y", type=float, default=0.0)
    ap.add_argument("--height", type=float, default=140.0)
    ap.add_argument("--back", type=float, default=220.0)
    ap.add_argument("--yaw", type=float, default=90.0, help="view heading, degrees (90 = north)")
    ap.add_argument("--width", type=int, default=1200)
    ap.add_argument("--px-height", type=int, default=700)
    a = ap.parse_args(argv)
    w = World(a.world)
    pw = PhysicsWorld(w, visuals=True).setup()
    pw.update(a.x, a.y, keep_radius=650.0, budget_ms=1e9)
    z = float(np.nan_to_num(w.ground_z(a.x, a.y)[0]))
    h = math.radians(a.yaw)
    eye = [a.x - a.back * math.cos(h), a.y - a.back * math.sin(h), z + a.height]
    target = [a.x + 60 * math.cos(h), a.y + 60 * math.sin(h), z]
    img = pw.camera_image(eye, target, a.width, a.px_height, fov=60, far=1500)
    save_png(a.out, img)
    print(f"{a.out}: {len(pw.tiles)} tiles, {pw.body_count()} bodies")
    pw.teardown()


if __name__ == "__main__":
    sys.exit(main())
