"""`evcap batch`: a collection of recordings through calibration, poses, reconstruction and
report, on a Ray cluster or one after the other."""
