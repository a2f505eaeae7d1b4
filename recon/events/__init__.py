"""The events as the reconstruction reads them: the windows' count tables (windows.py) and the
event loss (loss.py: the PyTorch reference and the compiled CPU path behind one function).
May import the scene's optics; no stage."""
