"""`evcap export`: the depth fused into a signed distance volume (tsdf.py), its surface, the
texture atlas baked from rendered views (bake.py), the files (export.py). May import the stages
and what is under them; not the evaluation."""
