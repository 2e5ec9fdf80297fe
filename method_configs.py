"""Methods this plugin registers with nerfstudio (entry point group `nerfstudio.method_configs`)."""

from __future__ import annotations

import copy

from nerfstudio.configs.base_config import ViewerConfig
from nerfstudio.engine.optimizers import AdamOptimizerConfig
from nerfstudio.plugins.types import MethodSpecification

from continual_nerf.continual_datamanager import ContinualDataManagerConfig
from continual_nerf.continual_model import ContinualNGPModelConfig
from continual_nerf.continual_pipeline import ContinualPipelineConfig
from continual_nerf.continual_trainer import ContinualTrainerConfig
from continual_nerf.streaming_datamanager import StreamingDataManagerConfig


def _adam() -> dict:
    # constant learning rate: a decaying schedule would leave later tasks less to learn with than earlier ones
    return {"optimizer": AdamOptimizerConfig(lr=1e-2, eps=1e-15), "scheduler": None}


continual_ngp = MethodSpecification(
    config=ContinualTrainerConfig(
        method_name="continual-ngp",
        steps_per_eval_batch=500,
        steps_per_eval_image=500,
        steps_per_eval_all_images=10**9,
        steps_per_save=2000,
        save_only_latest_checkpoint=False,
        mixed_precision=True,
        pipeline=ContinualPipelineConfig(
            datamanager=ContinualDataManagerConfig(train_num_rays_per_batch=1024),
            model=ContinualNGPModelConfig(eval_num_rays_per_chunk=1 << 13),
        ),
        optimizers={"proposal_networks": _adam(), "fields": _adam()},
        viewer=ViewerConfig(websocket_host="127.0.0.1", num_rays_per_chunk=1 << 13),
        vis="viewer",
    ),
    description="Instant continual learning of NeRFs (Po et al.): hash grid + replay by distillation, task by task.",
)


def _streaming(config: ContinualTrainerConfig) -> ContinualTrainerConfig:
    """`config` reading its tasks from a capture folder while it is written; every other option stays the same."""
    config = copy.deepcopy(config)
    config.method_name = "continual-ngp-stream"
    rays = config.pipeline.datamanager.train_num_rays_per_batch
    config.pipeline.datamanager = StreamingDataManagerConfig(train_num_rays_per_batch=rays)
    return config


continual_ngp_stream = MethodSpecification(
    config=_streaming(continual_ngp.config),
    description="continual-ngp on a capture folder that is still being written (continual-stream): "
    "a task opens whenever its frames have arrived.",
)
