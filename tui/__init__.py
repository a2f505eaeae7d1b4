"""evcap.tui: the terminal UI for live capture monitoring (textual)."""

from evcap.tui.app import MonitorApp, make_app

__all__ = ["MonitorApp", "make_app"]
