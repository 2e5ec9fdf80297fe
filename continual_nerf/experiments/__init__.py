"""The paper's experiments as one command (`continual-nerf-experiments`): plan, runner, report and CLI."""
