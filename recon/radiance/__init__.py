"""Stage I: the event-supervised Gaussian radiance field (stage.py) and its settings
(config.py: its own, the components' nested), its loss terms as a list (terms.py, over
losses.py), its densification strategy (densify.py) and the trajectory's refinement
(pose_refinement.py), each with its config beside it. May import the scene, the events and the
rasterizer; not stage II, the mesh or the evaluation."""
