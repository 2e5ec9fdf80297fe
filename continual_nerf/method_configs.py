"""Methods this plugin registers with nerfstudio (entry point group `nerfstudio.method_configs`)."""

from __future__ import annotations

import copy
import dataclasses

from nerfstudio.engine.optimizers import AdamOptimizerConfig, RAdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from continual_nerf.baselines.ewc import ContinualNGPEWCModelConfig, EWCPipelineConfig
from continual_nerf.baselines.nerf_model import ContinualNeRFModelConfig, ContinualNeRFPipelineConfig
from continual_nerf.core.continual_datamanager import ContinualDataManagerConfig
from continual_nerf.core.continual_pipeline import ContinualPipelineConfig
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig
from continual_nerf.core.ngp_model import COLOR_TRANSFORM_GROUP, ContinualNGPModelConfig
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.streaming.streaming_datamanager import StreamingDataManagerConfig
from continual_nerf.viewer.live_trainer import LiveViewerTrainerConfig
from continual_nerf.viewer.viewer_config import ContinualViewerConfig


def _adam() -> dict:
    # no schedule over the run: it would leave later tasks less to learn with than earlier ones (the pipeline's
    # --pipeline.lr-decay-per-task restarts with every task instead)
    return {"optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15), "scheduler": None}


CONTINUAL_NGP = LiveViewerTrainerConfig(
    method_name="continual-ngp",
    steps_per_eval_batch=500,
    steps_per_eval_image=500,
    steps_per_eval_all_images=10**9,
    steps_per_save=2000,
    save_only_latest_checkpoint=False,
    mixed_precision=True,
    pipeline=ContinualPipelineConfig(
        datamanager=ContinualDataManagerConfig(
            dataparser=ContinualDemoDataParserConfig(), train_num_rays_per_batch=1024
        ),
        model=ContinualNGPModelConfig(eval_num_rays_per_chunk=1 << 13),
        # the last quarter of each task at a falling rate: what each task ends with, and the oracle copies, has settled
        lr_decay_per_task=0.1,
        lr_decay_start=0.75,
    ),
    optimizers={
        "proposal_networks": _adam(),
        "fields": _adam(),
        # pose corrections (--pipeline.model.camera-optimizer.mode): below nerfacto's 1e-3, since a task's frames
        # refine in a few hundred steps and Adam's normalised steps at 1e-3 move even exact poses half a degree
        "camera_opt": {"optimizer": AdamOptimizerConfig(lr=3e-4, eps=1e-15), "scheduler": None},
        # colour transforms (--pipeline.model.use-color-transform): slower than the fields, since the fit at each task
        # switch starts them near their frames' exposure and a faster rate trades them off against the field's colour
        COLOR_TRANSFORM_GROUP: {"optimizer": AdamOptimizerConfig(lr=3e-3, eps=1e-15), "scheduler": None},
    },
    viewer=ContinualViewerConfig(),
    vis="viewer",
)
"""continual-ngp: the paper's method; every other method is a difference from it."""

continual_ngp = MethodSpecification(
    config=CONTINUAL_NGP,
    description="Instant continual learning of NeRFs (Po et al.): hash grid + replay by distillation, task by task.",
)


def _streaming(config: LiveViewerTrainerConfig) -> LiveViewerTrainerConfig:
    """`config` reading its tasks from a capture folder while it is written; every other option stays the same."""
    config = copy.deepcopy(config)
    config.method_name = "continual-ngp-stream"
    rays = config.pipeline.datamanager.train_num_rays_per_batch
    config.pipeline.datamanager = StreamingDataManagerConfig(train_num_rays_per_batch=rays)
    config.viewer.follow_newest_task = True  # later tasks' cameras leave the first task's view
    return config


continual_ngp_stream = MethodSpecification(
    config=_streaming(CONTINUAL_NGP),
    description="continual-ngp on a capture folder that is still being written (continual-stream): "
    "a task opens whenever its frames have arrived.",
)


def _depth(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
    """`config` whose model trains on the capture's depth maps too, with depth-nerfacto's losses; the options `config`
    sets apart from its model's defaults stay, the depth model's defaults (its own and those it changes) apply to the
    rest."""
    config = copy.deepcopy(config)
    config.method_name = "continual-ngp-depth"
    model, defaults = config.pipeline.model, type(config.pipeline.model)()
    options = {
        f.name: getattr(model, f.name)
        for f in dataclasses.fields(model)
        if f.init and f.name != "_target" and getattr(model, f.name) != getattr(defaults, f.name)
    }
    config.pipeline.model = ContinualNGPDepthModelConfig(**options)
    return config


CONTINUAL_NGP_DEPTH = _depth(CONTINUAL_NGP)
"""continual-ngp-depth: continual-ngp trained on depth maps too (as depth-nerfacto beside nerfacto)."""

continual_ngp_depth = MethodSpecification(
    config=CONTINUAL_NGP_DEPTH,
    description="continual-ngp trained on RGB-D captures' depth maps too (ScanNet, TUM, transforms.json "
    "depth_file_path, the demo), with depth-nerfacto's DS-NeRF or URF loss.",
)


def _variant(config: ContinualTrainerConfig, method_name: str, **datamanager: object) -> ContinualTrainerConfig:
    """`config` under another name with some datamanager options changed and the paper's constant learning rates: a
    baseline is a configuration."""
    config = copy.deepcopy(config)
    config.method_name = method_name
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, **datamanager)
    config.pipeline.lr_decay_per_task, config.pipeline.lr_decay_start = 1.0, 0.0
    return config


def _ewc(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
    """`config` without replay, its model and pipeline adding the EWC penalty and estimating the Fisher information."""
    config = _variant(config, "continual-ngp-ewc", replay=False)
    model = ContinualNGPEWCModelConfig(eval_num_rays_per_chunk=config.pipeline.model.eval_num_rays_per_chunk)
    config.pipeline = EWCPipelineConfig(datamanager=config.pipeline.datamanager, model=model)
    return config


def _nerf(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
    """`config` with nerfstudio's vanilla NeRF model and its optimizer (RAdam, lr 5e-4, full precision)."""
    config = _variant(config, "continual-nerf-meil")
    model = ContinualNeRFModelConfig(eval_num_rays_per_chunk=config.pipeline.model.eval_num_rays_per_chunk)
    config.pipeline = ContinualNeRFPipelineConfig(datamanager=config.pipeline.datamanager, model=model)
    # constant learning rate, as for continual-ngp
    config.optimizers = {"fields": {"optimizer": RAdamOptimizerConfig(lr=5e-4, eps=1e-8), "scheduler": None}}
    config.mixed_precision = False
    return config


CONTINUAL_NGP_PAPER = _variant(CONTINUAL_NGP, "continual-ngp-paper", current_task_fraction="uniform")
"""The paper's recipe exactly: each batch uniform over all released pixels, no stored pixels."""

continual_ngp_paper = MethodSpecification(
    config=CONTINUAL_NGP_PAPER,
    description="continual-ngp with the paper's recipe exactly (Po et al.): batches uniform over all released pixels.",
)

CONTINUAL_NGP_INCRE = _variant(CONTINUAL_NGP, "continual-ngp-incre", replay=False)
"""iNGP-Incre: continual-ngp without replay."""

continual_ngp_incre = MethodSpecification(
    config=CONTINUAL_NGP_INCRE,
    description="iNGP-Incre (paper baseline): continual-ngp's hash grid trained task by task without replay.",
)

continual_ngp_ewc = MethodSpecification(
    config=_ewc(CONTINUAL_NGP),
    description="iNGP + EWC (paper baseline): the hash grid without replay, held near each task's parameters "
    "by Elastic Weight Consolidation.",
)

CONTINUAL_NGP_JOINT = _variant(CONTINUAL_NGP, "continual-ngp-joint", replay=False, joint=True)
"""iNGP*: the joint upper bound."""

continual_ngp_joint = MethodSpecification(
    config=CONTINUAL_NGP_JOINT,
    description="iNGP* (upper bound): the hash grid trained on every task's images at once, same total budget.",
)

CONTINUAL_NERF_MEIL = _nerf(CONTINUAL_NGP)
"""MEIL-NeRF as the paper ran it; the NeRF-backbone baselines differ from it."""

continual_nerf_meil = MethodSpecification(
    config=CONTINUAL_NERF_MEIL,
    description="MEIL-NeRF as the paper ran it: vanilla NeRF with replay by distillation from stored poses (Eq. 4).",
)

continual_nerf_incre = MethodSpecification(
    config=_variant(CONTINUAL_NERF_MEIL, "continual-nerf-incre", replay=False),
    description="NeRF-Incre (paper baseline): vanilla NeRF (frequency encoding + MLP) trained task by task.",
)

continual_nerf_joint = MethodSpecification(
    config=_variant(CONTINUAL_NERF_MEIL, "continual-nerf-joint", replay=False, joint=True),
    description="NeRF* (upper bound): vanilla NeRF trained on every task's images at once, same total budget.",
)
