"""Shared test fixtures.

Real data only: the embedded presets, and ../shared/data beside the checkout (tests that
need a file from there skip with a reason naming it when it is absent, as on a user's clone).
"""
from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("COSIM_SHARED_DATA", REPO.parent / "shared" / "data"))

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")


def shared_file(rel: str) -> Path:
    """Path of a file under ../shared/data, or skip the test naming the missing file."""
    p = SHARED_DATA / rel
    if not p.exists():
        pytest.skip(f"needs ../shared/data/{rel}, which is absent (it lives beside the checkout in CI)")
    return p


@pytest.fixture
def shared():
    return shared_file


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """Each test session gets its own cache dir so tests never trust a user's cache."""
    monkeypatch.setenv("COSIM_CACHE", str(tmp_path_factory.getbasetemp() / "cosim-cache"))


class SmallDisk:
    """A real, small file system (tmpfs) that can be filled, for the full-disk checks."""

    def __init__(self, path: Path):
        self.path = path

    def fill(self, leave: int = 0) -> None:
        """Take all its free space but ``leave`` bytes (one file, allocated at once)."""
        import shutil
        free = shutil.disk_usage(self.path).free
        fd = os.open(self.path / f"filler-{free}", os.O_WRONLY | os.O_CREAT, 0o600)
        try:
            if free > leave:
                os.posix_fallocate(fd, 0, free - leave)
        finally:
            os.close(fd)

    def empty(self) -> None:
        for f in self.path.glob("filler-*"):
            f.unlink()


@pytest.fixture
def small_disk(tmp_path):
    """An 8 MB tmpfs mounted in the test's folder. Mounting needs root (CAP_SYS_ADMIN):
    elsewhere the test skips and says so."""
    import subprocess
    mnt = tmp_path / "small-disk"
    mnt.mkdir()
    try:
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=8m", "tmpfs", str(mnt)],
                           capture_output=True, text=True, timeout=30)
    except OSError as e:
        pytest.skip(f"cannot mount a small tmpfs for the full-disk check: {e}")
    if r.returncode != 0:
        pytest.skip("cannot mount a small tmpfs for the full-disk check (needs root): "
                    + (r.stderr.strip().splitlines() or ["mount failed"])[-1])
    try:
        yield SmallDisk(mnt)
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True, timeout=30)
