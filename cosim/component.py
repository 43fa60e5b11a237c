"""The lifecycle every co-simulation component shares: ``setup()``, per-frame work,
``teardown()`` (idempotent), and use as a context manager."""
from __future__ import annotations


class Component:
    def setup(self):
        return self

    def teardown(self) -> None:
        pass

    def __enter__(self):
        self.setup()
        return self

    def __exit__(self, *exc):
        self.teardown()
