"""The desktop launcher (``cosim gui``): inputs on the left, the running simulation on the right.

The window is a thin client of the Python API (:class:`cosim.config.SimConfig`,
:class:`cosim.sim.Simulation`): it turns what the user typed into a SimConfig
(:mod:`ui.validation`), hands it to :class:`ui.worker.SimWorker` in a QThread, and shows what
comes back through signals. States (see :class:`ui.validation.StateMachine`):

    Idle --edit--> Input checked --invalid--> Error --edit--> Input checked
                                 --valid----> Ready --edit--> Input checked
    Ready --Start--> Simulation --Stop--> Stop --stopped--> Idle (inputs are checked again)
    Simulation --failed--> Error

Keys while the simulation runs and the focus is not in a text field: arrows / WASD drive
(throttle, brake, steer), R toggles reverse, M toggles manual and automatic driving, Esc leaves
a text field.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

from PyQt5.QtCore import QEvent, QRectF, Qt, QTimer, pyqtSignal
from PyQt5.QtGui import QImage, QPainter, QColor
from PyQt5.QtWidgets import (QAbstractSpinBox, QApplication, QButtonGroup, QCheckBox, QComboBox,
                             QFileDialog, QFormLayout, QFrame, QGridLayout, QGroupBox, QHBoxLayout,
                             QLabel, QLineEdit, QMainWindow, QProgressBar, QPushButton, QRadioButton,
                             QScrollArea, QSizePolicy, QSplitter, QStatusBar, QStyle, QVBoxLayout,
                             QWidget)

from cosim.config import DENSITIES, MAX_SPEED_MPS
from cosim.display import display_problem
from netgen.config import MAX_RINGS, QUALITY
from netgen.errors import CosimError, SimulationError

from . import validation as V
from .mapview import MapView
from .worker import CheckWorker, SimWorker, WorkerThread

KEYS = {Qt.Key_Up: "up", Qt.Key_Down: "down", Qt.Key_Left: "left", Qt.Key_Right: "right",
        Qt.Key_W: "w", Qt.Key_A: "a", Qt.Key_S: "s", Qt.Key_D: "d", Qt.Key_M: "m", Qt.Key_R: "r"}
ERROR_STYLE = "border: 1px solid #d0302a; background: #fff3f2;"


def has_display(env=None) -> bool:
    """Can PyBullet open its own 3D window here? (It needs an X server on Linux:
    ``cosim.display.display_problem``.)"""
    return display_problem(env) is None


class CameraView(QWidget):
    """PyBullet's camera image, scaled to fit with its aspect ratio."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.image: QImage | None = None
        self.frames = 0
        self.setMinimumSize(240, 135)
        self.setSizePolicy(QSizePolicy.Expanding, QSizePolicy.Expanding)
        self.setFocusPolicy(Qt.ClickFocus)

    def set_image(self, img: QImage):
        self.image = img
        self.frames += 1
        self.update()

    def clear(self):
        self.image = None
        self.update()

    def paintEvent(self, ev):
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(30, 32, 36))
        if self.image is None or self.image.isNull():
            p.setPen(QColor(200, 200, 200))
            p.drawText(self.rect(), Qt.AlignCenter, "Camera view from the car")
        else:
            iw, ih = self.image.width(), self.image.height()
            k = min(self.width() / iw, self.height() / ih)
            w, h = iw * k, ih * k
            p.setRenderHint(QPainter.SmoothPixmapTransform, True)
            p.drawImage(QRectF((self.width() - w) / 2, (self.height() - h) / 2, w, h), self.image)
        p.end()


class MainWindow(QMainWindow):
    # window -> workers (queued: the receivers live in the worker threads)
    _to_start = pyqtSignal(object)
    _to_speed = pyqtSignal(float)
    _to_goal = pyqtSignal(object)
    _to_key_press = pyqtSignal(str)
    _to_key_release = pyqtSignal(str)
    _to_view = pyqtSignal(str)
    _to_check = pyqtSignal(int, object)
    # state changes, for scripts and tests: (old state name, new state name, message)
    state_changed = pyqtSignal(str, str, str)

    CHECK_DELAY_MS = 250        # the road check waits for the user to stop typing

    def __init__(self, out_root: str | Path | None = None, realtime: bool = True, preset: str | None = None):
        super().__init__()
        from netgen.config import default_cache_dir
        from netgen.presets import DEFAULT_PRESET, list_presets

        self.setWindowTitle("cosim — drive anywhere")
        self.out_root = Path(out_root) if out_root else default_cache_dir() / "worlds"
        self.presets = list_presets()
        self.machine = V.StateMachine()
        self.machine.subscribe(self._on_state)
        self.config = None                 # the SimConfig of the last successful check
        self.last_frame: dict | None = None
        self.last_summary = ""
        self.last_goal: dict | None = None
        self.notes: list[str] = []
        self._note = ""
        self._gen = 0
        self._pending = None
        self._close_pending = False
        self._closed = False
        self._running = False              # the worker has started stepping
        self._warning = ""
        self._warning_until = 0.0
        self._init_done = False            # widgets fire change signals while being filled in
        self._build_ui(preset or DEFAULT_PRESET, realtime)
        self._start_threads()
        self._debounce = QTimer(self)
        self._debounce.setSingleShot(True)
        self._debounce.setInterval(self.CHECK_DELAY_MS)
        self._debounce.timeout.connect(self._send_check)
        self._speed_timer = QTimer(self)
        self._speed_timer.setSingleShot(True)
        self._speed_timer.setInterval(300)
        self._speed_timer.timeout.connect(self._send_speed)
        QApplication.instance().installEventFilter(self)
        self._init_done = True
        self._on_state(V.State.IDLE, V.State.IDLE, "")
        # Idle: the defaults are filled in; they are checked at the next turn of the event loop
        QTimer.singleShot(0, self._inputs_changed)

    # ----------------------------------------------------------------------------------
    # layout
    # ----------------------------------------------------------------------------------
    def _build_ui(self, preset: str, realtime: bool):
        central = QWidget()
        self.setCentralWidget(central)
        root = QHBoxLayout(central)
        left = QWidget()
        left.setFixedWidth(430)
        lv = QVBoxLayout(left)
        lv.setContentsMargins(0, 0, 0, 0)

        # place
        g = QGroupBox("Place")
        gl = QGridLayout(g)
        self.rb_preset = QRadioButton("Preset")
        self.rb_coords = QRadioButton("Start at")
        self.rb_preset.setChecked(True)
        grp = QButtonGroup(self)
        grp.addButton(self.rb_preset)
        grp.addButton(self.rb_coords)
        self.cb_preset = QComboBox()
        for p in self.presets:
            self.cb_preset.addItem(f"{p.name} — {p.environment}", p.name)
            self.cb_preset.setItemData(self.cb_preset.count() - 1, p.place, Qt.ToolTipRole)
        i = self.cb_preset.findData(preset)
        self.cb_preset.setCurrentIndex(max(0, i))
        # (short placeholders: the fields are narrow, and a cut one reads "latitude -90.....")
        self.ed_lat = QLineEdit()
        self.ed_lat.setPlaceholderText("latitude")
        self.ed_lat.setToolTip("start latitude, -90..90 degrees")
        self.ed_lon = QLineEdit()
        self.ed_lon.setPlaceholderText("longitude")
        self.ed_lon.setToolTip("start longitude, -180..180 degrees")
        self.ed_osm = QLineEdit()
        self.ed_osm.setPlaceholderText("optional .osm / .pbf")
        self.ed_osm.setToolTip("an OSM file: .osm, .osm.pbf, .osm.gz or .osm.bz2 (default: the preset's, or Overpass)")
        self.ed_dem = QLineEdit()
        self.ed_dem.setPlaceholderText("optional .hgt / GeoTIFF")
        self.ed_dem.setToolTip("a DEM file: SRTM .hgt / .hgt.zip, or a GeoTIFF in a geographic CRS")
        self.chk_flat = QCheckBox("Flat ground when there is no DEM")
        b_osm = QPushButton("…")
        b_osm.setFixedWidth(28)
        b_osm.clicked.connect(lambda: self._browse(self.ed_osm, "OSM files (*.osm *.pbf *.osm.gz *.osm.bz2 *.xml)"))
        b_dem = QPushButton("…")
        b_dem.setFixedWidth(28)
        b_dem.clicked.connect(lambda: self._browse(self.ed_dem, "DEM files (*.hgt *.zip *.tif *.tiff)"))
        self.b_osm, self.b_dem = b_osm, b_dem
        gl.addWidget(self.rb_preset, 0, 0)
        gl.addWidget(self.cb_preset, 0, 1, 1, 3)
        gl.addWidget(self.rb_coords, 1, 0)
        gl.addWidget(self.ed_lat, 1, 1)
        gl.addWidget(self.ed_lon, 1, 2, 1, 2)
        gl.addWidget(QLabel("OSM file"), 2, 0)
        gl.addWidget(self.ed_osm, 2, 1, 1, 2)
        gl.addWidget(b_osm, 2, 3)
        gl.addWidget(QLabel("DEM file"), 3, 0)
        gl.addWidget(self.ed_dem, 3, 1, 1, 2)
        gl.addWidget(b_dem, 3, 3)
        gl.addWidget(self.chk_flat, 4, 1, 1, 3)
        gl.setColumnStretch(1, 1)
        gl.setColumnStretch(2, 1)
        lv.addWidget(g)

        # world and traffic
        g = QGroupBox("World and traffic")
        fl = QFormLayout(g)
        self.ed_chunks = QLineEdit("1")
        self.ed_chunks.setToolTip(f"rings of 1 km chunks around the car: 0..{MAX_RINGS} (1 -> 3 x 3 km)")
        self.cb_quality = QComboBox()
        self.cb_quality.addItems(list(QUALITY))
        self.cb_quality.setToolTip("terrain resolution (10 / 5 / 2.5 m), scenery density and road mesh detail")
        self.cb_traffic = QComboBox()
        self.cb_traffic.setEditable(True)
        self.cb_traffic.addItems(list(DENSITIES))
        self.cb_traffic.setCurrentText("normal")
        self.cb_traffic.setToolTip("none | light | normal | dense (30 / 80 / 200 vehicles per km², times the "
                                   "preset's traffic_scale: half in Kouvola), or vehicles per km² (0..2000)")
        fl.addRow("Chunks", self.ed_chunks)
        fl.addRow("Quality", self.cb_quality)
        fl.addRow("Traffic", self.cb_traffic)
        lv.addWidget(g)

        # drive
        g = QGroupBox("Drive")
        gl = QGridLayout(g)
        self.ed_speed = QLineEdit("10")
        self.ed_speed.setToolTip(f"the car's set speed, 0..{MAX_SPEED_MPS:.0f} m/s; can be changed while it drives")
        self.ed_dest_lat = QLineEdit()
        self.ed_dest_lat.setPlaceholderText("optional latitude")
        self.ed_dest_lon = QLineEdit()
        self.ed_dest_lon.setPlaceholderText("optional longitude")
        self.btn_goal = QPushButton("Set destination")
        self.btn_goal.setToolTip("route from where the car is now (empty fields: drive on at random)")
        self.btn_goal.clicked.connect(self._send_goal)
        gl.addWidget(QLabel("Speed (m/s)"), 0, 0)
        gl.addWidget(self.ed_speed, 0, 1, 1, 2)
        gl.addWidget(QLabel("Destination"), 1, 0)
        gl.addWidget(self.ed_dest_lat, 1, 1)
        gl.addWidget(self.ed_dest_lon, 1, 2)
        gl.addWidget(self.btn_goal, 2, 1, 1, 2)
        self.chk_gui = QCheckBox("PyBullet 3D window")
        why = self._no_display = display_problem()     # (asked once: it connects to the X server)
        if why is None:
            self.chk_gui.setToolTip("open PyBullet's own 3D window beside the launcher")
        else:
            self.chk_gui.setEnabled(False)
            self.chk_gui.setToolTip(f"no display here ({why}): PyBullet cannot open a window")
        self.chk_realtime = QCheckBox("Real time")
        self.chk_realtime.setChecked(realtime)
        self.chk_realtime.setToolTip("pace the simulation to the wall clock (off: as fast as it runs)")
        gl.addWidget(self.chk_gui, 3, 0, 1, 2)
        gl.addWidget(self.chk_realtime, 3, 2)
        lv.addWidget(g)

        # message, buttons, progress
        self.lbl_msg = QLabel("")
        self.lbl_msg.setWordWrap(True)
        self.lbl_msg.setMinimumHeight(36)
        self.lbl_msg.setTextInteractionFlags(Qt.TextSelectableByMouse)
        lv.addWidget(self.lbl_msg)
        hb = QHBoxLayout()
        self.btn_start = QPushButton("Start")
        self.btn_stop = QPushButton("Stop")
        self.btn_start.clicked.connect(self.start)
        self.btn_stop.clicked.connect(self.stop)
        hb.addWidget(self.btn_start)
        hb.addWidget(self.btn_stop)
        lv.addLayout(hb)
        self.progress = QProgressBar()
        self.progress.setRange(0, 1000)
        self.progress.setTextVisible(True)
        self.progress.setVisible(False)
        lv.addWidget(self.progress)

        # live values
        g = self.live_box = QGroupBox("Live")
        gl = QGridLayout(g)
        self.live = {}
        for r, (k, name) in enumerate([("lat", "Latitude"), ("lon", "Longitude"), ("speed", "Velocity"),
                                       ("t", "Sim time"), ("mode", "Driving"), ("control", "Pedals"),
                                       ("steer", "Steering"), ("route", "Route")]):
            gl.addWidget(QLabel(name), r, 0)
            lab = QLabel("—")
            lab.setTextInteractionFlags(Qt.TextSelectableByMouse)
            lab.setWordWrap(k == "route")       # (the longest: "no destination: driving on at random")
            gl.addWidget(lab, r, 1)
            self.live[k] = lab
        gl.setColumnStretch(1, 1)
        lv.addWidget(g)
        lv.addStretch(1)
        hint = QLabel("Keys: WASD/arrows, R reverse, M manual/auto")
        hint.setToolTip("WASD or the arrows drive; R toggles reverse; M toggles manual and automatic driving; "
                        "Esc leaves a text field")
        hint.setWordWrap(True)
        hint.setStyleSheet("color: #666;")
        lv.addWidget(hint)
        # the inputs scroll where the screen is short (a laptop's 768 px): the window's least
        # height was the whole column's, 939 px
        scroll = QScrollArea()
        scroll.setWidget(left)
        scroll.setWidgetResizable(True)
        scroll.setFrameShape(QFrame.NoFrame)
        scroll.setHorizontalScrollBarPolicy(Qt.ScrollBarAlwaysOff)
        scroll.setFixedWidth(left.width() + self.style().pixelMetric(QStyle.PM_ScrollBarExtent) + 2)
        self.inputs_scroll = scroll
        root.addWidget(scroll)

        # right: camera above the map
        right = QSplitter(Qt.Vertical)
        cam_box = QWidget()
        cv = QVBoxLayout(cam_box)
        cv.setContentsMargins(0, 0, 0, 0)
        top = QHBoxLayout()
        top.addWidget(QLabel("Camera"))
        self.cb_view = QComboBox()
        self.cb_view.addItems(["chase", "driver"])
        self.cb_view.currentTextChanged.connect(lambda v: self._to_view.emit(v))
        self.cb_view.setFocusPolicy(Qt.NoFocus)
        top.addWidget(self.cb_view)
        top.addStretch(1)
        cv.addLayout(top)
        self.camera = CameraView()
        cv.addWidget(self.camera)
        right.addWidget(cam_box)
        self.map = MapView()
        right.addWidget(self.map)
        right.setSizes([300, 420])
        root.addWidget(right, 1)

        self.status_label = QLabel("")
        sb = QStatusBar()
        sb.addWidget(self.status_label, 1)
        self.setStatusBar(sb)
        self.resize(1180, 800)

        self._tips: dict = {}
        self.fields = {"preset": [self.cb_preset], "lat": [self.ed_lat], "lon": [self.ed_lon],
                       "start": [self.ed_lat, self.ed_lon], "chunks": [self.ed_chunks],
                       "speed": [self.ed_speed], "quality": [self.cb_quality], "traffic": [self.cb_traffic],
                       "dest_lat": [self.ed_dest_lat], "dest_lon": [self.ed_dest_lon],
                       "dest": [self.ed_dest_lat, self.ed_dest_lon], "osm": [self.ed_osm], "dem": [self.ed_dem]}
        # every input change is an "edit" (the speed and the destination are live while driving)
        for w in (self.ed_lat, self.ed_lon, self.ed_osm, self.ed_dem, self.ed_chunks, self.ed_dest_lat,
                  self.ed_dest_lon):
            w.textChanged.connect(self._inputs_changed)
        self.ed_speed.textChanged.connect(self._speed_changed)
        for w in (self.cb_preset, self.cb_quality):
            w.currentIndexChanged.connect(self._inputs_changed)
        self.cb_traffic.currentTextChanged.connect(self._inputs_changed)
        self.rb_preset.toggled.connect(self._mode_changed)
        self.chk_flat.toggled.connect(self._inputs_changed)
        self._mode_changed()

    def _browse(self, edit: QLineEdit, filt: str):
        f, _ = QFileDialog.getOpenFileName(self, "Choose a file", str(Path.home()), filt + ";;All files (*)")
        if f:
            edit.setText(f)

    # ----------------------------------------------------------------------------------
    # threads
    # ----------------------------------------------------------------------------------
    def _start_threads(self):
        self.sim_thread = WorkerThread(self)
        self.sim_thread.setObjectName("cosim-sim")
        self.worker = SimWorker()
        self.worker.moveToThread(self.sim_thread)
        self._to_start.connect(self.worker.start)
        self._to_speed.connect(self.worker.set_speed)
        self._to_goal.connect(self.worker.set_goal)
        self._to_key_press.connect(self.worker.key_press)
        self._to_key_release.connect(self.worker.key_release)
        self._to_view.connect(self.worker.set_camera_view)
        self.worker.progress.connect(self._on_progress)
        self.worker.started.connect(self._on_started)
        self.worker.frame.connect(self._on_frame)
        self.worker.warning.connect(self._on_warning)
        self.worker.goal_result.connect(self._on_goal)
        self.worker.speed_result.connect(self._on_speed)
        self.worker.stopped.connect(self._on_stopped)
        self.worker.failed.connect(self._on_failed)
        self.sim_thread.finished.connect(self.worker.deleteLater)
        self.sim_thread.start()

        self.check_thread = WorkerThread(self)
        self.check_thread.setObjectName("cosim-check")
        self.checker = CheckWorker(self.out_root)
        self.checker.moveToThread(self.check_thread)
        self._to_check.connect(self.checker.check)
        self.checker.done.connect(self._on_checked)
        self.check_thread.finished.connect(self.checker.deleteLater)
        self.check_thread.start()

    # ----------------------------------------------------------------------------------
    # inputs and checks
    # ----------------------------------------------------------------------------------
    @property
    def state(self) -> V.State:
        return self.machine.state

    def values(self) -> V.FormValues:
        return V.FormValues(
            mode="preset" if self.rb_preset.isChecked() else "coords",
            preset=self.cb_preset.currentData() or "", lat=self.ed_lat.text(), lon=self.ed_lon.text(),
            chunks=self.ed_chunks.text(), speed=self.ed_speed.text(), quality=self.cb_quality.currentText(),
            traffic=self.cb_traffic.currentText(), dest_lat=self.ed_dest_lat.text(),
            dest_lon=self.ed_dest_lon.text(), osm=self.ed_osm.text(), dem=self.ed_dem.text(),
            flat=self.chk_flat.isChecked(), gui=self.chk_gui.isChecked() and self.chk_gui.isEnabled(),
            realtime=self.chk_realtime.isChecked())

    def _mode_changed(self, *_):
        coords = self.rb_coords.isChecked()
        if coords and not self.ed_lat.text() and not self.ed_lon.text():
            # start from the preset's centre, so there is something sensible to edit
            p = next((p for p in self.presets if p.name == self.cb_preset.currentData()), None)
            if p is not None:
                self.ed_lat.blockSignals(True)
                self.ed_lat.setText(f"{p.center[0]:.5f}")
                self.ed_lat.blockSignals(False)
                self.ed_lon.setText(f"{p.center[1]:.5f}")
        self._apply_enabled()
        self._inputs_changed()

    def _inputs_changed(self, *_):
        """Idle / Ready / Error / Input checked --edit--> Input checked: the range checks at
        once, the road check (maybe reading an OSM file) in the check worker, debounced."""
        if not self._init_done or self._closed or self.state in (V.State.SIMULATION, V.State.STOPPING):
            return
        self.machine.fire("edit")
        self._gen += 1
        ranged, errors = V.check_ranges(self.values())
        self._mark(errors)
        if errors:
            self._debounce.stop()
            if self._note and self.status_label.text() == self._note:
                self._status("")
            self.machine.fire("invalid", "\n".join(e.text() for e in errors))
            return
        self._pending = ranged
        self._debounce.start()

    def _send_check(self):
        if self.state is V.State.CHECKING and self._pending is not None:
            self._to_check.emit(self._gen, self._pending)

    def _on_checked(self, gen: int, res):
        if gen != self._gen or self.state is not V.State.CHECKING:
            return           # the inputs changed since: a newer check is on its way
        self._mark(res.errors)
        self.notes = list(res.notes)
        if self.status_label.text() == self._note:        # an earlier note no longer applies
            self._status("")
        self._note = "; ".join(self.notes)
        if res.ok:
            self.config = res.config
            self.machine.fire("valid")
            if self.notes:
                self._status(self._note)
        else:
            self.config = None
            self.machine.fire("invalid", res.message())

    def _mark(self, errors):
        """Outline the inputs that are wrong; their tooltip says why."""
        bad: dict = {}
        for e in errors:
            for w in self.fields.get(e.field, []):
                bad.setdefault(w, e.text())
        for ws in self.fields.values():
            for w in ws:
                if w not in self._tips:
                    self._tips[w] = w.toolTip()
                w.setStyleSheet(ERROR_STYLE if w in bad else "")
                w.setToolTip(bad.get(w, self._tips[w]))

    # ----------------------------------------------------------------------------------
    # start, stop, live controls
    # ----------------------------------------------------------------------------------
    def start(self):
        """Ready --start--> Simulation: the worker builds (or loads) the world and runs it."""
        if self.state is not V.State.READY or self.config is None:
            return
        import copy

        cfg = copy.deepcopy(self.config)
        cfg.gui = self.chk_gui.isChecked() and self.chk_gui.isEnabled()
        cfg.realtime = self.chk_realtime.isChecked()
        self.machine.fire("start")
        self.last_frame = None
        self.last_summary = ""
        self.last_goal = None
        self._running = False
        self._warning = ""
        self.map.clear()
        self.camera.clear()
        for lab in self.live.values():
            lab.setText("—")
        self.progress.setValue(0)
        self.progress.setFormat("starting…")
        self.progress.setVisible(True)
        self.worker.camera_on = True
        self.worker.arm()
        self._to_start.emit(cfg)
        self.map.setFocus()
        # on a short screen the inputs scroll: show the live values (the inputs are locked now)
        QTimer.singleShot(0, lambda: self.inputs_scroll.ensureWidgetVisible(self.live_box, 0, 0))

    def stop(self):
        """Simulation --stop--> Stop: the worker ends the run and tears SUMO and PyBullet down."""
        if self.state is V.State.SIMULATION:
            self.machine.fire("stop")
            self.worker.request_stop()
            self._status("stopping: shutting SUMO and PyBullet down…")
        elif self.state is V.State.STOPPING:
            self.worker.request_stop()

    def _speed_changed(self, *_):
        if self.state is V.State.SIMULATION:
            self._speed_timer.start()          # live: sent once the user pauses typing
        else:
            self._inputs_changed()

    def _send_speed(self):
        if self.state is not V.State.SIMULATION:
            return
        errs: list = []
        v = V._number(self.ed_speed.text(), "speed", errs, 0.0, MAX_SPEED_MPS, "m/s")
        self._mark(errs)
        if errs:
            self._show_message(errs[0].text(), error=True)
            return
        self._show_message("")
        self._to_speed.emit(float(v))

    def _send_goal(self):
        if self.state is not V.State.SIMULATION or not self._running:
            return
        v = self.values()
        if not v.dest_lat.strip() and not v.dest_lon.strip():
            self._to_goal.emit(None)
            return
        errs: list = []
        goal = V._latlon(v.dest_lat, v.dest_lon, "dest_lat", "dest_lon", errs, "destination")
        self._mark(errs)
        if errs:
            self._show_message(errs[0].text(), error=True)
            return
        self._show_message("routing…")
        self._to_goal.emit(goal)

    # ----------------------------------------------------------------------------------
    # from the worker
    # ----------------------------------------------------------------------------------
    def _on_progress(self, stage, frac, msg, overall):
        if overall >= 0:
            self.progress.setValue(int(overall * 1000))
        self.progress.setFormat(f"{stage}: {msg}"[:70] if msg else stage)
        where = f"building the world — {stage}: {msg}" if stage not in ("traffic", "sumo", "physics", "run") \
            else f"{stage}: {msg}"
        if self.state is V.State.SIMULATION:
            self._status(where)

    def _on_started(self, info):
        self._running = True
        self.progress.setVisible(False)
        self.map.set_world(info)
        self._update_route_label(info.get("snap", {}))
        self._apply_enabled()
        self.map.setFocus()

    def _on_frame(self, f):
        if self.state not in (V.State.SIMULATION, V.State.STOPPING):
            return
        self.last_frame = f
        e = f["ego"]
        self.live["lat"].setText(f"{e['lat']:.6f}°")
        self.live["lon"].setText(f"{e['lon']:.6f}°")
        self.live["speed"].setText(f"{e['speed']:.1f} m/s ({e['speed'] * 3.6:.0f} km/h), set {f['speed_mps']:.1f}")
        self.live["t"].setText(f"{f['t']:.1f} s")
        th, br, st = f["control"]
        self.live["mode"].setText("manual (keys)" if f["manual"] else "automatic")
        self.live["control"].setText(f"throttle {th:.0%} · brake {br:.0%}")
        self.live["steer"].setText("straight" if abs(st) < 0.005 else f"{abs(st):.0%} {'left' if st > 0 else 'right'}")
        if f.get("arrived"):
            self.live["route"].setText("arrived at the destination")
        elif f.get("route_left") is not None:
            m, eta = f["route_left"]
            self._update_route_label({"route_length_m": m, "eta_s": eta})
        self.map.set_frame(f)
        if "camera" in f:
            self.camera.set_image(f["camera"])
        parts = [f"chunk {f['chunk'][0]},{f['chunk'][1]}", f"{f['tiles_loaded']} tiles loaded",
                 f"x{f['rtf']:.1f} real time"]
        if f.get("tiles_new"):
            k = f["tiles_new"][0]
            parts.append(f"loaded tile {k[2]},{k[3]} of chunk {k[0]},{k[1]}"
                         + (f" (+{len(f['tiles_new']) - 1})" if len(f["tiles_new"]) > 1 else ""))
        if f.get("building") is not None:
            b = f["building"]
            parts.append(f"building the chunks around {b[0]},{b[1]} in the background")
        if f.get("warning"):
            self._on_warning(f["warning"])
        if self._warning and time.monotonic() < self._warning_until:
            parts.append("warning: " + self._warning)
        self._status(" · ".join(parts))

    WARNING_S = 8.0             # a warning stays on the status line this long

    def _on_warning(self, msg):
        self._warning, self._warning_until = msg, time.monotonic() + self.WARNING_S
        if self.last_frame is None and self.state is V.State.SIMULATION:     # still starting up
            self._status(self.status_label.text().split(" · warning: ")[0] + " · warning: " + msg)

    def _on_goal(self, info):
        self.last_goal = info
        if "error" in info:
            self._mark([V.FieldError("dest", info["error"])])      # (outlined, as before a run)
            self._show_message("Destination: " + info["error"], error=True)
            return
        self._mark([])
        self._show_message("")
        self.map.set_route(info.get("route"), info.get("goal_xy"))
        self._update_route_label(info)

    def _on_speed(self, info):
        if "error" in info:
            self._show_message("Speed: " + info["error"], error=True)

    def _update_route_label(self, info):
        if info.get("route_length_m") is not None:
            self.live["route"].setText(f"{info['route_length_m']:.0f} m to the destination, "
                                       f"ETA {info.get('eta_s') or 0:.0f} s")
        else:
            self.live["route"].setText("no destination: driving on at random")

    def _on_stopped(self, line):
        """Stop --stopped--> Idle; the inputs are then checked again."""
        self.last_summary = line
        self._running = False
        self.progress.setVisible(False)
        if self.machine.can("stopped"):
            self.machine.fire("stopped")
        self._status("stopped. " + line)
        if self._close_pending:
            QTimer.singleShot(0, self.close)
        else:
            QTimer.singleShot(0, self._inputs_changed)

    def _on_failed(self, msg):
        """Simulation --failed--> Error (the worker has torn everything down)."""
        self._running = False
        self.progress.setVisible(False)
        if self.machine.can("failed"):
            self.machine.fire("failed", msg)
        self._status("error: " + msg)
        if self._close_pending:
            QTimer.singleShot(0, self.close)

    # ----------------------------------------------------------------------------------
    # state -> widgets
    # ----------------------------------------------------------------------------------
    def _on_state(self, old, new, message):
        self._apply_enabled()
        if new is V.State.ERROR:
            self._show_message(message, error=True)
        elif new is V.State.CHECKING:
            pass                         # keep the last message until the check answers
        else:
            self._show_message(message)
        self.state_changed.emit(old.value, new.value, message)

    def _show_message(self, text, error=False):
        self.lbl_msg.setText(text)
        self.lbl_msg.setStyleSheet("color: #c0261f; font-weight: bold;" if error else "color: #333;")

    def _status(self, text):
        self.status_label.setText(text)

    def _apply_enabled(self):
        if not self._init_done:
            return
        st = self.state
        editing = st in (V.State.IDLE, V.State.CHECKING, V.State.ERROR, V.State.READY)
        live = st is V.State.SIMULATION
        coords = self.rb_coords.isChecked()
        for w in (self.rb_preset, self.rb_coords, self.ed_chunks, self.cb_quality, self.cb_traffic,
                  self.ed_dem, self.b_dem, self.chk_flat, self.chk_realtime):
            w.setEnabled(editing)
        self.cb_preset.setEnabled(editing and not coords)
        for w in (self.ed_lat, self.ed_lon, self.ed_osm, self.b_osm):
            w.setEnabled(editing and coords)
        self.chk_gui.setEnabled(editing and self._no_display is None)
        for w in (self.ed_speed, self.ed_dest_lat, self.ed_dest_lon):
            w.setEnabled(editing or live)
        self.btn_goal.setEnabled(live and self._running)
        self.btn_start.setEnabled(st is V.State.READY)
        self.btn_stop.setEnabled(live)

    # ----------------------------------------------------------------------------------
    # keyboard driving
    # ----------------------------------------------------------------------------------
    def eventFilter(self, obj, ev):
        t = ev.type()
        if t in (QEvent.KeyPress, QEvent.KeyRelease) and isinstance(obj, QWidget) and obj.window() is self:
            focus = QApplication.focusWidget()
            typing = isinstance(focus, (QLineEdit, QAbstractSpinBox)) or (
                isinstance(focus, QComboBox) and focus.isEditable())
            if typing and t == QEvent.KeyPress and ev.key() == Qt.Key_Escape:
                self.map.setFocus()
                return True
            if not typing and self.state is V.State.SIMULATION and self._running and ev.key() in KEYS:
                if not ev.isAutoRepeat():
                    (self._to_key_press if t == QEvent.KeyPress else self._to_key_release).emit(KEYS[ev.key()])
                return True
        return super().eventFilter(obj, ev)

    # ----------------------------------------------------------------------------------
    # closing: never leave SUMO, PyBullet or a build behind
    # ----------------------------------------------------------------------------------
    def closeEvent(self, ev):
        if self._closed:
            ev.accept()
            return
        if self.state in (V.State.SIMULATION, V.State.STOPPING):
            # the worker stops the build or the run and tears down; then the window closes
            self._close_pending = True
            self.stop()
            self._status("closing: stopping the simulation first…")
            ev.ignore()
            return
        self._shutdown_threads()
        ev.accept()

    def _shutdown_threads(self, timeout_ms: int = 120_000):
        if self._closed:
            return
        self._closed = True
        self._debounce.stop()
        self._speed_timer.stop()
        app = QApplication.instance()
        if app is not None:
            app.removeEventFilter(self)
        # a last resort when the window is destroyed without a close (the app quitting):
        # stop the worker and wait for its teardown before its thread ends
        self.worker.request_stop()
        self.worker.idle.wait(timeout_ms / 1000.0)
        for th in (self.sim_thread, self.check_thread):
            th.quit()
            th.wait(timeout_ms)

    def shutdown(self, timeout_ms: int = 120_000):
        """Blocking: stop any run, tear down, end the worker threads (scripts and tests)."""
        if self.state is V.State.SIMULATION:
            self.stop()
        self._shutdown_threads(timeout_ms)


#: Debian / Ubuntu packages of the X11 libraries Qt's xcb platform plugin needs beyond PyQt5's wheel
XCB_PACKAGES = ("libxcb-icccm4 libxcb-keysyms1 libxcb-xinerama0 libxcb-image0 libxcb-render-util0 "
                "libxcb-randr0 libxcb-shape0 libxkbcommon-x11-0")


def xcb_problem() -> str | None:
    """Why Qt's X11 platform plugin (``libqxcb.so``, PyQt5's wheel) cannot load here, in a
    line, or None. Loaded without a system library it needs (``libxcb-icccm.so.4`` and others,
    not on a minimal system), Qt aborts the process with several lines about reinstalling
    the application; the plugin is loaded here first (the dynamic loader names what is
    missing)."""
    import ctypes

    from PyQt5.QtCore import QLibraryInfo

    plugin = Path(QLibraryInfo.location(QLibraryInfo.PluginsPath)) / "platforms" / "libqxcb.so"
    if not plugin.exists():
        return None                     # (Qt lists the platforms it has)
    try:
        ctypes.CDLL(str(plugin))
    except OSError as e:
        first = str(e).split(":")[0].strip()        # ("libxcb-icccm.so.4: cannot open shared object file")
        what = first if ".so" in first else str(e)
        return (f"Qt's X11 platform plugin cannot load: {what} is missing (on Debian or Ubuntu: "
                f"apt install {XCB_PACKAGES})")
    return None


def launch(preset: str | None = None, worlds: str | None = None, realtime: bool = True) -> int:
    """Open the launcher; returns the Qt event loop's exit status. Qt's default platform on
    Linux (xcb) aborts the process without an X server, or without the X11 libraries its
    plugin needs: each is a one-line SimulationError here, unless QT_QPA_PLATFORM names
    another platform (``offscreen`` for screenshots)."""
    platform = os.environ.get("QT_QPA_PLATFORM", "")
    if not QApplication.instance() and platform in ("", "xcb") and sys.platform.startswith("linux"):
        why = display_problem()
        if why:
            raise SimulationError(f"the launcher needs a display: {why} (QT_QPA_PLATFORM=offscreen runs it "
                                  "without one)")
        why = xcb_problem()
        if why:
            raise SimulationError(why)
    app = QApplication.instance() or QApplication(sys.argv[:1])
    w = MainWindow(out_root=worlds, realtime=realtime, preset=preset)
    app.aboutToQuit.connect(w._shutdown_threads)
    w.show()
    return int(app.exec_())


def main(argv=None) -> int:
    """``python -m ui.app``: the same as ``cosim gui``."""
    from cosim.cli import add_gui_args

    p = argparse.ArgumentParser(prog="cosim gui", description="Desktop launcher with a live view of the simulation.")
    add_gui_args(p)
    a = p.parse_args(argv)
    try:
        return launch(preset=a.preset, worlds=a.worlds, realtime=not a.no_realtime)
    except CosimError as e:
        print(f"error: {e}", file=sys.stderr)
        return e.exit_code


if __name__ == "__main__":
    sys.exit(main())
