"""The events as the reconstruction reads them: the windows' count tables and the windows a step
draws (windows.py, its config WindowsConfig; the events filtered by evcap.event_filters) and the
event loss both stages use (loss.py: one function over its PyTorch reference and its compiled
CPU kernel, _loss_cpu.py; its config EventLossConfig). May import the scene's optics; no
stage."""
