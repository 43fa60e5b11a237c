"""User-facing errors.

Every error a user can cause (bad coordinates, a corrupt file, a DEM that does not cover the
area, a web service that is down) is raised as a :class:`CosimError` subclass with a message
that fits on one line. The CLI prints ``error: <message>`` and exits non-zero; it never shows a
traceback for these.
"""


class CosimError(Exception):
    """Base class: an error whose message is meant for the user, one line."""

    exit_code = 2

    def __str__(self) -> str:  # keep it to one line whatever the caller passed
        return " ".join(str(self.args[0] if self.args else self.__class__.__name__).split())


class InputError(CosimError):
    """The user's input is out of range or inconsistent."""


class DataError(CosimError):
    """Input data (OSM file, DEM) is missing, corrupt, empty or does not cover the area."""


class ServiceError(CosimError):
    """A web service (Overpass, open-elevation) failed after retries, or answered garbage."""


class BuildError(CosimError):
    """A build step (netconvert, writing output) failed."""


class SimulationError(CosimError):
    """SUMO or PyBullet failed during a run."""
