"""`python -m continual_nerf.experiments`: the same as `continual-nerf-experiments`."""

from continual_nerf.experiments.cli import entrypoint

if __name__ == "__main__":
    entrypoint()
