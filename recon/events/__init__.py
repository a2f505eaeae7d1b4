"""The events as the reconstruction reads them: the windows' count tables (windows.py), the
compiled CPU event loss (_loss_cpu.py; its PyTorch reference is still in
recon/radiance/losses.py and stage.py) and the background-activity filter. May import the
scene's optics; no stage."""
