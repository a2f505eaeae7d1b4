"""Scoring against a simulated session's truth: the held-out views rendered and scored
(views.py), the image and geometry metrics (metrics.py), LPIPS. May import the stages and what
is under them; nothing imports it but reconstruct.py and the benches."""
