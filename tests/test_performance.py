"""The speed levers change no result (compiled = eager, detached positions = same gradients), and memory stays
flat in the number of tasks."""

from __future__ import annotations

import dataclasses
import json
import threading
from pathlib import Path
from typing import Dict

import numpy as np
import pytest
import torch
from helpers import tiny_config
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.scene_box import SceneBox
from PIL import Image

from continual_nerf.bench.memory import MemoryBenchmark, train_recording_memory
from continual_nerf.compilation import CompiledForward, warm_up
from continual_nerf.core.continual_pipeline import ContinualPipeline
from continual_nerf.core.ngp_model import ContinualNGPModel, ContinualNGPModelConfig
from continual_nerf.core.replay_oracle import ReplayOracle
from continual_nerf.dataparsers.continual_demo_dataparser import ContinualDemoDataParserConfig
from continual_nerf.dataparsers.ordered_capture_dataparser import OrderedCaptureDataParserConfig
from continual_nerf.errors import ContinualConfigError
from continual_nerf.recipes import small_model

SMALL_MODEL = small_model(ContinualNGPModelConfig(replay_sample_fraction=1.0))


def build_model(**options) -> ContinualNGPModel:
    torch.manual_seed(0)
    config = dataclasses.replace(SMALL_MODEL, **options)
    return config.setup(scene_box=SceneBox(aabb=torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])), num_train_data=1)


def fixed_rays(num_rays: int = 96) -> RayBundle:
    generator = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(num_rays, 3, generator=generator), dim=-1)
    return RayBundle(
        origins=torch.rand(num_rays, 3, generator=generator) * 0.4 - 0.2,
        directions=directions,
        pixel_area=torch.full((num_rays, 1), 1e-4),
        camera_indices=torch.zeros(num_rays, 1, dtype=torch.long),
    )


def render(model: ContinualNGPModel, training: bool) -> Dict[str, torch.Tensor]:
    """Outputs for the fixed rays and, in training mode, the gradients of their colour sum."""
    model.train(training)
    model.zero_grad(set_to_none=True)
    torch.manual_seed(1)  # the proposal sampler's jitter
    with torch.set_grad_enabled(training):
        outputs = model(fixed_rays())
    results = {name: outputs[name].detach() for name in ("rgb", "accumulation", "depth")}
    if training:
        outputs["rgb"].sum().backward()
        results.update({f"grad {name}": p.grad.clone() for name, p in model.named_parameters() if p.grad is not None})
    return results


def test_compiled_and_eager_models_give_the_same_outputs():
    eager = build_model(compile=False)
    compiled = build_model(compile=True)
    assert isinstance(compiled.field.mlp_head.forward, CompiledForward)
    assert compiled.state_dict().keys() == eager.state_dict().keys(), "compiling changed the checkpoint's keys"
    compiled.load_state_dict(eager.state_dict())
    for training in (True, False):
        expected, actual = render(eager, training), render(compiled, training)
        assert not CompiledForward.failed, (
            "torch.compile failed on this machine (see the notice above); a C++ compiler (gcc) is needed for CPU"
        )
        assert expected.keys() == actual.keys()
        assert any(name.startswith("grad") for name in actual) == training
        for name in expected:
            torch.testing.assert_close(actual[name], expected[name], rtol=1e-4, atol=1e-5, msg=f"{name} differs")
    oracle = ReplayOracle()
    oracle.update(compiled)  # a second compiled model, built from the config, loading the state dict
    torch.testing.assert_close(oracle.render(fixed_rays()), expected["rgb"], rtol=1e-4, atol=1e-5)
    from_viewer_thread = {}  # the viewer renders from its own thread, where the model runs eager
    viewer = threading.Thread(target=lambda: from_viewer_thread.update(render(compiled, training=False)))
    viewer.start()
    viewer.join()
    torch.testing.assert_close(from_viewer_thread["rgb"], expected["rgb"], rtol=1e-4, atol=1e-5)


def test_detached_sample_positions_leave_every_parameter_gradient_unchanged():
    expected = render(build_model(compile=False, detach_sample_positions=False), training=True)
    actual = render(build_model(compile=False, detach_sample_positions=True), training=True)
    assert expected.keys() == actual.keys()
    for name in expected:
        torch.testing.assert_close(actual[name], expected[name], rtol=0, atol=0, msg=f"{name} differs")


NUM_TASKS, FRAMES_PER_TASK, WIDTH, HEIGHT = 10, 9, 384, 288  # pixels well above the allocator's noise
"""Each task trains on 8 frames of 192x144 (2.7 MB of float pixels) and tests on 1."""


def write_capture(folder: Path) -> Path:
    """A transforms.json capture of a camera sliding sideways, with noise images (fast to write)."""
    rng = np.random.default_rng(0)
    frames = []
    for i in range(NUM_TASKS * FRAMES_PER_TASK):
        name = f"images/frame_{i:05d}.png"
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(rng.integers(0, 255, (HEIGHT, WIDTH, 3), dtype=np.uint8)).save(folder / name)
        pose = np.eye(4)
        pose[:3, 3] = [0.05 * i, 0.0, 0.0]
        frames.append({"file_path": name, "transform_matrix": pose.tolist()})
    intrinsics = {"fl_x": 150.0, "fl_y": 150.0, "cx": WIDTH / 2, "cy": HEIGHT / 2, "w": WIDTH, "h": HEIGHT}
    (folder / "transforms.json").write_text(json.dumps({**intrinsics, "frames": frames}))
    return folder


@pytest.mark.slow
def test_memory_stays_flat_over_many_tasks(tmp_path, monkeypatch):
    # no evaluation: rendering every seen test frame after every task would dominate the run and measures nothing here
    monkeypatch.setattr(ContinualPipeline, "evaluate_seen_tasks", lambda self, step, output_dir: None)
    parser = OrderedCaptureDataParserConfig(data=write_capture(tmp_path / "capture"))
    config = tiny_config(tmp_path / "outputs", parser, num_tasks=NUM_TASKS, iterations_per_task=1)
    config.pipeline.datamanager.test_interval = FRAMES_PER_TASK
    records = train_recording_memory(config)
    assert len(records) == NUM_TASKS

    task_pixel_bytes = (FRAMES_PER_TASK - 1) * WIDTH * HEIGHT * 3 * 4
    tasks_later = NUM_TASKS - 2
    after_2, after_last = records[1], records[-1]
    tensor_growth = after_last.live_tensor_bytes - after_2.live_tensor_bytes
    resident_growth = after_last.resident_bytes - after_2.resident_bytes
    print(
        f"\nfrom task 2 to task {NUM_TASKS}: live tensors {tensor_growth / 2**20:+.2f} MiB, resident {resident_growth / 2**20:+.1f} "
        f"MiB; keeping each closed task's pixels would add {tasks_later * task_pixel_bytes / 2**20:.1f} MiB"
    )
    # keeping the pixels of closed tasks, or one more oracle copy per task, would grow both by far more
    assert tensor_growth < task_pixel_bytes / 2
    assert resident_growth < tasks_later * task_pixel_bytes / 2


def test_the_replay_oracle_renders_with_a_fraction_of_the_samples():
    model = build_model(compile=False, replay_sample_fraction=0.5)
    oracle = ReplayOracle()
    oracle.update(model)
    assert oracle.model.proposal_sampler.num_proposal_samples_per_ray == (16,)
    assert oracle.model.proposal_sampler.num_nerf_samples_per_ray == 8
    assert model.proposal_sampler.num_nerf_samples_per_ray == 16, "the model itself keeps its samples"
    with pytest.raises(ContinualConfigError, match="replay-sample-fraction must be positive"):
        build_model(compile=False, replay_sample_fraction=0.0)


@pytest.mark.slow
def test_warm_up_compiles_at_set_up_and_leaves_the_model_as_it_was():
    from torch._dynamo.utils import counters

    model = build_model(compile=True)
    sampler = model.proposal_sampler
    before = {name: p.detach().clone() for name, p in model.named_parameters()}
    counters_before, rng_before = (sampler._step, sampler._steps_since_update), torch.get_rng_state()
    warm_up(model, num_rays=1024)
    assert not CompiledForward.failed
    assert all(torch.equal(before[name], p) for name, p in model.named_parameters()), "warm-up changed weights"
    assert all(p.grad is None for p in model.parameters()), "warm-up left gradients for the optimizer"
    assert (sampler._step, sampler._steps_since_update) == counters_before
    assert torch.equal(torch.get_rng_state(), rng_before), "warm-up drew from the run's random numbers"
    oracle = ReplayOracle(rays_per_batch=1024)
    oracle.update(model)
    compiled_frames = counters["frames"]["ok"]
    model.train()
    model(fixed_rays(1024))["rgb"].sum().backward()  # a training step of the paper's batch
    model.eval()
    with torch.no_grad():
        model(fixed_rays(4096))  # an evaluation chunk
    oracle.render(fixed_rays(900))  # a replay batch of another size
    assert counters["frames"]["ok"] == compiled_frames, "something compiled after set-up, inside the timed steps"


@pytest.mark.parametrize("where", ["at torch.compile", "at the first call"])
def test_compilation_failure_falls_back_to_eager_with_one_line(monkeypatch, capsys, where):
    monkeypatch.setattr(CompiledForward, "failed", False)  # the class-wide flag, restored after the test

    def failing_compile(function, **options):
        if where == "at torch.compile":
            raise RuntimeError("Compiler: cc not found\nmore detail")

        def first_call(*args, **kwargs):
            raise RuntimeError("InductorError: cc not found\nmore detail")

        return first_call

    monkeypatch.setattr(torch, "compile", failing_compile)
    expected = render(build_model(compile=False), training=False)
    actual = render(build_model(compile=True), training=False)
    assert CompiledForward.failed
    notices = [line for line in capsys.readouterr().out.splitlines() if "torch.compile unavailable" in line]
    assert len(notices) == 1 and "cc not found" in notices[0] and "running the model eager" in notices[0]
    for name in expected:
        torch.testing.assert_close(actual[name], expected[name], rtol=0, atol=0, msg=f"{name} differs")


def test_the_memory_benchmark_trains_on_the_scene_it_is_given(tmp_path):
    benchmark = MemoryBenchmark(scene="long-street", num_tasks=40, data=tmp_path / "demo", output_dir=tmp_path / "out")
    config = benchmark.trainer_config()
    demo = config.pipeline.datamanager.dataparser
    assert isinstance(demo, ContinualDemoDataParserConfig)
    assert (demo.scene, demo.num_frames, demo.data) == ("long-street", None, tmp_path / "demo")
    assert config.pipeline.datamanager.num_tasks == 40
