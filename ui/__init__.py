"""The desktop launcher (``cosim gui``): a PyQt5 client of the same Python API as the CLI.

* :mod:`ui.app` — the main window and :func:`ui.app.main`;
* :mod:`ui.validation` — the inputs' checks and the launcher's state machine (no Qt);
* :mod:`ui.worker` — the QThread workers that own the Simulation and run the checks;
* :mod:`ui.mapview` — the top-down map.
"""
