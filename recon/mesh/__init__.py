"""`evcap export`: the depth fused into a signed distance volume (tsdf.py), its surface, the
texture atlas baked from rendered views (bake.py), the files (export.py), its settings
(config.py: MeshConfig, without torch). May import the stages and what is under them; not the
evaluation."""
