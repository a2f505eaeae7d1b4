"""evcap.sim: synthetic scenes with ground truth and the event simulator."""
