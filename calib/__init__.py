"""evcap.calib: intrinsics, per-pixel contrast thresholds, hot pixels and noise."""
