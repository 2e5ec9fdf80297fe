"""continual-nerf: instant continual learning of neural radiance fields, as a nerfstudio plugin."""
