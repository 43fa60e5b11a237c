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
