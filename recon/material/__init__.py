"""Stage II: base color, roughness, normals and the light on stage I's frozen Gaussians
(stage.py, its terms a list as stage I's), its settings (config.py), the shading and the
visibility. May import stage I, the scene, the events and the rasterizer; not the mesh or the
evaluation."""
