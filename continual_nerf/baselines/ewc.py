"""Elastic Weight Consolidation on continual-ngp: the paper's iNGP + EWC baseline (section 5.1).

At the end of every task but the last, while its pixels are still readable, the diagonal Fisher
information of the task's loss is estimated from squared gradients over a few of its batches, and
the current parameters become the reference. Training on later tasks adds
lambda/2 * sum F (phi - phi_ref)^2 over every trainable parameter: hash features and MLP weights.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Dict, Type

import torch
from torch import Tensor, nn

from continual_nerf.core import distributed
from continual_nerf.core.continual_pipeline import ContinualPipeline, ContinualPipelineConfig
from continual_nerf.core.ngp_model import ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.errors import ContinualConfigError

EWC_LOSS = "ewc_loss"


def _buffer_name(parameter_name: str) -> str:
    return parameter_name.replace(".", "__")  # buffer names cannot contain dots


class EWCPenalty(nn.Module):
    """Fisher information and reference values of named parameters, as buffers so that checkpoints hold them."""

    num_consolidated: Tensor
    """Tasks consolidated so far (a buffer)."""

    def __init__(self, parameters: Dict[str, Tensor]) -> None:
        super().__init__()
        self.fisher = nn.Module()
        self.reference = nn.Module()
        for name, parameter in parameters.items():
            self.fisher.register_buffer(_buffer_name(name), torch.zeros_like(parameter, requires_grad=False))
            self.reference.register_buffer(_buffer_name(name), torch.zeros_like(parameter, requires_grad=False))
        self.register_buffer("num_consolidated", torch.zeros((), dtype=torch.long))

    @property
    def active(self) -> bool:
        return bool(self.num_consolidated > 0)

    @torch.no_grad()
    def consolidate(self, fisher: Dict[str, Tensor], parameters: Dict[str, Tensor]) -> None:
        """Add a finished task's Fisher information and take the current parameter values as the reference."""
        for name, parameter in parameters.items():
            # summed over tasks (online EWC with no decay): one reference, but every task's importance is kept
            getattr(self.fisher, _buffer_name(name)).add_(fisher[name])
            getattr(self.reference, _buffer_name(name)).copy_(parameter)
        self.num_consolidated += 1

    def forward(self, parameters: Dict[str, Tensor]) -> Tensor:
        """sum F (phi - phi_ref)^2 over all parameters (the penalty without its lambda/2)."""
        terms = [
            (
                getattr(self.fisher, _buffer_name(name))
                * (parameter - getattr(self.reference, _buffer_name(name))).pow(2)
            ).sum()
            for name, parameter in parameters.items()
        ]
        return torch.stack(terms).sum()


def estimate_fisher(
    parameters: Dict[str, Tensor], batch_loss: Callable[[], Tensor], num_batches: int
) -> Dict[str, Tensor]:
    """Diagonal empirical Fisher information: the mean over `num_batches` batches of the squared loss gradient."""
    names, tensors = list(parameters), list(parameters.values())
    fisher = {name: torch.zeros_like(tensor) for name, tensor in parameters.items()}
    for _ in range(num_batches):
        # autograd.grad leaves the parameters' .grad, which the optimizers read, untouched
        gradients = torch.autograd.grad(batch_loss(), tensors, allow_unused=True)
        for name, gradient in zip(names, gradients):
            if gradient is not None:
                fisher[name] += gradient.detach().pow(2) / num_batches
    return fisher


@dataclass
class ContinualNGPEWCModelConfig(ContinualNGPModelConfig):
    """continual-ngp's hash-grid model with the EWC penalty added to its loss once a task has been consolidated."""

    _target: Type = field(default_factory=lambda: ContinualNGPEWCModel)
    ewc_lambda: float = 1e6
    """Weight lambda of the penalty lambda/2 * sum F (phi - phi_ref)^2 (demo room: 1e4 barely acts, 1e8 stalls)."""

    def validate(self) -> None:
        super().validate()
        if self.ewc_lambda < 0:
            raise ContinualConfigError(f"--pipeline.model.ewc-lambda must not be negative, got {self.ewc_lambda}")


class ContinualNGPEWCModel(ContinualNGPModel):
    """ContinualNGPModel plus the EWC penalty over all its trainable parameters."""

    config: ContinualNGPEWCModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        self.ewc = EWCPenalty(self.consolidated_parameters())

    def consolidated_parameters(self) -> Dict[str, Tensor]:
        """The parameters EWC holds near their reference: the field's and proposal networks' hash features and MLPs."""
        modules = {"field": self.field, "proposal_networks": self.proposal_networks}
        return {
            f"{prefix}.{name}": parameter
            for prefix, module in modules.items()
            for name, parameter in module.named_parameters()
            if parameter.requires_grad
        }

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        loss_dict = super().get_loss_dict(outputs, batch, metrics_dict)
        if self.training and self.ewc.active:
            loss_dict[EWC_LOSS] = self.config.ewc_lambda / 2 * self.ewc(self.consolidated_parameters())
        return loss_dict


@dataclass
class EWCPipelineConfig(ContinualPipelineConfig):
    """The continual pipeline that estimates the Fisher information at the end of every task."""

    _target: Type = field(default_factory=lambda: EWCPipeline)
    model: ContinualNGPEWCModelConfig = field(default_factory=ContinualNGPEWCModelConfig)
    """The hash-grid model with the EWC penalty."""
    fisher_batches: int = 8
    """Batches of the finished task whose squared loss gradients are averaged into its Fisher information."""

    def validate(self) -> None:
        super().validate()
        if self.fisher_batches < 1:
            raise ContinualConfigError(f"--pipeline.fisher-batches must be at least 1, got {self.fisher_batches}")


class EWCPipeline(ContinualPipeline):
    """ContinualPipeline whose task end consolidates the finished task into the model's EWC penalty."""

    config: EWCPipelineConfig
    model: ContinualNGPEWCModel

    def before_task_switch(self) -> None:
        parameters = self.model.consolidated_parameters()

        def task_loss() -> Tensor:
            # the task's own loss: batches of the open task, without the penalty of earlier tasks; through the
            # unwrapped model, as autograd.grad leaves DDP's gradient all-reduce waiting
            _, loss_dict, _ = self.local_train_loss_dict(step=0)
            return torch.stack([value for name, value in loss_dict.items() if name != EWC_LOSS]).sum()

        # every rank estimates from its own batches; their mean is the estimate over all of them
        fisher = distributed.averaged_over_ranks(estimate_fisher(parameters, task_loss, self.config.fisher_batches))
        self.model.ewc.consolidate(fisher, parameters)
