"""The PyQt5 launcher (ui/): its states and transitions, the checks of every input, and a real
run (world build or reuse, SUMO, PyBullet) driven through the window on Qt's offscreen
platform, with live speed, destination and keyboard control, Stop, and closing the window
during a build and during a run.

Nothing is mocked: the window, its worker threads, SUMO (libsumo) and PyBullet are real.
One kouvola world (1 ring of chunks, low quality) is built once per session and reused.
"""
from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PyQt5.QtCore import Qt
from PyQt5.QtGui import QColor

from cosim.config import MAX_SPEED_MPS
from netgen.config import MAX_RINGS, WorldConfig
from ui import validation as V

REPO = Path(__file__).resolve().parents[1]
S = V.State
# A point inside the kouvola extract, in a field ~210 m from any road for cars (by the OSM
# ways; test_reality_checks confirms it against the SUMO network of the built world)
OFFROAD = (60.52323, 26.95479)
KOUVOLA = (60.5300, 26.9450)


# --------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def worlds(tmp_path_factory):
    """A folder of built worlds holding the kouvola world the launcher's defaults ask for
    (so Start reuses it instead of building)."""
    from netgen.build import build_world

    root = tmp_path_factory.mktemp("gui-worlds")
    cache = tmp_path_factory.getbasetemp() / "cosim-cache"      # the cache conftest points COSIM_CACHE at
    wc = WorldConfig(preset="kouvola", chunks=1, quality="low", cache_dir=str(cache))
    wc.out = str(V.world_out_dir(wc, root))
    build_world(wc)
    return root


@pytest.fixture(scope="session")
def kouvola_world(worlds):
    from cosim.world import World

    return World(V.world_out_dir(WorldConfig(preset="kouvola", chunks=1, quality="low"), worlds))


def make_window(qtbot, out_root, **kw):
    from ui.app import MainWindow

    w = MainWindow(out_root=out_root, realtime=False, preset="kouvola", **kw)
    qtbot.addWidget(w)
    w.show()
    return w


@pytest.fixture
def win(qtbot, worlds):
    w = make_window(qtbot, worlds)
    yield w
    w.shutdown()            # blocking: stops a run, tears down, ends the worker threads
    w.close()


def wait_state(qtbot, w, state, timeout=10_000):
    qtbot.waitUntil(lambda: w.state is state, timeout=timeout)


def set_text(w, edit, text):
    edit.setText(text)


def libsumo_running() -> bool:
    import libsumo

    import cosim.traffic as tr
    from cosim.sumo_process import live_workers

    return tr._LIBSUMO_OWNER is not None or libsumo.simulation.isLoaded() or bool(live_workers())


def pybullet_connected(client) -> bool:
    import pybullet as pb

    return bool(pb.getConnectionInfo(physicsClientId=client)["isConnected"])


def child_processes():
    import psutil

    return [p for p in psutil.Process().children(recursive=True) if p.is_running()
            and p.status() != psutil.STATUS_ZOMBIE]


# --------------------------------------------------------------------------------------
# the state machine and the checks, without a window
# --------------------------------------------------------------------------------------
def test_state_machine_every_transition_and_no_other():
    events = sorted({e for _, e in V.TRANSITIONS})
    for (src, ev), dst in V.TRANSITIONS.items():
        m = V.StateMachine()
        m.state = src
        seen = []
        m.subscribe(lambda o, n, msg: seen.append((o, n, msg)))
        assert m.fire(ev, "why") is dst
        assert seen == [(src, dst, m.message)]
    for st in S:
        for ev in events:
            if (st, ev) not in V.TRANSITIONS:
                m = V.StateMachine()
                m.state = st
                with pytest.raises(V.InvalidTransition):
                    m.fire(ev)
                assert m.state is st
    # the seed's path, with what each state says
    m = V.StateMachine()
    assert m.state is S.IDLE
    m.fire("edit")
    m.fire("invalid", "Latitude: 95° is out of range (-90..90°)")
    assert (m.state, m.message) == (S.ERROR, "Latitude: 95° is out of range (-90..90°)")
    m.fire("edit")
    assert m.state is S.CHECKING and m.message.startswith("Latitude")   # kept until the check answers
    m.fire("valid")
    assert (m.state, m.message) == (S.READY, "")
    assert not m.can("stop") and m.can("start")
    m.fire("start")
    m.fire("stop")
    m.fire("stopped")
    assert m.state is S.IDLE
    assert [e for _, e, _ in m.history] == ["edit", "invalid", "edit", "valid", "start", "stop", "stopped"]


@pytest.mark.parametrize("changes, field, text", [
    ({"mode": "coords", "lat": "95", "lon": "26.9"}, "lat", "95° is out of range (-90..90°)"),
    ({"mode": "coords", "lat": "-90.5", "lon": "26.9"}, "lat", "out of range (-90..90°)"),
    ({"mode": "coords", "lat": "60.5", "lon": "-181"}, "lon", "-181° is out of range (-180..180°)"),
    ({"mode": "coords", "lat": "60.5", "lon": "east"}, "lon", "'east' is not a number"),
    ({"mode": "coords", "lat": "", "lon": "26.9"}, "lat", "is empty"),
    ({"mode": "coords", "lat": "86", "lon": "26.9"}, "lat", "too close to a pole"),
    ({"chunks": str(MAX_RINGS + 1)}, "chunks", f"out of range (0..{MAX_RINGS})"),
    ({"chunks": "-1"}, "chunks", "out of range"),
    ({"chunks": "1.5"}, "chunks", "not a whole number"),
    ({"speed": str(MAX_SPEED_MPS + 1)}, "speed", f"out of range (0..{MAX_SPEED_MPS:g} m/s)"),
    ({"speed": "-3"}, "speed", "out of range"),
    ({"traffic": "lots"}, "traffic", "neither one of none, light, normal, dense"),
    ({"traffic": "2500"}, "traffic", "out of range (0..2000 vehicles/km²)"),
    ({"dest_lat": "60.53"}, "dest_lon", "is empty"),
    ({"dest_lat": "60.53", "dest_lon": "200"}, "dest_lon", "out of range"),
    ({"mode": "coords", "lat": "60.5", "lon": "26.9", "osm": "/nonexistent/x.osm.pbf"}, "osm", "does not exist"),
    ({"dem": __file__}, "dem", "unknown format"),
])
def test_range_checks_name_the_field_and_why(changes, field, text):
    v = V.FormValues(**changes)
    _, errors = V.check_ranges(v)
    assert [e.field for e in errors] == [field], errors
    assert text in errors[0].message
    assert errors[0].text().startswith(V.LABELS[field] + ": ")


def test_range_checks_accept_the_defaults_and_edges():
    for changes in ({}, {"chunks": "0"}, {"chunks": str(MAX_RINGS)}, {"speed": "0"}, {"speed": str(MAX_SPEED_MPS)},
                    {"traffic": "dense"}, {"traffic": "150"}, {"mode": "coords", "lat": "-84", "lon": "180"}):
        r, errors = V.check_ranges(V.FormValues(**changes))
        assert errors == [], (changes, errors)
    r, _ = V.check_ranges(V.FormValues(traffic="150", speed="12.5"))
    assert (r.traffic, r.speed) == (150.0, 12.5)


def write_hgt(path: Path, value: int = 100):
    np.full((1201, 1201), value, dtype=">i2").tofile(path)


def test_reality_checks(tmp_path, kouvola_world):
    # the preset's centre: fine
    res = V.check_all(V.FormValues(preset="kouvola"), tmp_path)
    assert res.ok, res.message()
    assert res.config.world.preset == "kouvola" and res.config.start is None
    assert res.config.render and res.config.world.out.startswith(str(tmp_path))

    # a start in a field: no road for cars near it; the SUMO network agrees it is far from any lane
    res = V.check_all(V.FormValues(mode="coords", lat=str(OFFROAD[0]), lon=str(OFFROAD[1])), tmp_path)
    assert not res.ok and res.errors[0].field == "lat"
    assert "no road for cars within 50 m" in res.errors[0].message
    x, y = (float(a) for a in kouvola_world.frame.to_xy(OFFROAD[1], OFFROAD[0]))
    lanes = np.vstack(kouvola_world.map_layers()["roads"])
    assert np.hypot(lanes[:, 0] - x, lanes[:, 1] - y).min() > 150.0

    # a start on a road in the kouvola extract: the preset's data, centred on the start
    res = V.check_all(V.FormValues(mode="coords", lat="60.5300", lon="26.9450"), tmp_path)
    assert res.ok, res.message()
    assert res.config.world.preset == "kouvola" and res.config.world.center == (60.53, 26.945)
    assert res.config.start == (60.53, 26.945)

    # outside the map data of a given OSM file
    osm = REPO / "netgen" / "presets" / "kouvola.osm.pbf"
    res = V.check_all(V.FormValues(mode="coords", lat="60.60", lon="26.945", osm=str(osm)), tmp_path)
    assert not res.ok and "outside the map data of kouvola.osm.pbf" in res.errors[0].message

    # somewhere without a preset or a DEM: elevation is needed (or flat ground, then Overpass)
    res = V.check_all(V.FormValues(mode="coords", lat="48.137", lon="11.575"), tmp_path)
    assert [e.field for e in res.errors] == ["dem"] and "choose a DEM file" in res.errors[0].message
    res = V.check_all(V.FormValues(mode="coords", lat="48.137", lon="11.575", flat=True), tmp_path)
    assert res.ok and res.config.world.flat and res.config.world.preset is None
    assert any("Overpass" in n for n in res.notes)

    # a DEM that does not cover the world
    dem = tmp_path / "N10E010.hgt"
    write_hgt(dem)
    res = V.check_all(V.FormValues(preset="kouvola", dem=str(dem)), tmp_path)
    assert [e.field for e in res.errors] == ["dem"] and "does not cover the area" in res.errors[0].message

    # destinations: beyond the world, then inside the world but beyond the map data, then off-road
    far = V.FormValues(preset="kouvola", dest_lat="60.5460", dest_lon="26.9450")      # 1.8 km north
    res = V.check_all(far, tmp_path)
    assert res.errors[0].field == "dest" and "outside the world to be built" in res.errors[0].message
    assert "raise Chunks" in res.errors[0].message
    far.chunks = "2"
    res = V.check_all(far, tmp_path)
    assert res.errors[0].field == "dest" and "outside the map data" in res.errors[0].message
    res = V.check_all(V.FormValues(preset="kouvola", dest_lat=str(OFFROAD[0]), dest_lon=str(OFFROAD[1])), tmp_path)
    assert res.errors[0].field == "dest" and "no road for cars" in res.errors[0].message
    res = V.check_all(V.FormValues(preset="kouvola", dest_lat="60.5331", dest_lon="26.9471"), tmp_path)
    assert res.ok and res.config.goal == (60.5331, 26.9471)


# --------------------------------------------------------------------------------------
# the map widget on its own
# --------------------------------------------------------------------------------------
def test_map_draws_roads_route_actors_ego_and_tiles(qtbot):
    from ui.mapview import COL, MapView

    m = MapView()
    qtbot.addWidget(m)
    m.resize(400, 300)
    m.scale = 1.0
    layers = {"roads": [np.array([[-500.0, 0.0], [500.0, 0.0]])], "paths": [],
              "buildings": [np.array([[40.0, 40.0], [80.0, 40.0], [80.0, 80.0], [40.0, 80.0]])]}
    m.set_world({"layers": layers, "chunks": {(0, 0): (-500, -500, 500, 500)},
                 "route": np.array([[0.0, 0.0], [0.0, -120.0]]), "goal_xy": (0.0, -120.0)})
    m.set_frame({"ego": {"x": 0.0, "y": 0.0, "yaw": 0.0},
                 "actors": {"kind": ["passenger", "person"], "x": [-60.0, -60.0], "y": [0.0, 40.0],
                            "yaw": [0.0, 0.0], "length": [4.5, 0.5], "width": [1.8, 0.5]},
                 "tiles": {(0, 0, 2, 2): (-125.0, -125.0, 125.0, 125.0)}})
    img = m.grab().toImage()
    cx, cy = 200, 150

    def near(px, py, colour, tol=40, r=2):
        for dx in range(-r, r + 1):
            for dy in range(-r, r + 1):
                c = QColor(img.pixel(px + dx, py + dy))
                if all(abs(a - b) <= tol for a, b in zip(c.getRgb()[:3], colour.getRgb()[:3])):
                    return True
        return False

    assert near(cx, cy, COL["ego"])                       # the ego at the centre
    assert near(cx - 150, cy, COL["road"])                # the road runs east-west through it
    assert near(cx, cy + 60, COL["route"])                # the route goes south (screen: down)
    assert near(cx, cy + 120, COL["goal"], r=3)           # to the destination
    assert near(cx - 60, cy, COL["vehicle"])              # a car on the road
    assert near(cx - 60, cy - 40, COL["person"], r=2)     # a person north of it
    assert near(cx + 60, cy - 60, COL["building"], tol=12)
    tile = QColor(img.pixel(cx + 100, cy + 100))
    outside = QColor(img.pixel(cx + 170, cy + 140))
    assert tile.rgb() != outside.rgb()                    # the loaded tile is tinted


# --------------------------------------------------------------------------------------
# the window: Idle -> Input checked -> Error / Ready
# --------------------------------------------------------------------------------------
def test_idle_with_defaults_then_ready(qtbot, worlds):
    from ui.app import MainWindow

    win = MainWindow(out_root=worlds, realtime=False, preset="kouvola")
    qtbot.addWidget(win)
    try:
        # the window fits a laptop's 1366 x 768 screen: the inputs scroll (it needed 939 px)
        hint = win.minimumSizeHint()
        assert hint.height() <= 700 and hint.width() <= 1000, (hint.width(), hint.height())
        _idle_then_ready(win, qtbot)
    finally:
        win.shutdown()
        win.close()


def _idle_then_ready(win, qtbot):
    assert win.state is S.IDLE                            # before the event loop has run
    assert win.lbl_msg.text() == "" and win.machine.history == []
    assert (win.cb_preset.currentData(), win.ed_chunks.text(), win.ed_speed.text(),
            win.cb_quality.currentText(), win.cb_traffic.currentText()) == ("kouvola", "1", "10", "low", "normal")
    assert not win.btn_start.isEnabled() and not win.btn_stop.isEnabled()
    states = []
    win.state_changed.connect(lambda a, b, msg: states.append(b))
    wait_state(qtbot, win, S.READY)
    assert states == ["Input checked", "Ready"]
    assert win.btn_start.isEnabled() and not win.btn_stop.isEnabled()
    assert win.lbl_msg.text() == ""
    cfg = win.config
    assert (cfg.world.preset, cfg.world.chunks, cfg.world.quality, cfg.speed_mps, cfg.traffic) == \
        ("kouvola", 1, "low", 10.0, "normal")


def test_each_wrong_input_is_an_error_that_says_which_and_why(win, qtbot):
    wait_state(qtbot, win, S.READY)
    win.rb_coords.setChecked(True)                        # fills in the preset's centre
    wait_state(qtbot, win, S.READY)
    assert win.ed_lat.isEnabled() and not win.cb_preset.isEnabled()
    assert abs(float(win.ed_lat.text()) - KOUVOLA[0]) < 1e-4

    cases = [(win.ed_lat, "95", "Latitude: 95° is out of range (-90..90°)"),
             (win.ed_lon, "-190", "Longitude: -190° is out of range (-180..180°)"),
             (win.ed_chunks, "9", f"Chunks: 9 is out of range (0..{MAX_RINGS})"),
             (win.ed_speed, "55", f"Speed: 55 m/s is out of range (0..{MAX_SPEED_MPS:g} m/s)"),
             (win.ed_dest_lat, "x", "Destination latitude: 'x' is not a number")]
    for edit, bad, msg in cases:
        good = edit.text()
        edit.clear()
        qtbot.keyClicks(edit, bad)                         # typed: each keystroke is checked
        assert win.state is S.ERROR                        # range errors show at once
        assert win.lbl_msg.text().split("\n")[0] == msg   # (an empty partner field is named too)
        assert not win.btn_start.isEnabled()
        assert "d0302a" in edit.styleSheet() and edit.toolTip() == msg
        set_text(win, edit, good)                          # Error --edit--> Input checked --valid--> Ready
        assert win.state is S.CHECKING
        wait_state(qtbot, win, S.READY)
        assert win.lbl_msg.text() == "" and edit.styleSheet() == ""
        assert win.btn_start.isEnabled()

    # against reality (in the check worker): a start with no road near it
    win.ed_lat.setText(str(OFFROAD[0]))
    win.ed_lon.setText(str(OFFROAD[1]))
    assert win.state is S.CHECKING
    wait_state(qtbot, win, S.ERROR)
    assert win.lbl_msg.text().startswith("Latitude: no road for cars within 50 m of 60.52323, 26.95479")
    assert not win.btn_start.isEnabled()
    # a destination outside the world to be built
    win.ed_lat.setText(str(KOUVOLA[0]))
    win.ed_lon.setText(str(KOUVOLA[1]))
    win.ed_dest_lat.setText("60.5460")
    win.ed_dest_lon.setText("26.9450")
    wait_state(qtbot, win, S.ERROR)
    assert "Destination: 60.54600, 26.94500 is outside the world to be built" in win.lbl_msg.text()
    win.ed_dest_lat.clear()
    win.ed_dest_lon.clear()
    wait_state(qtbot, win, S.READY)
    # an answer to inputs that have changed since is dropped
    win._on_checked(win._gen - 1, V.CheckResult(errors=[V.FieldError("lat", "stale")]))
    assert win.state is S.READY


def test_display_check_asks_the_x_server(tmp_path):
    """A display is there when an X server takes a connection at $DISPLAY: a Unix socket
    ``X<n>`` for ``:n``, TCP port 6000 + n for ``host:n`` (real sockets here)."""
    import socket

    from cosim.display import display_problem
    from ui.app import has_display

    if not sys.platform.startswith("linux"):
        assert display_problem({}) is None
        return
    assert display_problem({}) == "there is no display (DISPLAY is not set)" and not has_display({})
    assert "not a display name" in display_problem({"DISPLAY": "nonsense"})
    x11 = tmp_path / "x11"
    x11.mkdir()
    unix = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    unix.bind(str(x11 / "X7"))
    unix.listen(1)
    try:
        assert display_problem({"DISPLAY": ":7"}, x11_dir=str(x11)) is None
        assert display_problem({"DISPLAY": ":7.0"}, x11_dir=str(x11)) is None
        assert display_problem({"DISPLAY": ":8"}, x11_dir=str(x11)) == "no X server answers at DISPLAY=:8"
    finally:
        unix.close()
    assert display_problem({"DISPLAY": ":7"}, x11_dir=str(x11)) == "no X server answers at DISPLAY=:7"
    tcp = socket.socket()
    for n in range(50, 400):                 # a free port 6000 + n on the loopback
        try:
            tcp.bind(("127.0.0.1", 6000 + n))
            break
        except OSError:
            continue
    tcp.listen(1)
    try:
        assert display_problem({"DISPLAY": f"127.0.0.1:{n}.0"}) is None
    finally:
        tcp.close()
    assert display_problem({"DISPLAY": f"127.0.0.1:{n}"}) == f"no X server answers at DISPLAY=127.0.0.1:{n}"


def test_cosim_gui_without_a_display_is_a_clear_error(tmp_path):
    """``cosim gui`` (its options passed on) where no X server answers and Qt would use its
    default platform: a one-line error naming the way out, not Qt's abort (exit code 134)."""
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "QT_QPA_PLATFORM")}
    r = subprocess.run([sys.executable, "-m", "cosim", "gui", "--preset", "kouvola", "--no-realtime"],
                       capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert lines[0] == ("error: the launcher needs a display: there is no display (DISPLAY is not set) "
                        "(QT_QPA_PLATFORM=offscreen runs it without one)")


def test_qt_x11_plugin_without_its_libraries_is_a_clear_error(tmp_path):
    """Qt's X11 platform plugin, loaded without a system library it needs (``libxcb-icccm``
    and others are not on a minimal system), aborts the process with Qt's lines about
    reinstalling the application. ``xcb_problem`` agrees with the dynamic loader (``ldd``),
    and ``cosim gui`` with an X server answering says in one line what is missing."""
    import socket

    from PyQt5.QtCore import QLibraryInfo

    from ui.app import XCB_PACKAGES, xcb_problem

    plugin = Path(QLibraryInfo.location(QLibraryInfo.PluginsPath)) / "platforms" / "libqxcb.so"
    assert plugin.exists()
    ldd = subprocess.run(["ldd", str(plugin)], capture_output=True, text=True, timeout=60).stdout
    missing = {ln.split()[0] for ln in ldd.splitlines() if "not found" in ln}
    why = xcb_problem()
    if not missing:
        assert why is None
        return
    assert why is not None and "\n" not in why and XCB_PACKAGES in why
    assert any(f"{lib} is missing" in why for lib in missing), why
    # an X server's socket that takes connections (a display here), then the launcher
    x11 = Path("/tmp/.X11-unix")
    x11.mkdir(exist_ok=True)
    n = next(k for k in range(90, 200) if not (x11 / f"X{k}").exists())
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(str(x11 / f"X{n}"))
    srv.listen(8)
    try:
        env = {k: v for k, v in os.environ.items() if k != "QT_QPA_PLATFORM"}
        env["DISPLAY"] = f":{n}"
        r = subprocess.run([sys.executable, "-m", "cosim", "gui", "--preset", "kouvola", "--no-realtime"],
                           capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    finally:
        srv.close()
        (x11 / f"X{n}").unlink()
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr[-2000:]
    assert lines[0] == f"error: {why}"


def test_pybullet_window_checkbox_needs_a_display(qtbot, worlds, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    w = make_window(qtbot, worlds)
    try:
        wait_state(qtbot, w, S.READY)
        assert not w.chk_gui.isEnabled()
        assert "no display" in w.chk_gui.toolTip()
        assert w.values().gui is False
    finally:
        w.shutdown()
        w.close()


# --------------------------------------------------------------------------------------
# the window: Ready -> Simulation -> Stop -> Idle, with everything live
# --------------------------------------------------------------------------------------
def road_point(world, lo: float, hi: float):
    """lat, lon of the middle of a lane for cars lo..hi m from the world's centre."""
    for lane in world.map_layers()["roads"]:
        x, y = lane[len(lane) // 2]
        if lo < math.hypot(x, y) < hi:
            lon, lat = world.frame.to_lonlat(x, y)
            return float(lat), float(lon), (float(x), float(y))
    raise AssertionError("no lane found")


def test_run_with_live_controls_then_stop(win, qtbot, kouvola_world):
    win.cb_traffic.setCurrentText("light")
    wait_state(qtbot, win, S.READY)
    progress = []
    win.worker.progress.connect(lambda st, f, msg, o: progress.append((st, o)))
    states = []
    win.state_changed.connect(lambda a, b, msg: states.append(b))
    qtbot.mouseClick(win.btn_start, Qt.LeftButton)
    assert win.state is S.SIMULATION
    assert win.progress.isVisible() and not win.btn_start.isEnabled() and win.btn_stop.isEnabled()
    assert not win.ed_chunks.isEnabled() and win.ed_speed.isEnabled()
    qtbot.waitUntil(lambda: win.last_frame is not None and win.camera.image is not None, timeout=120_000)
    stages = [s for s, _ in progress]
    assert stages[0] == "build" and "done" in stages and stages.index("sumo") < stages.index("run")
    overall = [o for _, o in progress if o >= 0]
    assert overall == sorted(overall)                     # one bar that only moves forward
    assert not win.progress.isVisible()
    client = win.worker.sim.physics.client

    # live location, velocity, map, camera, status line
    qtbot.waitUntil(lambda: win.last_frame["t"] > 3.0, timeout=30_000)
    f = win.last_frame
    lat, lon = float(win.live["lat"].text().rstrip("°")), float(win.live["lon"].text().rstrip("°"))
    assert abs(lat - KOUVOLA[0]) < 0.01 and abs(lon - KOUVOLA[1]) < 0.02
    assert "m/s" in win.live["speed"].text() and f["ego"]["speed"] > 1.0
    assert win.map.roads.elementCount() > 500 and win.map.ego is not None
    assert len(win.map.chunks) == 9 and len(win.map.tiles) == f["tiles_loaded"] > 0
    assert win.map.route is not None
    cam = win.camera.image
    arr = np.frombuffer(cam.constBits().asstring(cam.byteCount()), np.uint8)
    assert cam.width() == 480 and arr.std() > 20           # a picture, not a blank
    status = win.status_label.text()
    assert "chunk 0,0" in status and "tiles loaded" in status and "real time" in status
    shot = win.grab()
    assert shot.width() >= 1000 and not shot.toImage().isNull()

    # speed changed while driving; a wrong one is refused and the run goes on
    win.ed_speed.setText("5")
    qtbot.waitUntil(lambda: win.last_frame["speed_mps"] == 5.0, timeout=10_000)
    win.ed_speed.setText("99")
    qtbot.waitUntil(lambda: win.lbl_msg.text().startswith("Speed: 99 m/s is out of range"), timeout=5_000)
    assert win.state is S.SIMULATION
    t = win.last_frame["t"]
    qtbot.waitUntil(lambda: win.last_frame["t"] > t + 1.0, timeout=10_000)
    assert win.last_frame["speed_mps"] == 5.0
    win.ed_speed.setText("8")
    qtbot.waitUntil(lambda: win.last_frame["speed_mps"] == 8.0, timeout=10_000)
    assert win.lbl_msg.text() == ""

    # a destination set while driving: routed from where the car is
    glat, glon, gxy = road_point(kouvola_world, 300.0, 500.0)
    win.ed_dest_lat.setText(f"{glat:.6f}")
    win.ed_dest_lon.setText(f"{glon:.6f}")
    assert win.state is S.SIMULATION                      # no re-check of the inputs while running
    qtbot.mouseClick(win.btn_goal, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.last_goal is not None, timeout=20_000)
    assert "error" not in win.last_goal, win.last_goal
    assert win.last_goal["route_length_m"] > 100
    assert "m to the destination" in win.live["route"].text()
    assert math.hypot(win.map.goal_xy[0] - gxy[0], win.map.goal_xy[1] - gxy[1]) < 10.0
    # the route's length left counts down as the car drives (it stayed at the first figure)
    m0 = win.last_goal["route_length_m"]

    def left():
        txt = win.live["route"].text()
        return float(txt.split(" m to")[0]) if " m to the destination" in txt else None

    qtbot.waitUntil(lambda: left() is not None and left() < m0 - 10.0, timeout=30_000)
    assert abs(left() - win.last_frame["route_left"][0]) < 1.0 and win.last_frame["route_left"][1] > 0
    # one with no road near it is refused; the car drives on
    win.last_goal = None
    win.ed_dest_lat.setText(str(OFFROAD[0]))
    win.ed_dest_lon.setText(str(OFFROAD[1]))
    qtbot.mouseClick(win.btn_goal, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.last_goal is not None, timeout=20_000)
    assert "nearest road" in win.last_goal["error"] and win.lbl_msg.text().startswith("Destination: ")
    # outlined, as before a run; the car is still on its way to the destination it had (the
    # refused one dropped it, and the route line stopped)
    from ui.app import ERROR_STYLE

    assert win.ed_dest_lat.styleSheet() == ERROR_STYLE and win.ed_dest_lon.styleSheet() == ERROR_STYLE
    t = win.last_frame["t"]
    qtbot.waitUntil(lambda: win.last_frame["t"] > t + 1.0, timeout=10_000)
    assert win.state is S.SIMULATION
    assert win.last_frame["route_left"] is not None and "m to the destination" in win.live["route"].text()
    # no destination: the route line says so (it kept the old route's length and ETA)
    win.last_goal = None
    win.ed_dest_lat.clear()
    win.ed_dest_lon.clear()
    qtbot.mouseClick(win.btn_goal, Qt.LeftButton)
    qtbot.waitUntil(lambda: win.last_goal is not None, timeout=20_000)
    assert "error" not in win.last_goal and win.last_goal["route_length_m"] is None
    assert win.live["route"].text() == "no destination: driving on at random"
    assert win.ed_dest_lat.styleSheet() == "" and win.lbl_msg.text() == ""
    t = win.last_frame["t"]
    qtbot.waitUntil(lambda: win.last_frame["t"] > t + 1.0, timeout=10_000)
    assert win.live["route"].text() == "no destination: driving on at random"

    # a warning logged by the simulation shows on the status line
    import logging

    logging.getLogger("cosim.streaming").warning("could not build the window around chunk (1, 0): disk full")
    qtbot.waitUntil(lambda: "warning: could not build the window around chunk (1, 0)" in win.status_label.text(),
                    timeout=10_000)

    # keyboard: M takes over, the arrows drive, M gives control back. Keys typed into a
    # text field stay there; Esc leaves the field.
    win.ed_dest_lat.setFocus()
    qtbot.keyClick(win.ed_dest_lat, Qt.Key_M)
    assert win.ed_dest_lat.text().endswith("m")
    t = win.last_frame["t"]
    qtbot.waitUntil(lambda: win.last_frame["t"] > t + 0.5, timeout=10_000)
    assert not win.last_frame["manual"]
    qtbot.keyClick(win.ed_dest_lat, Qt.Key_Escape)
    assert win.ed_dest_lat.text().endswith("m") and not win.ed_dest_lat.hasFocus()
    qtbot.keyClick(win.map, Qt.Key_M)
    qtbot.waitUntil(lambda: win.last_frame["manual"], timeout=10_000)
    assert win.live["mode"].text().startswith("manual")
    qtbot.keyPress(win.map, Qt.Key_Up)                    # held
    qtbot.waitUntil(lambda: win.last_frame["control"][0] > 0.5, timeout=10_000)
    qtbot.keyRelease(win.map, Qt.Key_Up)
    qtbot.keyPress(win.map, Qt.Key_S)
    qtbot.keyPress(win.map, Qt.Key_A)
    qtbot.waitUntil(lambda: win.last_frame["control"][1] > 0.5 and win.last_frame["control"][2] > 0.3,
                    timeout=10_000)
    qtbot.keyRelease(win.map, Qt.Key_S)
    qtbot.keyRelease(win.map, Qt.Key_A)
    qtbot.waitUntil(lambda: win.last_frame["control"][1] == 0.0, timeout=10_000)
    # R: reverse, and the throttle backs the car up; R again: drive
    qtbot.waitUntil(lambda: abs(win.last_frame["ego"]["speed"]) < 0.5, timeout=20_000)
    qtbot.keyClick(win.map, Qt.Key_R)
    qtbot.keyPress(win.map, Qt.Key_Up)
    qtbot.waitUntil(lambda: win.last_frame["ego"]["speed"] < -0.5, timeout=10_000)
    qtbot.keyRelease(win.map, Qt.Key_Up)
    qtbot.keyClick(win.map, Qt.Key_R)
    qtbot.keyClick(win.map, Qt.Key_M)
    qtbot.waitUntil(lambda: not win.last_frame["manual"], timeout=10_000)
    assert win.live["mode"].text() == "automatic"

    # Stop: SUMO and PyBullet shut down in the worker, then Idle, then the inputs are checked again
    win.ed_dest_lat.clear()
    win.ed_dest_lon.clear()
    assert libsumo_running() and pybullet_connected(client)
    states.clear()
    qtbot.mouseClick(win.btn_stop, Qt.LeftButton)
    assert win.state is S.STOPPING and not win.btn_stop.isEnabled()
    wait_state(qtbot, win, S.READY, timeout=30_000)
    assert states == ["Stop", "Idle", "Input checked", "Ready"]
    assert "driven" in win.last_summary and "stopped." in win.status_label.text()
    assert win.worker.sim is None and win.worker.idle.is_set()
    assert not libsumo_running() and not pybullet_connected(client)
    assert win.ed_chunks.isEnabled() and not win.btn_goal.isEnabled()


def test_run_ends_by_itself_at_its_duration(qtbot, worlds):
    w = make_window(qtbot, worlds)
    try:
        w.cb_traffic.setCurrentText("light")
        wait_state(qtbot, w, S.READY)
        assert w.config.duration_s == V.RUN_DURATION_S
        w.config.duration_s = 2.0                          # the same object Start hands to the worker
        states = []
        w.state_changed.connect(lambda a, b, msg: states.append(b))
        w.btn_start.click()
        wait_state(qtbot, w, S.READY, timeout=120_000)
        assert states[:3] == ["Simulation", "Idle", "Input checked"]   # Simulation --stopped--> Idle
        assert w.last_summary.startswith("sim 2.0 s") and w.last_frame["t"] >= 2.0 - 1e-6
        assert not libsumo_running()
    finally:
        w.shutdown()
        w.close()


def test_closing_during_a_run_tears_everything_down(qtbot, worlds):
    w = make_window(qtbot, worlds)
    w.cb_traffic.setCurrentText("light")
    wait_state(qtbot, w, S.READY)
    w.btn_start.click()
    qtbot.waitUntil(lambda: w.last_frame is not None, timeout=120_000)
    client = w.worker.sim.physics.client
    assert libsumo_running()
    w.close()                                             # waits for the worker: not closed yet
    assert w.isVisible() and w.state is S.STOPPING
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=30_000)
    assert w._closed and w.sim_thread.isFinished() and w.check_thread.isFinished()
    assert not libsumo_running() and not pybullet_connected(client)
    assert not [p for p in child_processes() if "sumo" in p.name().lower()]


def test_closing_during_a_build_leaves_nothing_half_written(qtbot, tmp_path):
    from netgen.build import load_world_json

    root = tmp_path / "worlds"
    w = make_window(qtbot, root)
    w.ed_chunks.setText("0")
    w.cb_traffic.setCurrentText("none")
    wait_state(qtbot, w, S.READY)
    stages = []
    w.worker.progress.connect(lambda st, f, msg, o: stages.append(st))
    before = {p.pid for p in child_processes()}
    w.btn_start.click()
    qtbot.waitUntil(lambda: "osm" in stages, timeout=60_000)   # the build has begun
    w.close()
    assert w.state is S.STOPPING
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=120_000)
    assert "run" not in stages                             # it never ran
    assert w.last_summary == "stopped before the simulation ran"
    assert not libsumo_running()
    leftovers = [p for p in root.rglob("*") if ".tmp-" in p.name]
    assert leftovers == []
    for d in (root.iterdir() if root.exists() else []):
        if d.name.startswith(".") and d.name.endswith(".lock"):     # (a folder's empty lock file)
            assert d.is_file() and d.stat().st_size == 0
            continue
        assert load_world_json(d) is not None, f"{d} is a world folder without a complete world"
    # netconvert, a forked scenery process: whatever the build started has ended
    qtbot.waitUntil(lambda: not [p for p in child_processes() if p.pid not in before], timeout=10_000)


def test_setup_error_is_shown_in_the_error_state(qtbot, tmp_path):
    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the worlds folder should be")
    w = make_window(qtbot, blocker)
    try:
        w.ed_chunks.setText("0")
        wait_state(qtbot, w, S.READY)
        w.btn_start.click()
        wait_state(qtbot, w, S.ERROR, timeout=60_000)
        assert w.lbl_msg.text().startswith("cannot write")
        assert not w.btn_start.isEnabled() and not w.btn_stop.isEnabled() and w.ed_chunks.isEnabled()
        assert w.worker.sim is None and not libsumo_running()
        w.ed_chunks.setText("1")                           # Error --edit--> Input checked -> Ready
        wait_state(qtbot, w, S.READY)
    finally:
        w.shutdown()
        w.close()


def test_screenshot_script(tmp_path, worlds):
    out = tmp_path / "gui.png"
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    r = subprocess.run([sys.executable, str(REPO / "scripts" / "screenshot_gui.py"), "--out", str(out),
                        "--worlds", str(worlds), "--seconds", "3", "--traffic", "light"],
                       capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "wrote" in r.stdout and "real time" in r.stdout
    from PyQt5.QtGui import QImage

    img = QImage(str(out))
    assert img.width() >= 1000 and img.height() >= 700


_WINDOW_SCRIPT = r"""
import subprocess, sys, time
import numpy as np, pybullet as pb
from cosim.physics import PhysicsWorld
from cosim.world import World

fb, world = sys.argv[1], sys.argv[2]


def screen():
    raw = open(fb, "rb").read()            # Xvfb's frame buffer, an XWD dump
    h = np.frombuffer(raw[:100], ">u4")
    size, width, height, stride, ncolors = int(h[0]), int(h[4]), int(h[5]), int(h[12]), int(h[19])
    off = size + 12 * ncolors
    px = np.frombuffer(raw[off:off + stride * height], np.uint8).reshape(height, stride)
    return px[:, :width * 4].reshape(height, width, 4)[:, :, :3].astype(int)


def drawn():
    # the share of the window's lower half not in the background's colour: the ground, drawn
    for _ in range(40):
        pb.stepSimulation(physicsClientId=c)
        time.sleep(0.025)
    img = screen()
    sky = img[5, img.shape[1] // 4]
    lower = img[img.shape[0] // 2 + 20:img.shape[0] - 20, 20:img.shape[1] // 2]
    vivid = img.max(axis=2) - img.min(axis=2) > 120     # (none of the world's own colours is)
    return float((np.abs(lower - sky).sum(axis=2) > 24).mean()), float(vivid.mean())


pw = PhysicsWorld(World(world), gui=True).setup()
c = pw.client
pw.update(0.0, 0.0, 200.0, budget_ms=1e9)
pb.resetDebugVisualizerCamera(40, 30, -40, [0, 0, float(pw.world.ground_z(0.0, 0.0)[0])], physicsClientId=c)
before = drawn()
win = subprocess.run(["xdotool", "search", "--name", "Bullet"], capture_output=True, text=True).stdout.split()
subprocess.run(["xdotool", "windowactivate", "--sync", win[0]], capture_output=True)
for key in ("w", "a", "s", "d"):
    subprocess.run(["xdotool", "key", key])
after = drawn()
print(f"drawn {before[0]:.3f} {after[0]:.3f} vivid {before[1]:.4f}")
pb.disconnect(c)
"""


def test_pybullet_window_keeps_drawing_the_world_when_wasd_are_pressed(tmp_path, kouvola_world):
    """In PyBullet's own window (``cosim run --gui``), the world is drawn in its own colours,
    and W A S D drive the car. The window's own keyboard shortcuts are off: W switched the
    world to wireframe (the ground no longer drawn). Needs Xvfb and xdotool (`.ci/run` installs them; elsewhere this skips, saying so):
    the window is drawn on a virtual screen and the keys are typed into it."""
    import shutil
    import time

    tools = [t for t in ("Xvfb", "xdotool") if shutil.which(t) is None]
    if tools:
        pytest.skip(f"{' and '.join(tools)} not installed (Debian: apt install xvfb xdotool)")
    x11 = Path("/tmp/.X11-unix")
    n = next(k for k in range(150, 300) if not (x11 / f"X{k}").exists() and not Path(f"/tmp/.X{k}-lock").exists())
    xvfb = subprocess.Popen(["Xvfb", f":{n}", "-screen", "0", "1024x768x24", "-fbdir", str(tmp_path), "-nolisten", "tcp"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        from cosim.display import display_problem

        env = dict(os.environ, DISPLAY=f":{n}")
        env.pop("QT_QPA_PLATFORM", None)
        # (until the server takes a connection, not only until its socket file is there: on a
        # loaded machine, the suite's other worker busy, PyBullet once found no X server)
        t_end = time.monotonic() + 60.0
        while display_problem(env) is not None and xvfb.poll() is None and time.monotonic() < t_end:
            time.sleep(0.1)
        assert display_problem(env) is None, f"Xvfb :{n} did not come up ({display_problem(env)})"
        r = subprocess.run([sys.executable, "-c", _WINDOW_SCRIPT, str(tmp_path / "Xvfb_screen0"), str(kouvola_world.path)],
                           capture_output=True, text=True, timeout=300, env=env,
                           cwd=Path(__file__).resolve().parents[1])
    finally:
        xvfb.terminate()
        xvfb.wait(timeout=30)
    got = [ln for ln in r.stdout.splitlines() if ln.startswith("drawn ")]
    assert r.returncode == 0 and got, (r.stdout + r.stderr)[-3000:]
    before, after, vivid = (float(v) for v in got[0].split()[1:] if v != "vivid")
    assert before > 0.9, before             # the ground fills the lower half
    assert after > 0.9, after               # and still does after W A S D
    # and in its own colours: the window drew the collision parts of the roads and buildings
    # in vivid colours of its own over their meshes, unless they have an invisible shape
    assert vivid < 0.002, vivid
