"""The application floor: the `evcap` command, the demo and the pipeline they and `evcap batch`
run, over the steps (acquire, calib, poses, recon, report, sim, tui) and the spine."""
