"""Stage I: the event-supervised Gaussian radiance field (stage.py), its loss terms, its
densification strategy and the trajectory's refinement. May import the scene, the events and
the rasterizer; not stage II, the mesh or the evaluation."""
