"""The rasterizer: differentiable rendering of 3D Gaussians (rasterize.py), one interface over
three backends (the compiled CPU kernels, pure PyTorch, gsplat's CUDA) and a per-pixel
reference for the tests. Imports nothing of evcap.recon but recon/_threads.py."""
