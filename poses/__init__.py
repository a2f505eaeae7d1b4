"""evcap.poses: camera poses from the events (event frames, structure from motion)."""
