"""The paper's method: task split, continual dataset and datamanager, replay oracle, Eq. 4, hash-grid model,
pipeline (which owns the continual state), trainer and accuracy matrix."""
