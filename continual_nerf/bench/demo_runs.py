"""The configurations the benchmarks compare: registered methods on the demo scene, and nerfstudio's nerfacto."""

from __future__ import annotations

import copy
import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Literal, Optional, Sequence

import tyro
from nerfstudio.configs.method_configs import all_methods, method_configs as nerfstudio_methods
from nerfstudio.engine.trainer import TrainerConfig

from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.method_configs import CONTINUAL_NGP
from continual_nerf.recipes import quiet_config

Device = Literal["cpu", "cuda"]


@dataclass
class DemoBenchmark:
    """Options every benchmark that trains on the demo scenes has."""

    rays_per_batch: int = 1024
    """Rays per training batch (the paper's 1024); a grid recipe that sets
    --pipeline.datamanager.train-num-rays-per-batch trains with its own."""
    device: Device = "cpu"
    """Device every run trains on."""
    data: Path = Path("data/continual-demo")
    """Where the demo scenes are generated (and reused from)."""


def check_names(option: str, chosen: Iterable[str], known: Iterable[str]) -> None:
    """Exit with one line naming the chosen names that are not known ones."""
    known = list(known)
    unknown = [name for name in chosen if name not in known]
    if unknown:
        raise SystemExit(f"--{option}: unknown {', '.join(unknown)} (known: {', '.join(known)})")


def recipe_config(
    arguments: Sequence[str], option: str, rays_per_batch: Optional[int] = None
) -> ContinualTrainerConfig:
    """The config `ns-train METHOD OPTIONS` would train, for `arguments` = METHOD OPTIONS (a registered continual
    method, its options and optionally a dataparser subcommand with its own); bad ones end with one line naming
    `option`. `rays_per_batch` replaces the method's rays per batch, and the options may set their own over it."""
    if not arguments:
        raise SystemExit(f"{option}: no method given")
    method, options = arguments[0], list(arguments[1:])
    base = all_methods.get(method)
    if not isinstance(base, ContinualTrainerConfig):
        raise SystemExit(f"{option}: {method} is not a registered continual method")
    base = copy.deepcopy(base)
    if rays_per_batch is not None:
        base.pipeline.datamanager.train_num_rays_per_batch = rays_per_batch
    try:
        # as ns-train parses: booleans take a value (--pipeline.model.use-color-transform True)
        return tyro.cli(
            tyro.conf.FlagConversionOff[ContinualTrainerConfig],  # type: ignore[valid-type]
            default=base,
            args=options,
            console_outputs=False,
        )
    except SystemExit:
        raise SystemExit(f"{option}: {shlex.join(options)} are not options of ns-train {method}") from None


def on_demo(
    config: ContinualTrainerConfig,
    demo: ContinualDemoDataParserConfig,
    device: Device,
    output_dir: Path,
    **options: Any,
) -> ContinualTrainerConfig:
    """A quiet copy of `config` training on the `demo` scene, with datamanager options."""
    return quiet_config(config, output_dir, device=device, dataparser=demo, **options)


def nerfacto_on_demo(
    demo: ContinualDemoDataParserConfig, device: Device, output_dir: Path, **datamanager: Any
) -> ContinualTrainerConfig:
    """nerfstudio's registered nerfacto (model and optimizers) fed by the same datamanager, all images open at once."""
    nerfacto = nerfstudio_methods["nerfacto"]
    assert isinstance(nerfacto, TrainerConfig)
    config = on_demo(CONTINUAL_NGP, demo, device, output_dir, replay=False, joint=True, **datamanager)
    config.method_name = "nerfacto"
    # nerfacto's model in the continual pipeline: a benchmark reference, not a registered method
    config.pipeline.model = copy.deepcopy(nerfacto.pipeline.model)  # type: ignore[assignment]
    config.optimizers = copy.deepcopy(nerfacto.optimizers)
    return config
