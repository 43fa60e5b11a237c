"""Top-down map of the running simulation, drawn with QPainter.

World metres in, pixels out: the view follows the ego (north up), the wheel zooms. Layers,
back to front: built chunks (outline) and the tiles loaded in PyBullet (tinted), building
footprints, footpaths, lanes for cars, the route, the destination, SUMO's actors (vehicles
as boxes, persons as dots) and the ego (a green arrow). The static layers are turned into
QPainterPaths once, when the world arrives.
"""
from __future__ import annotations

import math

import numpy as np
from PyQt5.QtCore import QPointF, QRectF, Qt
from PyQt5.QtGui import QColor, QImage, QPainter, QPainterPath, QPen, QPolygonF, QTransform
from PyQt5.QtWidgets import QSizePolicy, QWidget

COL = {
    "bg": QColor(236, 238, 232),
    "chunk": QColor(120, 120, 140),
    "tile": QColor(120, 170, 230, 55),
    "building": QColor(200, 180, 160),
    "building_edge": QColor(160, 140, 120),
    "path": QColor(170, 160, 150),
    "road": QColor(90, 92, 100),
    "route": QColor(30, 110, 255),
    "goal": QColor(220, 30, 160),
    "vehicle": QColor(230, 110, 20),
    "person": QColor(150, 40, 200),
    "ego": QColor(0, 170, 60),
    "text": QColor(40, 40, 40),
}


def _path_of(lines, closed=False) -> QPainterPath:
    p = QPainterPath()
    for a in lines:
        a = np.asarray(a, dtype=float)
        if len(a) < 2:
            continue
        p.moveTo(float(a[0, 0]), float(a[0, 1]))
        for x, y in a[1:, :2]:
            p.lineTo(float(x), float(y))
        if closed:
            p.closeSubpath()
    return p


class MapView(QWidget):
    def __init__(self, parent=None):
        super().__init__(parent)
        self.setMinimumSize(240, 200)
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Expanding)
        self.setFocusPolicy(Qt.ClickFocus)
        self.scale = 0.8               # pixels per metre
        self.clear()

    # --- data in --------------------------------------------------------------------------
    def clear(self):
        self.roads = self.paths = self.buildings = None
        self._static = None
        self._static_version = 0
        self.chunks: dict = {}
        self.tiles: dict = {}
        self.route = None
        self.goal_xy = None
        self.ego = None
        self.actors = None
        self.center = (0.0, 0.0)
        self.update()

    def set_world(self, info: dict):
        """The static layers (from the worker's `started` signal, and again whenever the
        world has grown)."""
        layers = info["layers"]
        self.roads = _path_of(layers.get("roads", []))
        self.paths = _path_of(layers.get("paths", []))
        self.buildings = _path_of(layers.get("buildings", []), closed=True)
        self.n_buildings = len(layers.get("buildings", []))
        self.chunks = dict(info.get("chunks", {}))
        self._static_version += 1
        if "route" in info:
            self.set_route(info.get("route"), info.get("goal_xy"))
        self.update()

    def set_route(self, xy, goal_xy=None):
        self.route = _path_of([xy]) if xy is not None and len(xy) >= 2 else None
        self.goal_xy = goal_xy
        self.update()

    def set_frame(self, f: dict):
        e = f["ego"]
        self.ego = (e["x"], e["y"], e["yaw"])
        self.center = (e["x"], e["y"])
        self.actors = f.get("actors")
        if "world" in f:
            self.set_world(f["world"])
        if "tiles" in f:
            self.tiles = f["tiles"]
        if "route" in f:
            self.set_route(f["route"], f.get("goal_xy"))
        self.update()

    # --- view -----------------------------------------------------------------------------
    def world_transform(self) -> QTransform:
        t = QTransform()
        t.translate(self.width() / 2.0, self.height() / 2.0)
        t.scale(self.scale, -self.scale)          # north up
        t.translate(-self.center[0], -self.center[1])
        return t

    def to_screen(self, x: float, y: float) -> QPointF:
        return self.world_transform().map(QPointF(x, y))

    def wheelEvent(self, ev):
        k = 1.25 if ev.angleDelta().y() > 0 else 1 / 1.25
        self.scale = max(0.05, min(20.0, self.scale * k))
        self.update()

    # --- drawing --------------------------------------------------------------------------
    @staticmethod
    def _pen(c, w_px, px, style=Qt.SolidLine):
        q = QPen(c, w_px * px, style)
        q.setCapStyle(Qt.RoundCap)
        q.setJoinStyle(Qt.RoundJoin)
        return q

    def _render_static(self):
        """Chunks, buildings, footpaths and roads into an image three times the widget's size
        around the current centre: frames then only move it (a city's lanes take ~100 ms to
        draw, too long to redraw 20 times a second)."""
        W, H = min(3 * max(self.width(), 1), 4000), min(3 * max(self.height(), 1), 4000)
        img = QImage(W, H, QImage.Format_ARGB32_Premultiplied)
        img.fill(Qt.transparent)
        cx, cy = self.center
        p = QPainter(img)
        p.setRenderHint(QPainter.Antialiasing, True)
        t = QTransform()
        t.translate(W / 2.0, H / 2.0)
        t.scale(self.scale, -self.scale)
        t.translate(-cx, -cy)
        p.setTransform(t)
        px = 1.0 / self.scale
        p.setBrush(Qt.NoBrush)
        p.setPen(self._pen(COL["chunk"], 1.2, px, Qt.DashLine))
        for xmin, ymin, xmax, ymax in self.chunks.values():
            p.drawRect(QRectF(xmin, ymin, xmax - xmin, ymax - ymin))
        p.setPen(self._pen(COL["building_edge"], 0.6, px))
        p.setBrush(COL["building"])
        p.drawPath(self.buildings)
        p.setBrush(Qt.NoBrush)
        p.setPen(self._pen(COL["path"], 0.8, px))
        p.drawPath(self.paths)
        p.setPen(self._pen(COL["road"], max(1.5, 3.2 * self.scale), px))
        p.drawPath(self.roads)
        p.end()
        self._static = (img, (cx, cy), self.scale, self._static_version)

    def paintEvent(self, ev):
        p = QPainter(self)
        p.setRenderHint(QPainter.Antialiasing, True)
        p.fillRect(self.rect(), COL["bg"])
        if self.roads is None:
            p.setPen(COL["text"])
            p.drawText(self.rect(), Qt.AlignCenter, "The map appears when the simulation runs")
            p.end()
            return
        # the loaded tiles, under everything else
        p.save()
        p.setTransform(self.world_transform())
        px = 1.0 / self.scale          # one pixel in metres: widths in pixels whatever the zoom
        p.setPen(Qt.NoPen)
        p.setBrush(COL["tile"])
        for xmin, ymin, xmax, ymax in self.tiles.values():
            p.drawRect(QRectF(xmin, ymin, xmax - xmin, ymax - ymin))
        p.restore()
        # the static layers, from the cached image (re-rendered when the view leaves it)
        off = self._static_offset()
        if off is None:
            self._render_static()
            off = self._static_offset()
        p.drawImage(QPointF(*off), self._static[0])
        p.save()
        p.setTransform(self.world_transform())
        pen = lambda c, w, style=Qt.SolidLine: self._pen(c, w, px, style)   # noqa: E731
        # route and destination
        if self.route is not None:
            p.setBrush(Qt.NoBrush)
            p.setPen(pen(COL["route"], 3.0))
            p.drawPath(self.route)
        if self.goal_xy is not None:
            p.setPen(pen(COL["goal"], 2.0))
            p.setBrush(COL["goal"])
            p.drawEllipse(QPointF(*self.goal_xy), 6 * px, 6 * px)
        # actors
        a = self.actors
        if a and a.get("x"):
            for kind, x, y, yaw, L, W in zip(a["kind"], a["x"], a["y"], a["yaw"], a["length"], a["width"]):
                if kind == "person":
                    p.setPen(Qt.NoPen)
                    p.setBrush(COL["person"])
                    r = max(0.6, 3.0 * px)
                    p.drawEllipse(QPointF(x, y), r, r)
                else:
                    self._box(p, x, y, yaw, max(L, 7 * px), max(W, 3.5 * px), COL["vehicle"])
        # the ego: a box with an arrow
        if self.ego is not None:
            x, y, yaw = self.ego
            self._box(p, x, y, yaw, max(4.6, 10 * px), max(1.9, 6 * px), COL["ego"])
            c, s = math.cos(yaw), math.sin(yaw)
            r = max(6.0, 14 * px)
            tri = QPolygonF([QPointF(x + c * r, y + s * r), QPointF(x - s * r * 0.4, y + c * r * 0.4),
                             QPointF(x + s * r * 0.4, y - c * r * 0.4)])
            p.setBrush(COL["ego"])
            p.setPen(Qt.NoPen)
            p.drawPolygon(tri)
        p.restore()
        # scale bar
        p.setPen(COL["text"])
        m = self._nice(80 / self.scale)
        x0, y0 = 12, self.height() - 14
        p.drawLine(x0, y0, x0 + int(m * self.scale), y0)
        p.drawText(x0, y0 - 4, f"{m:g} m")
        p.end()

    def _static_offset(self):
        """Where the cached static image goes in the widget, or None if it must be redrawn."""
        if self._static is None:
            return None
        img, (cx0, cy0), scale, version = self._static
        if scale != self.scale or version != self._static_version:
            return None
        cx, cy = self.center
        ox = self.width() / 2.0 - img.width() / 2.0 + self.scale * (cx0 - cx)
        oy = self.height() / 2.0 - img.height() / 2.0 - self.scale * (cy0 - cy)
        if ox > 0 or oy > 0 or ox + img.width() < self.width() or oy + img.height() < self.height():
            return None
        return ox, oy

    def _box(self, p, x, y, yaw, L, W, colour):
        c, s = math.cos(yaw), math.sin(yaw)
        hl, hw = L / 2, W / 2
        pts = [QPointF(x + c * dx - s * dy, y + s * dx + c * dy)
               for dx, dy in ((hl, hw), (-hl, hw), (-hl, -hw), (hl, -hw))]
        p.setPen(Qt.NoPen)
        p.setBrush(colour)
        p.drawPolygon(QPolygonF(pts))

    @staticmethod
    def _nice(v: float) -> float:
        e = 10 ** math.floor(math.log10(max(v, 1e-9)))
        for k in (1, 2, 5, 10):
            if k * e >= v:
                return k * e
        return 10 * e
