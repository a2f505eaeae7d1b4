"""Importers: recordings made by other tools brought into a session. Each module reads one
container and writes a session with ``SessionWriter``; `evcap import` picks the module by the
file's content (``detect``)."""
