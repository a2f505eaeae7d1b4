"""evcap.tui: the terminal UI for live capture monitoring."""
