"""Compile ``sdf_checker.cc`` against the system's SDFormat library (on demand, cached).

    python tests/sdf_checker/build.py            # prints the checker's path, or why it cannot be built

Needs a C++17 compiler, pkg-config and SDFormat >= 12 with headers (Debian/Ubuntu:
``apt-get install g++ pkg-config libsdformat-dev sdformat-sdf``; bookworm ships SDFormat 12).
The binary is cached under ``$COSIM_SDF_CHECKER_CACHE`` (default
``$XDG_CACHE_HOME/cosim/sdf_checker`` or ``~/.cache/cosim/sdf_checker``; ``$TMPDIR/cosim-sdf-checker-UID``
when that cannot be written), named by a hash of the source, the compiler and the library
flags, so a changed source or library rebuilds it. No binary is committed.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "sdf_checker.cc"
MIN_MAJOR = 12          # sdf::ParserConfig with enforcement policies
MODULES = [f"sdformat{n}" for n in range(16, MIN_MAJOR - 1, -1)]


class CheckerUnavailable(Exception):
    """The SDFormat checker cannot be built on this machine (the message says why)."""


def _run(args, **kw) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, **kw)


def find_sdformat() -> tuple[str, str]:
    """(pkg-config module, version) of the newest usable SDFormat, or raise CheckerUnavailable."""
    if not shutil.which("pkg-config"):
        raise CheckerUnavailable("pkg-config is not installed "
                                 "(apt-get install pkg-config libsdformat-dev sdformat-sdf)")
    for mod in MODULES:
        r = _run(["pkg-config", "--modversion", mod])
        if r.returncode == 0:
            return mod, r.stdout.strip()
    older = [f"sdformat{n}" for n in range(MIN_MAJOR - 1, 5, -1)]
    for mod in older:
        if _run(["pkg-config", "--exists", mod]).returncode == 0:
            raise CheckerUnavailable(f"SDFormat {mod[8:]} is too old for the checker (needs >= {MIN_MAJOR})")
    raise CheckerUnavailable("the SDFormat library with headers is not installed (no pkg-config module "
                             f"sdformat{MIN_MAJOR}+; on Debian/Ubuntu: apt-get install libsdformat-dev sdformat-sdf)")


def cache_dir() -> Path:
    d = os.environ.get("COSIM_SDF_CHECKER_CACHE")
    if d:
        return Path(d)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "cosim" / "sdf_checker"


def build_checker(out_dir: Path | None = None) -> Path:
    """Path of a compiled checker (compiling it if needed), or raise CheckerUnavailable."""
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++") or shutil.which("clang++")
    if not cxx:
        raise CheckerUnavailable("no C++ compiler (apt-get install g++)")
    mod, version = find_sdformat()
    flags = _run(["pkg-config", "--cflags", "--libs", mod])
    if flags.returncode != 0:
        raise CheckerUnavailable(f"pkg-config {mod} failed: {flags.stderr.strip()}")
    cver = _run([cxx, "--version"]).stdout.splitlines()[:1]
    key = hashlib.sha256(SOURCE.read_bytes() + flags.stdout.encode() + repr(cver).encode() +
                         version.encode()).hexdigest()[:16]
    fallback = Path(tempfile.gettempdir()) / f"cosim-sdf-checker-{os.getuid()}"
    dirs = [Path(out_dir)] if out_dir else [cache_dir(), fallback]
    for d in dirs:
        exe = d / f"sdf_checker-{mod}-{key}"
        if exe.exists() and os.access(exe, os.X_OK):
            return exe
    for d in dirs:                      # the cache, or a temp folder when the cache is read-only
        exe = d / f"sdf_checker-{mod}-{key}"
        try:
            d.mkdir(parents=True, exist_ok=True)
            fd, tmp = tempfile.mkstemp(prefix=exe.name + ".tmp-", dir=d)
            os.close(fd)
            break
        except OSError as e:
            err = e
    else:
        raise CheckerUnavailable(f"cannot write the checker's cache folder {dirs[-1]}: {err}")
    args = [cxx, "-std=c++17", "-O1", "-o", tmp, str(SOURCE)] + flags.stdout.split()
    r = _run(args)
    if r.returncode != 0:
        os.unlink(tmp)
        # headers are there but the checker does not compile: a real failure, not a skip
        raise RuntimeError(f"compiling the SDFormat checker failed ({' '.join(args)}):\n{r.stderr[-4000:]}")
    os.chmod(tmp, 0o755)
    os.replace(tmp, exe)
    return exe


if __name__ == "__main__":
    try:
        print(build_checker())
    except CheckerUnavailable as e:
        print(f"unavailable: {e}", file=sys.stderr)
        sys.exit(1)
