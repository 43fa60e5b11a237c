"""Can a window open here? PyBullet's 3D window (``--gui``) and sumo-gui (``--sumo-gui``) need
an X server on Linux, and neither fails cleanly without one: PyBullet's window thread ends the
whole process ("cannot connect to X server", exit code 1), and sumo-gui ends before TraCI can
connect. :func:`display_problem` asks before they try.
"""
from __future__ import annotations

import os
import socket
import sys

X11_SOCKET_DIR = "/tmp/.X11-unix"
X11_TCP_BASE = 6000


def display_problem(env=None, x11_dir: str = X11_SOCKET_DIR) -> str | None:
    """Why no window can open here, in a few words; None when an X server answers at
    ``$DISPLAY`` (or off Linux, where nothing is checked). An X server answers when its
    socket takes a connection: ``<x11_dir>/X<n>`` (or Linux's abstract socket of that name)
    for ``:n``, TCP port 6000 + n of the host for ``host:n``."""
    env = os.environ if env is None else env
    if not sys.platform.startswith("linux"):
        return None
    disp = env.get("DISPLAY", "")
    if not disp:
        return "there is no display (DISPLAY is not set)"
    host, _, rest = disp.rpartition(":")
    num = rest.split(".")[0]
    if not num.isdigit():
        return f"DISPLAY={disp} is not a display name"
    if host in ("", "unix"):
        path = os.path.join(x11_dir, f"X{num}")
        for address in (path, "\0" + path):         # the file, then the abstract socket
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                s.settimeout(2.0)
                s.connect(address)
                return None
            except OSError:
                pass
            finally:
                s.close()
    else:
        try:
            socket.create_connection((host, X11_TCP_BASE + int(num)), timeout=2.0).close()
            return None
        except OSError:
            pass
    return f"no X server answers at DISPLAY={disp}"
