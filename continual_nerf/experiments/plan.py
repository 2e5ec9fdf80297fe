"""Which runs the experiments train: a run per method, task count and per-task budget; tables share runs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional

from nerfstudio.plugins.registry import discover_methods

from continual_nerf.baselines.nerf_model import ContinualNeRFModelConfig
from continual_nerf.core.continual_trainer import ContinualTrainerConfig

PAPER_TABLE1 = (
    "continual-ngp-paper", "continual-ngp-incre", "continual-ngp-ewc", "continual-nerf-incre", "continual-nerf-meil",
    "continual-ngp-joint", "continual-nerf-joint",
)  # fmt: skip
"""The methods of the paper's Table 1, its own method with the paper's recipe exactly."""
TABLE1 = (*PAPER_TABLE1, "continual-ngp")
"""The report's Table 1: the paper's rows, then continual-ngp with this plugin's defaults."""


@dataclass(frozen=True)
class RunSpec:
    """One training run: a method, a number of tasks and a per-task budget (iterations or seconds)."""

    method: str
    num_tasks: int
    iterations_per_task: Optional[int]
    seconds_per_task: Optional[float] = None

    @property
    def key(self) -> str:
        budget = f"{self.seconds_per_task:g}s" if self.seconds_per_task is not None else f"{self.iterations_per_task}it"
        return f"{self.method}_{self.num_tasks}tasks_{budget}"


@dataclass
class Plan:
    """The runs behind each table; a run several tables need is trained once."""

    table1: List[RunSpec]
    table2: List[RunSpec]
    table3: List[RunSpec]

    def runs(self) -> List[RunSpec]:
        return list(dict.fromkeys(self.table1 + self.table2 + self.table3))

    def keys(self) -> Dict[str, List[str]]:
        """Run keys per table, as results.json lists them."""
        return {
            "table1": [spec.key for spec in self.table1],
            "table2": [spec.key for spec in self.table2],
            "table3": [spec.key for spec in self.table3],
        }


def continual_methods() -> Dict[str, ContinualTrainerConfig]:
    """Every registered nerfstudio method that trains task by task (this plugin's and any other's)."""
    methods, _ = discover_methods()
    return {name: config for name, config in methods.items() if isinstance(config, ContinualTrainerConfig)}


def is_implicit(config: ContinualTrainerConfig) -> bool:
    """Whether the method's model is the fully implicit NeRF (the paper gives those a longer budget)."""
    return isinstance(config.pipeline.model, ContinualNeRFModelConfig)
