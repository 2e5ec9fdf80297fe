"""nerfstudio's own test (its tests/test_train.py) on every registered continual method: 2 iterations, 4 rays,
CPU, torch implementation, no grad scaler, started with `train_loop(local_rank=0, world_size=0, ...)` as nerfstudio
starts it. On the demo scene: nerfstudio's one-frame lego test data cannot be split into tasks."""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
from helpers import demo_parser
from nerfstudio.scripts.train import train_loop

from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.continual_trainer import ContinualTrainerConfig
from continual_nerf.dataparsers.stream_dataparser import StreamDataParserConfig
from continual_nerf.experiments.plan import continual_methods
from continual_nerf.streaming.replay_capture import ReplayCaptureConfig, replay

pytestmark = pytest.mark.slow  # trains models, runs subprocesses or a browser

METHODS = sorted(continual_methods())


def set_reduced_config(config: ContinualTrainerConfig, tmp_path: Path) -> ContinualTrainerConfig:
    """nerfstudio's set_reduced_config, but for the scene, and logging into the test's folder (not /tmp)."""
    config = copy.deepcopy(config)
    config.machine.device_type = "cpu"
    if hasattr(config.pipeline.model, "implementation"):
        config.pipeline.model.implementation = "torch"  # type: ignore[attr-defined]
    config.mixed_precision = False
    config.use_grad_scaler = False
    config.max_num_iterations = 2
    config.pipeline.datamanager.train_num_images_to_sample_from = 1
    config.pipeline.datamanager.train_num_rays_per_batch = 4
    config.vis = "tensorboard"
    if hasattr(config.pipeline.model, "num_coarse_samples"):
        config.pipeline.model.num_coarse_samples = 4  # type: ignore[attr-defined]
        config.pipeline.model.num_importance_samples = 4  # type: ignore[attr-defined]
    config.viewer.quit_on_train_completion = True
    config.set_timestamp()
    config.output_dir = tmp_path / "outputs"
    return config


@pytest.mark.parametrize("method", METHODS)
def test_nerfstudio_reduced_run(method, tmp_path, capsys):
    config = set_reduced_config(continual_methods()[method], tmp_path)
    if isinstance(config.pipeline.datamanager.dataparser, StreamDataParserConfig):
        capture = tmp_path / "capture"
        replay(ReplayCaptureConfig(output=capture, fps=0, dataparser=demo_parser()))
        config.pipeline.datamanager.dataparser = StreamDataParserConfig(data=capture, frames_per_task=4)
    else:
        config.pipeline.datamanager.dataparser = demo_parser()
    config.pipeline.datamanager.num_tasks = 2
    train_loop(local_rank=0, world_size=0, config=config)
    matrix = AccuracyMatrix.read(config.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert not matrix.psnr and not matrix.finished, "2 iterations end the run inside task 1"
    assert "--max-num-iterations 2 may end the run before its last task" in capsys.readouterr().out
    assert sorted(path.name for path in config.get_checkpoint_dir().iterdir()) == ["step-000000001.ckpt"]
    assert list(config.get_base_dir().glob("events.out.tfevents.*")), "tensorboard logs into the run's folder"
