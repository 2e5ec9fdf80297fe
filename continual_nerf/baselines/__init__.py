"""The paper's baselines that need code of their own: EWC and the vanilla-NeRF backbone (the rest are configs)."""
