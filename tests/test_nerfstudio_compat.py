"""One test per nerfstudio internal the plugin relies on (continual_nerf/nerfstudio_compat.py): each fails loudly
when a nerfstudio release changes what the plugin depends on."""

from __future__ import annotations

import inspect
import logging
import random
import socket
import sys
import threading
import time
import traceback
import warnings
from datetime import timedelta
from typing import List
from unittest import mock

import numpy as np
import pytest
import torch
import viser.transforms as vtf
from helpers import demo_parser, stopped_run, tiny_config, train
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation
from nerfstudio.engine.trainer import Trainer, TrainerConfig
from nerfstudio.field_components.embedding import Embedding
from nerfstudio.models.nerfacto import NerfactoModelConfig
from nerfstudio.pipelines.base_pipeline import VanillaPipeline
from torch import nn
from torch.nn.parallel import DistributedDataParallel

from continual_nerf import nerfstudio_compat as compat
from continual_nerf.compilation import random_rays
from continual_nerf.core.accuracy_matrix import ACCURACY_MATRIX_FILENAME, AccuracyMatrix
from continual_nerf.core.depth_maps import METRES_PER_SCENE_UNIT
from continual_nerf.core.depth_model import ContinualNGPDepthModelConfig
from continual_nerf.core.ngp_model import ContinualNGPModelConfig
from continual_nerf.recipes import set_up_like_ns_train, small_model

SCENE_BOX = SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))


def test_nerfacto_builds_offline_with_lpips_replaced():
    with compat.without_lpips():
        model = NerfactoModelConfig().setup(scene_box=SCENE_BOX, num_train_data=1)
    assert isinstance(model.lpips, compat._LPIPSNotComputed), "nerfstudio no longer builds LPIPS where it is patched"


def test_nerfstudio_raises_the_warnings_kept_out_of_the_terminal_and_only_those_are(monkeypatch):
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.configs.base_config import MachineConfig
    from nerfstudio.engine.trainer import TrainerConfig

    cameras = Cameras(camera_to_worlds=torch.eye(4)[None, :3], fx=10.0, fy=10.0, cx=2.0, cy=2.0, width=4, height=4)

    def raised() -> set:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if quiet:
                compat.quiet_nerfstudio_warnings(on_cpu=True)
            cameras.generate_rays(camera_indices=torch.zeros(3, 1, dtype=torch.long), coords=torch.zeros(3, 2))
            Trainer(
                TrainerConfig(method_name="nerfacto", mixed_precision=True, machine=MachineConfig(device_type="cpu"))
            )
            warnings.warn("a warning of anyone else's", UserWarning)
        return {str(warning.message).split(".")[0] for warning in caught}

    monkeypatch.setattr(sys, "warnoptions", [])
    quiet = False
    assert {"Using a non-tuple sequence for multidimensional indexing is deprecated and will be changed in pytorch 2",
            "`torch", "torch"} <= raised(), "nerfstudio's camera indexing and its GradScaler on a CPU warn"  # fmt: skip
    quiet = True
    assert raised() == {"a warning of anyone else's"}, "kept out by message and module, nothing else"
    assert "ignore:Using a non-tuple sequence for multidimensional indexing:UserWarning:nerfstudio.cameras.cameras" in (
        sys.warnoptions
    ), "the processes ns-train starts get the same filters"


def test_proposal_sampler_counters_exist_and_round_trip():
    model = small_model(ContinualNGPModelConfig(compile=False)).setup(scene_box=SCENE_BOX, num_train_data=1)
    state = compat.proposal_sampler_state(model)
    assert set(state) == {"proposal_step", "proposal_steps_since_update"}
    compat.set_proposal_sampler_state(model, {"proposal_step": 7, "proposal_steps_since_update": 2})
    assert compat.proposal_sampler_state(model) == {"proposal_step": 7, "proposal_steps_since_update": 2}
    model.proposal_sampler.step_cb(11)  # nerfstudio's own callback sets the counter the checkpoint keeps
    assert compat.proposal_sampler_state(model)["proposal_step"] == 11


@pytest.mark.parametrize("metres_per_unit, near_plane", [(None, 0.05), (10.0, 0.05), (200.0, 0.01)])
def test_nerfactos_collider_starts_rays_at_the_near_plane_brought_in_to_its_metres(metres_per_unit, near_plane):
    metadata = {} if metres_per_unit is None else {METRES_PER_SCENE_UNIT: metres_per_unit}
    config = small_model(ContinualNGPModelConfig(compile=False, near_plane=0.05, near_plane_metres=2.0))
    model = config.setup(scene_box=SCENE_BOX, num_train_data=1, metadata=metadata)
    nears = model.collider(random_rays(model, 4)).nears
    assert nears is not None and torch.allclose(nears, torch.full_like(nears, near_plane))


@pytest.mark.parametrize(
    "metres_per_unit, contracted, max_res",
    [(None, True, 128), (10.0, True, 128), (40.0, True, 320), (200.0, True, 1600), (200.0, False, 800)],
)
def test_the_fields_finest_resolution_is_raised_where_the_captures_scale_makes_its_cells_coarse(
    metres_per_unit, contracted, max_res
):
    metadata = {} if metres_per_unit is None else {METRES_PER_SCENE_UNIT: metres_per_unit}
    config = small_model(  # max-res 128: cells of 0.5 m up to 16 m per scene unit (the contracted space spans 4 units)
        ContinualNGPModelConfig(compile=False, finest_cell_metres=0.5, disable_scene_contraction=not contracted)
    )
    model = config.setup(scene_box=SCENE_BOX, num_train_data=1, metadata=metadata)
    assert model.field.mlp_base.max_res == max_res
    assert config.max_res == 128, "the run's config keeps the option as given"
    oracle = model.config.setup(scene_box=SCENE_BOX, num_train_data=1, metadata=metadata)
    assert oracle.field.mlp_base.max_res == max_res, "a copy built from the model's config has the same grid"


def test_finest_cell_metres_none_keeps_max_res():
    config = small_model(ContinualNGPModelConfig(compile=False, finest_cell_metres=None))
    model = config.setup(scene_box=SCENE_BOX, num_train_data=1, metadata={METRES_PER_SCENE_UNIT: 200.0})
    assert model.field.mlp_base.max_res == 128


def test_depth_nerfacto_decays_its_sigma_in_an_attribute_no_checkpoint_keeps():
    config = ContinualNGPDepthModelConfig(
        compile=False, should_decay_sigma=True, starting_depth_sigma=0.2, sigma_decay_rate=0.5, depth_sigma=0.01
    )
    model = small_model(config).setup(scene_box=SCENE_BOX, num_train_data=1)
    assert compat.depth_sigma(model) == pytest.approx(0.2)
    assert not any("sigma" in name for name, _ in model.named_buffers()), "nerfstudio made it a buffer: drop the touch"
    model.train()

    def training_metrics() -> None:
        rays = random_rays(model, 8)
        rays.metadata["directions_norm"] = torch.ones(8, 1)
        model.get_metrics_dict(model(rays), {"image": torch.rand(8, 3), "depth_image": torch.rand(8, 1)})

    training_metrics()
    assert compat.depth_sigma(model) == pytest.approx(0.1), "depth-nerfacto decays it at every training batch"
    compat.set_depth_sigma(model, 0.05)
    training_metrics()
    assert compat.depth_sigma(model) == pytest.approx(0.025), "and decays the sigma it is given"


def test_rays_are_sampled_as_in_training_while_the_model_evaluates():
    model = small_model(ContinualNGPModelConfig(compile=False)).setup(scene_box=SCENE_BOX, num_train_data=1)
    model.eval()
    rays = random_rays(model, 64)

    def collided() -> RayBundle:
        rays.nears = rays.fars = None  # the collider leaves set planes as they are
        return model.collider(rays)

    def sample_starts() -> torch.Tensor:
        return model.proposal_sampler(collided(), density_fns=model.density_fns)[0].frustums.starts

    with torch.no_grad():
        fixed = sample_starts()
        assert torch.equal(sample_starts(), fixed), "evaluation samples at fixed places"
        assert torch.all(collided().nears == 0), "nerfstudio evaluates from the camera's centre on"
        compat.sample_rays_as_in_training(model)
        assert not model.training and not model.field.training, "only the samplers and the collider change mode"
        jittered = sample_starts()
        assert not torch.equal(jittered, fixed) and not torch.equal(sample_starts(), jittered)
        assert torch.all(collided().nears == model.config.near_plane), "the training near plane"


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
    stopped = tiny_config(tmp_path / "stopped", parser, num_tasks=2, iterations_per_task=2)
    resumed = tiny_config(tmp_path / "resumed", parser, num_tasks=2, iterations_per_task=2)
    resumed.load_checkpoint = stopped_run(stopped, last_step=1)  # the end of task 1
    trainer = train(resumed)
    matrix = AccuracyMatrix.read(resumed.get_base_dir() / ACCURACY_MATRIX_FILENAME)
    assert matrix.finished and matrix.steps == [1, 3] and trainer.step == 3
    assert compat.first_step(trainer) == 2, "the loop started after the checkpoint's step"


@pytest.mark.slow
def test_leaving_the_viewer_s_pause_lets_the_loop_go_on(tmp_path):
    """Depends on nerfstudio's loop waiting while `training_state` is "paused" (leave_pause)."""
    config = tiny_config(tmp_path / "outputs", demo_parser(), num_tasks=2, iterations_per_task=2)
    config.start_paused = True
    config.save_config()
    trainer = set_up_like_ns_train(config)
    steps: List[int] = []

    def trained(step: int) -> None:
        steps.append(step)

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], trained))
    thread = threading.Thread(target=trainer.train, daemon=True)  # paused, it would wait for ever
    thread.start()
    compat.leave_pause(trainer)
    thread.join(timeout=300)
    assert not thread.is_alive() and steps == [0, 1, 2, 3], "the paused loop went on and trained every step"


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


class RenderThread(threading.Thread):
    """What stop_rendering reads of nerfstudio's RenderStateMachine: a loop that runs while `running`."""

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.running, self.interrupt_render_flag, self.render_trigger = True, False, threading.Event()

    def run(self) -> None:
        while self.running:
            self.render_trigger.wait(0.05)


def test_a_render_thread_stored_but_not_yet_started_is_stopped_once_it_starts():
    # a browser connecting as the run ends: nerfstudio stores its render thread first and starts it a moment later
    late, running = RenderThread(), RenderThread()
    running.start()
    viewer = mock.Mock(render_statemachines={1: late, 2: running})
    threading.Timer(0.2, late.start).start()
    compat.stop_rendering(viewer)
    assert late.ident is not None and not late.is_alive() and not running.is_alive()


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
        handle = mock.Mock()
        compat.register_frustum(viewer, 3, handle, np.eye(4)[:3])
        assert viewer.camera_handles[3] is handle and viewer.original_c2w[3].shape == (3, 4)
        compat.set_current_camera(viewer, 3)
        assert viewer.current_camera_idx == 3
        compat.remove_frustum(viewer, 3)
        handle.remove.assert_called_once()
        assert viewer.camera_handles == {} and viewer.original_c2w == {}
        compat.show_resume_button(viewer)
        assert not viewer.pause_train.visible and viewer.resume_train.visible
        compat.set_render_defaults(viewer, 128, 0.95)
        assert viewer.control_panel.max_res == 128 and viewer.control_panel.train_util == 0.95
        compat.show_step(viewer, 7)
        assert viewer.stats_markdown.content.splitlines()[0].startswith("Step: 7")
        compat.disable_training_buttons(viewer)
        assert viewer.pause_train.disabled and viewer.resume_train.disabled
        compat.rerender(viewer)  # no browser connected: nothing to render, and no error
        import websocket  # the test extra's

        page = websocket.create_connection(
            f"ws://127.0.0.1:{config.viewer.websocket_port}", timeout=10, suppress_origin=True
        )
        try:
            page.send_binary(compat.viewer_camera_message(np.ones(3), np.zeros(3), np.array([0, 0, 1.0]), 1.0, 1.4))
            deadline = time.monotonic() + 120  # a hang, not a slow machine
            while not viewer.render_statemachines:
                assert time.monotonic() < deadline, "no render thread for the page"
                time.sleep(0.05)
            threads = list(viewer.render_statemachines.values())
            compat.stop_rendering(viewer)
            assert not any(thread.is_alive() for thread in threads), "the page's render thread has ended"
        finally:
            page.close()
    finally:
        trainer.shutdown()


def test_an_empty_profile_is_dropped_and_a_run_s_profile_kept():
    from nerfstudio.configs.base_config import LoggingConfig
    from nerfstudio.utils import profiler

    profiler.PROFILER[:] = [profiler.Profiler(LoggingConfig())]
    try:
        compat.forget_empty_profile()
        assert profiler.PROFILER == [], "set-up ended before a step: nothing to print"
        profiler.PROFILER.append(profiler.Profiler(LoggingConfig()))
        profiler.PROFILER[0].update_time("Trainer.train_iteration", 0.0, 0.5)
        compat.forget_empty_profile()
        assert len(profiler.PROFILER) == 1, "a run's timings are kept for nerfstudio to print"
    finally:
        profiler.PROFILER.clear()


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
    compat.launch_processes_here(lambda: None)
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


def test_a_process_leaving_at_ctrl_c_destroys_its_process_group_first(monkeypatch):
    from nerfstudio.utils import comms

    monkeypatch.setattr(comms, "LOCAL_PROCESS_GROUP", None)

    def interrupted(*_: object) -> None:
        assert torch.distributed.is_initialized()
        raise SystemExit(130)  # what the trainer raises once every rank has agreed to stop

    with pytest.raises(SystemExit) as exited:
        compat.process_worker(
            0, interrupted, 1, 1, 0, f"tcp://127.0.0.1:{_free_port()}", None, timedelta(seconds=30), "cpu"
        )
    assert exited.value.code == 130
    assert not torch.distributed.is_initialized(), "left alive, gloo's threads may abort the interpreter's exit"


def test_the_launcher_prints_the_failed_process_s_own_line_or_how_it_ended():
    from torch.multiprocessing import ProcessExitedException, ProcessRaisedException

    line = "continual-ngp: error: data/scene: no such folder"
    try:
        raise compat.ProcessFailed(line)
    except compat.ProcessFailed:
        traceback_text = traceback.format_exc()  # what mp.spawn hands the launching process
    raised = ProcessRaisedException(f"\n\n-- Process 1 terminated with the following error:\n{traceback_text}", 1, 42)
    assert compat.failed_process_line(raised, "continual-ngp") == line
    killed = ProcessExitedException("process 1 terminated with signal SIGKILL", 1, 42, -9, "SIGKILL")
    assert compat.failed_process_line(killed, "continual-ngp") == (
        "continual-ngp: error: process 1 terminated with signal SIGKILL; the other processes were stopped"
    )
    lost = ProcessExitedException("process 0 terminated with exit code 75", 0, 41, compat.PEER_LOST_EXIT)
    assert "process 0 lost its connection to another process" in compat.failed_process_line(lost, "continual-ngp")
    gloo = "[gloo/transport/tcp/pair.cc:545] Read error [127.0.0.1]:41659: Connection reset by peer. This is typically"
    assert compat.lost_a_peer(RuntimeError(gloo)) and not compat.lost_a_peer(RuntimeError("CUDA out of memory"))


def test_trainer_methods_the_continual_trainer_overrides():
    for name in compat.TRAINER_OVERRIDES:
        assert callable(getattr(Trainer, name, None)), f"nerfstudio's Trainer has no {name} any more"
    setup, train = inspect.getsource(Trainer.setup), inspect.getsource(Trainer.train)
    assert setup.index("ViewerState(") < setup.index("self._check_viewer_warnings()"), "called after the viewer starts"
    assert "self._load_checkpoint()" in setup and "self._init_viewer_state()" in train
    loop = train[train.index("for step in range") :]
    assert loop.index("self.step = step") < loop.index("if self.stop_training:"), "step moves on before the check"
    assert "self.save_checkpoint(self.step)" in inspect.getsource(Trainer._after_train)


def test_the_terminals_progress_counts_to_the_step_it_is_given():
    from nerfstudio.configs.base_config import LoggingConfig
    from nerfstudio.utils import writer

    writer.setup_local_writer(LoggingConfig(), max_iter=10)  # what a run resumed at step 30 of 40 has left
    compat.count_progress_to(40)
    writer.put_time(name=writer.EventName.ITER_TRAIN_TIME, duration=2.0, step=30, avg_over_steps=True, update_eta=True)
    assert writer.GLOBAL_BUFFER["events"][writer.EventName.ETA.value] == "20 s, 0.000 ms", "10 steps left of 2 s"
    assert writer.GLOBAL_BUFFER["max_iter"] == 40, "% done divides the step by it"


def test_a_camera_message_makes_a_viser_client_with_that_camera():
    import viser
    import websocket

    port = _free_port()
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    cameras = []
    server.on_client_connect(lambda client: cameras.append(client.camera))
    position, look_at, up = np.array([1.0, -8.0, 6.0]), np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0])
    page = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=10, suppress_origin=True)
    try:
        page.send_binary(compat.viewer_camera_message(position, look_at, up, fov=1.0, aspect=1.5))
        deadline = time.monotonic() + 120  # a hang, not a slow machine
        while not cameras and time.monotonic() < deadline:
            time.sleep(0.05)
        assert cameras, "viser did not take the message as a client's camera"
        camera = cameras[0]
        assert np.allclose(camera.position, position) and np.allclose(camera.look_at, look_at)
        assert camera.fov == 1.0 and camera.aspect == 1.5
        # viser's camera looks down its +z axis (OpenCV): the orientation sent must look at look_at
        forward = vtf.SO3(camera.wxyz).as_matrix()[:, 2]
        assert np.allclose(forward, (look_at - position) / np.linalg.norm(look_at - position), atol=1e-6)
    finally:
        page.close()
        server.stop()


def test_a_browser_sending_while_the_process_exits_is_not_reported_once_connections_are_quiet(caplog):
    import viser
    import websocket

    port = _free_port()
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    server._websock_server._thread_executor.shutdown(wait=False)  # what the interpreter does to it as it exits
    camera = compat.viewer_camera_message(np.ones(3), np.zeros(3), np.array([0.0, 0.0, 1.0]), fov=1.0, aspect=1.5)

    def failures_after_a_message() -> int:
        page = websocket.create_connection(f"ws://127.0.0.1:{port}", timeout=10, suppress_origin=True)
        try:
            page.send_binary(camera)
            deadline = time.monotonic() + 120  # a hang, not a slow machine
            while page.connected and time.monotonic() < deadline:
                try:
                    page.recv()  # until the server closes the failed connection
                except (websocket.WebSocketException, OSError):
                    break
        finally:
            page.close()
        return sum("connection handler failed" in record.getMessage() for record in caplog.records)

    try:
        with caplog.at_level(logging.ERROR, logger="websockets.server"):
            assert failures_after_a_message() == 1, "the failure this guards against: viser's pool is shut down"
            compat.quiet_viewer_connections()
            assert failures_after_a_message() == 1, "nothing more reported"
    finally:
        logging.getLogger("websockets.server").disabled = False
        server.stop()


def test_the_viewers_render_speed_is_read_where_the_render_thread_puts_it():
    from nerfstudio.configs.base_config import LoggingConfig
    from nerfstudio.utils import writer

    writer.setup_local_writer(LoggingConfig(), max_iter=10)  # the render thread writes once this was called
    assert compat.viewer_render_rays_per_second() is None
    writer.put_time(name=writer.EventName.VIS_RAYS_PER_SEC, duration=1000.0, step=0, avg_over_steps=True)
    writer.put_time(name=writer.EventName.VIS_RAYS_PER_SEC, duration=3000.0, step=1, avg_over_steps=True)
    assert compat.viewer_render_rays_per_second() == 2000.0


def test_nerfacto_gives_per_ray_appearance_codes_while_training_and_their_mean_otherwise():
    config = ContinualNGPModelConfig(compile=False, use_appearance_embedding=True, appearance_embed_dim=4)
    model = small_model(config).setup(scene_box=SCENE_BOX, num_train_data=2)
    codes = compat.appearance_codes(model.field)
    assert codes is not None
    with torch.no_grad():
        codes.embedding.weight.copy_(torch.tensor([[3.0, -3.0, 3.0, -3.0], [-3.0, 3.0, -3.0, 3.0]]))
    replacement = Embedding(2, 4)
    compat.set_appearance_codes(model.field, replacement)
    assert compat.appearance_codes(model.field) is replacement
    compat.set_appearance_codes(model.field, codes)
    model.eval()

    def rendered(frame: int) -> torch.Tensor:
        torch.manual_seed(0)
        rays = random_rays(model, 16)
        rays.camera_indices = torch.full_like(rays.camera_indices, frame)
        with torch.no_grad():
            return model(rays)["rgb"]

    assert torch.equal(rendered(0), rendered(1)), "outside training every ray gets the mean code"
    with compat.codes_looked_up_per_ray(model.field):
        assert (rendered(0) - rendered(1)).abs().max() > 1e-4, "each ray gets its frame's code"
        assert not model.proposal_networks.training, "only the field's own flag is set"
    assert not model.field.training


class Pausing(compat.DeferredPauseTrainer):
    """A trainer whose pauses wait for the end of the iteration, counting the state changes it is told of."""

    changes = 0

    def pause_waits(self) -> bool:
        return True

    def training_state_changed(self) -> None:
        self.changes += 1


def test_the_trainer_s_training_state_is_an_attribute_a_property_can_stand_in_for(tmp_path):
    from nerfstudio.viewer.viewer import Viewer

    assert "self.training_state: Literal" in inspect.getsource(Trainer.__init__)
    assert 'while self.training_state == "paused":' in inspect.getsource(Trainer.train)
    assert 'self.trainer.training_state = "paused"' in inspect.getsource(Viewer), "the Pause button assigns it"
    trainer = Pausing(TrainerConfig(output_dir=tmp_path, method_name="pausing", experiment_name="test"))
    assert trainer.training_state == "training" and trainer.changes == 1, "nerfstudio's __init__ went through it"
    trainer.training_state = "paused"
    assert trainer.training_state == "training" and trainer.pause_requested, "the pause waits for the iteration's end"
    trainer.stop_training = False
    assert trainer.pause_now() and trainer.training_state == "paused" and trainer.changes == 3


class Wrapper(DistributedDataParallel):
    """A DDP wrapper without a process group: the wrapped model as `module`."""

    def __init__(self, module: nn.Module) -> None:
        nn.Module.__init__(self)
        self.module = module


def test_the_pipeline_trains_the_model_it_keeps_as_model_and_unwraps_it():
    pipeline = VanillaPipeline.__new__(VanillaPipeline)  # only what the model's keeping needs
    nn.Module.__init__(pipeline)
    model = nn.Linear(2, 1)
    pipeline._model = model  # as VanillaPipeline.__init__ keeps it
    assert compat.model_keys_of_one_process(pipeline, pipeline.state_dict()).keys() == {"_model.weight", "_model.bias"}
    assert compat.model_state_of(pipeline.state_dict()).keys() == model.state_dict().keys(), "the model's own keys"
    compat.wrap_model(pipeline, Wrapper)
    assert pipeline.model is model, "nerfstudio's `model` unwraps the wrapper's module"
    assert isinstance(compat.trained_model(pipeline), Wrapper)
    assert set(pipeline.state_dict()) == {"_model.module.weight", "_model.module.bias"}
    assert compat.model_keys_of_one_process(pipeline, pipeline.state_dict()).keys() == {"_model.weight", "_model.bias"}


def test_a_dataset_keeps_the_cameras_as_parsed_before_its_downscale(tmp_path):
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
    from nerfstudio.data.datasets.base_dataset import InputDataset

    cameras = Cameras(camera_to_worlds=torch.eye(4)[None, :3], fx=10.0, fy=10.0, cx=8.0, cy=6.0, width=16, height=12)
    outputs = DataparserOutputs(image_filenames=[tmp_path / "frame.png"], cameras=cameras, scene_box=SCENE_BOX)
    dataset = InputDataset(outputs, scale_factor=0.5)
    assert int(dataset.cameras.width[0]) == 8, "the dataset's own cameras are downscaled"
    assert int(compat.cameras_as_parsed(dataset).width[0]) == 16


def test_a_viser_server_started_while_held_answers_once_released():
    import viser

    from continual_nerf.bench.browser import viewer_answers

    port = _free_port()
    with compat.viewer_answering_when_ready():
        server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
        assert not viewer_answers(port), "the page answered while the context was building it"
    try:
        assert viewer_answers(port), "the page did not answer once released"
    finally:
        server.stop()


def test_the_viewer_renders_through_the_model_s_get_outputs_for_camera():
    from nerfstudio.viewer.render_state_machine import RenderStateMachine

    assert "self.viewer.get_model().get_outputs_for_camera(camera, obb_box=obb)" in inspect.getsource(
        RenderStateMachine._render_img
    )
    model = small_model(ContinualNGPModelConfig(compile=False)).setup(scene_box=SCENE_BOX, num_train_data=1)
    model.get_outputs_for_camera = mock.Mock(side_effect=[{"rgb": torch.zeros(1)}, RuntimeError("interrupted")])
    seen = []
    compat.watch_viewer_renders(model, lambda camera, completed: seen.append((camera, completed)))
    model.get_outputs_for_camera("camera 1", obb_box=None)
    with pytest.raises(RuntimeError):
        model.get_outputs_for_camera("camera 2", obb_box=None)
    assert seen == [("camera 1", True), ("camera 2", False)]
