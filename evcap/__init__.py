"""evcap: record, calibrate and reconstruct scenes with a color event camera.

The session file (evcap.session) is the format every step reads and writes; the event
container (evcap.events) is what flows between steps in memory.
"""

__version__ = "0.1.0"
