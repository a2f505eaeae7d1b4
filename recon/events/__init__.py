"""The events as the reconstruction reads them: the windows' count tables (windows.py, which
filter the events with evcap.event_filters) and the compiled CPU event loss (_loss_cpu.py; its
PyTorch reference is still in recon/radiance/losses.py and stage.py). May import the scene's
optics; no stage."""
