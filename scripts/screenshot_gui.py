#!/usr/bin/env python3
"""Render the launcher with a running simulation offscreen and save a screenshot.

    .venv/bin/python scripts/screenshot_gui.py                 # -> docs/gui.png
    .venv/bin/python scripts/screenshot_gui.py --preset kouvola --seconds 30 --out /tmp/gui.png

The window is driven as a user would: the preset is picked, Start is pressed, and after
the given simulated seconds ``QWidget.grab()`` renders it into a PNG. Runs without a display
(Qt's offscreen platform) unless --onscreen is given.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def render(out: Path, preset: str = "kouvola", seconds: float = 25.0, traffic: str = "normal",
           worlds: str | None = None, size=(1280, 820), dest: tuple | None = None,
           timeout_s: float = 600.0) -> dict:
    from PyQt5.QtWidgets import QApplication

    from ui import validation as V
    from ui.app import MainWindow

    app = QApplication.instance() or QApplication([sys.argv[0]])
    w = MainWindow(out_root=worlds, realtime=False, preset=preset)
    w.resize(*size)
    w.show()
    t_end = time.monotonic() + timeout_s

    def wait(cond, what):
        while not cond():
            app.processEvents()
            time.sleep(0.005)
            if w.state is V.State.ERROR:
                raise SystemExit(f"error: {w.machine.message}")
            if time.monotonic() > t_end:
                raise SystemExit(f"timed out waiting for {what}")

    try:
        w.cb_traffic.setCurrentText(traffic)
        wait(lambda: w.state is V.State.READY, "the inputs to be checked")
        w.btn_start.click()
        wait(lambda: w.last_frame is not None, "the first frame")
        if dest:
            w.ed_dest_lat.setText(f"{dest[0]:.6f}")
            w.ed_dest_lon.setText(f"{dest[1]:.6f}")
            w.btn_goal.click()
            wait(lambda: w.last_goal is not None, "the route")
        wait(lambda: w.last_frame["t"] >= seconds and w.camera.image is not None, f"{seconds} simulated seconds")
        # one more camera frame and paint, so that the picture is of the same moment
        n = w.camera.frames
        wait(lambda: w.camera.frames > n, "a fresh camera frame")
        app.processEvents()
        out.parent.mkdir(parents=True, exist_ok=True)
        if not w.grab().save(str(out)):
            raise SystemExit(f"could not write {out}")
        return {"out": str(out), "t": w.last_frame["t"], "status": w.status_label.text()}
    finally:
        w.shutdown()
        w.close()


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(REPO / "docs" / "gui.png"))
    p.add_argument("--preset", default="kouvola")
    p.add_argument("--seconds", type=float, default=25.0, help="simulated seconds before the picture")
    p.add_argument("--traffic", default="normal")
    p.add_argument("--worlds", help="where built worlds are kept (default: the launcher's)")
    p.add_argument("--size", default="1280x820", help="window size WxH")
    p.add_argument("--dest", metavar="LAT,LON", help="set this destination once the car drives")
    p.add_argument("--onscreen", action="store_true", help="use the real display instead of offscreen")
    a = p.parse_args(argv)
    if not a.onscreen:
        os.environ["QT_QPA_PLATFORM"] = "offscreen"
    size = tuple(int(v) for v in a.size.lower().split("x"))
    dest = tuple(float(v) for v in a.dest.split(",")) if a.dest else None
    info = render(Path(a.out), a.preset, a.seconds, a.traffic, a.worlds, size, dest)
    print(f"wrote {info['out']} at t={info['t']:.1f} s: {info['status']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
