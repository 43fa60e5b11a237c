"""Worker processes of the co-simulation (SUMO, background window builds).

A worker is a plain interpreter running ``python -m <module> <fd>``, connected by a socket
pair wrapped in a ``multiprocessing.connection.Connection``. Not multiprocessing's spawn: it
re-runs the caller's ``__main__`` in the child, so a user's script without a main guard would
start a second simulation there.
"""
from __future__ import annotations

import os
import socket
import subprocess
import sys
from multiprocessing.connection import Connection
from pathlib import Path


def start_worker(module: str) -> tuple[subprocess.Popen, Connection]:
    """Start ``python -m module`` with one end of a socket pair; returns (process, our end).
    Raises OSError when the process cannot start."""
    parent, child = socket.socketpair()
    env = dict(os.environ)
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    try:
        # (-P, Python 3.11+: the working folder is not put first on the worker's path, so that
        # it imports this copy of the package, not one that happens to lie in the working folder)
        safe = ["-P"] if sys.version_info >= (3, 11) else []
        proc = subprocess.Popen([sys.executable, *safe, "-m", module, str(child.fileno())],
                                pass_fds=(child.fileno(),), env=env, cwd=os.getcwd())
    except OSError:
        parent.close()
        raise
    finally:
        child.close()
    return proc, Connection(parent.detach())


def worker_connection() -> Connection:
    """In the worker: the connection to the process that started it."""
    return Connection(int(sys.argv[1]))
