"""evcap.recon: event-only Gaussian Splatting reconstruction of geometry and material."""
