"""One test per nerfstudio internal the plugin relies on (continual_nerf/nerfstudio_compat.py): each fails loudly
when a nerfstudio release changes what the plugin depends on."""

from __future__ import annotations

import inspect
import random
import socket
from datetime import timedelta

import numpy as np
import pytest
import torch
from helpers import demo_parser, tiny_config, train
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipeline
from torch import nn

from continual_nerf import nerfstudio_compat as compat
from continual_nerf.compilation import random_rays
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.recipes import small_model

SCENE_BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def test_nerfacto_builds_offline_with_lpips_replaced():
    with compat.without_lpips():
        model = NerfactoModelConfig().setup(scene_box=SCENE_BOX, num_train_data=1)
    assert isinstance(model.lpips, compat._LPIPSNotComputed), "nerfstudio no longer builds LPIPS where it is patched"


def test_proposal_sampler_counters_exist_and_round_trip():
    model = small_model(ContinualNGPModelConfig(compile=False)).setup(scene_box=SCENE_BOX, num_train_data=1)
    state = compat.proposal_sampler_state(model)
    assert set(state) == {"proposal_step", "proposal_steps_since_update"}
    compat.set_proposal_sampler_state(model, {"proposal_step": 7, "proposal_steps_since_update": 2})
    assert compat.proposal_sampler_state(model) == {"proposal_step": 7, "proposal_steps_since_update": 2}
    model.proposal_sampler.step_cb(11)  # nerfstudio's own callback sets the counter the checkpoint keeps
    assert compat.proposal_sampler_state(model)["proposal_step"] == 11


@pytest.mark.parametrize("use_linear", [False, True])
def test_hot_modules_are_the_modules_every_sample_passes_through(use_linear):
    config = small_model(ContinualNGPModelConfig(compile=False))
    config.proposal_net_args_list = [{**args, "use_linear": use_linear} for args in config.proposal_net_args_list]
    model = config.setup(scene_box=SCENE_BOX, num_train_data=1)
    modules = compat.hot_modules(model)
    assert modules and all(isinstance(module, nn.Module) for module in modules)
    calls = []
    for module in modules:
        compat.replace_forward(module, counting(module, calls))
    model.eval()
    with torch.no_grad():
        model(random_rays(model, 8))
    assert {id(module) for module in calls} == {id(module) for module in modules}, (
        "nerfstudio calls every hot module through module(...), as replace_forward needs"
    )


def counting(module: nn.Module, calls: list):
    forward = module.forward

    def counted(*args, **kwargs):
        calls.append(module)
        return forward(*args, **kwargs)

    return counted


def test_seed_like_ns_train_seeds_python_numpy_and_torch():
    compat.seed_like_ns_train(5)
    drawn = (random.random(), np.random.rand(), torch.rand(1).item())
    random.seed(5), np.random.seed(5), torch.manual_seed(5)
    assert drawn == (random.random(), np.random.rand(), torch.rand(1).item())


@pytest.mark.slow
def test_a_resumed_run_ends_at_the_same_step_as_the_uninterrupted_one(tmp_path):
    """Depends on nerfstudio 1.1.5 counting max_num_iterations from the resumed step (set_resume_step)."""
    parser = demo_parser()
    whole = tiny_config(tmp_path / "whole", parser, num_tasks=2, iterations_per_task=2)
    train(whole)
    checkpoint_dir = whole.get_checkpoint_dir()
    resumed = tiny_config(tmp_path / "resumed", parser, num_tasks=2, iterations_per_task=2)
    resumed.load_checkpoint = checkpoint_dir / "step-000000001.ckpt"  # the end of task 1
    trainer = train(resumed)
    matrix = AccuracyMatrix.read(resumed.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert matrix.finished and matrix.steps == [1, 3] and trainer.step == 3


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def test_viewer_internals_the_panel_uses(tmp_path):
    config = tiny_config(tmp_path / "outputs", demo_parser(), num_tasks=2, iterations_per_task=2)
    config.vis = "viewer"
    config.viewer.websocket_port = _free_port()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    viewer = trainer.viewer_state
    try:
        compat.init_scene_without_frustums(viewer, trainer.pipeline.datamanager.train_dataset, "training")
        assert viewer.camera_handles == {} and viewer.config.max_num_display_images > 0, "no frustum, config restored"
        assert isinstance(compat.panel_order(viewer), float)
        assert compat.training_cameras_shown(viewer)
        compat.register_frustum(viewer, 3, "handle", np.eye(4)[:3])
        assert viewer.camera_handles[3] == "handle" and viewer.original_c2w[3].shape == (3, 4)
        compat.set_current_camera(viewer, 3)
        assert viewer.current_camera_idx == 3
        viewer.camera_handles.clear()
        compat.show_resume_button(viewer)
        assert not viewer.pause_train.visible and viewer.resume_train.visible
    finally:
        trainer.shutdown()


def test_vanilla_pipeline_wraps_with_cuda_device_ids_only_for_several_processes():
    source = inspect.getsource(VanillaPipeline.__init__)
    assert "if world_size > 1:" in source and "device_ids=[local_rank]" in source
    assert compat.world_size_for_vanilla_pipeline("cpu", 2) == 1
    assert compat.world_size_for_vanilla_pipeline("cuda:1", 2) == 2


def test_ns_train_saves_the_config_right_before_launch_and_looks_launch_up_when_called(monkeypatch):
    from nerfstudio.scripts import train as ns_train

    main = inspect.getsource(ns_train.main)
    assert main.index("config.save_config()") < main.index("launch(")
    assert "_distributed_worker," in inspect.getsource(ns_train.launch)  # a global, looked up when launch runs
    monkeypatch.setattr(ns_train, "launch", ns_train.launch)
    monkeypatch.setattr(ns_train, "_distributed_worker", ns_train._distributed_worker)
    monkeypatch.setattr(compat, "_nerfstudio_launch", [])
    compat.launch_processes_here()
    assert ns_train.launch is compat.launch_reporting_one_line
    assert ns_train._distributed_worker is compat.process_worker


def test_process_worker_runs_nerfstudios_worker_on_cpu_without_its_cuda_checks(monkeypatch):
    from nerfstudio.scripts.train import _distributed_worker
    from nerfstudio.utils import comms

    assert list(inspect.signature(_distributed_worker).parameters) == list(
        inspect.signature(compat.process_worker).parameters
    )
    monkeypatch.setattr(comms, "LOCAL_PROCESS_GROUP", None)
    seen = []
    compat.process_worker(
        0, lambda *args: seen.append((args, torch.cuda.is_available())), 1, 1, 0, f"tcp://127.0.0.1:{_free_port()}",
        None, timedelta(seconds=30), "cpu",
    )  # fmt: skip
    assert seen == [((0, 1, None, 0), torch.cuda.is_available())]  # training sees the machine as it is
