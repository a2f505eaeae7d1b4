"""The application floor: the `evcap` command (the single-step commands, `evcap demo`, `evcap
batch`) and the demo, over the pipeline (evcap.pipeline), the steps (acquire, calib, poses, recon,
report, sim, tui) and the spine."""
