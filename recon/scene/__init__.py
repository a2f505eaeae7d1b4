"""What both stages share of the scene: the Gaussians and the background (gaussians.py), their
spherical harmonics, the sensor's optics and render grids, the scene's volume from the poses,
nearest neighbours. May import the rasterizer and recon/'s own helpers; no stage."""
