"""Bad options end the run before training with one line that names the option."""

import dataclasses
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import DEMO_CACHE, demo_parser, tiny_config

BAD_OPTIONS = [
    ({"num_tasks": 0}, {}, "--pipeline.datamanager.num-tasks must be at least 1, got 0"),
    ({"num_tasks": 9}, {}, "--pipeline.datamanager.num-tasks 9 is too large for 12 frames"),
    ({"iterations_per_task": 0}, {}, "--pipeline.datamanager.iterations-per-task must be at least 1, got 0"),
    ({"seconds_per_task": 0.0}, {}, "--pipeline.datamanager.seconds-per-task must be positive, got 0.0"),
    ({"test_interval": 1}, {}, "--pipeline.datamanager.test-interval must be at least 2"),
    ({}, {"num_frames": 0}, "continual-demo --num-frames must be at least 1, got 0"),
    ({}, {"width": 0}, "continual-demo --width must be at least 1, got 0"),
]


@pytest.mark.parametrize("datamanager_options,parser_options,message", BAD_OPTIONS)
def test_bad_option_is_a_one_line_exit(run_dir, datamanager_options, parser_options, message):
    config = tiny_config(run_dir, dataclasses.replace(demo_parser(num_frames=12), **parser_options))
    config.pipeline.datamanager = dataclasses.replace(config.pipeline.datamanager, **datamanager_options)
    trainer = config.setup(local_rank=0, world_size=1)
    with pytest.raises(SystemExit) as exit_info:
        trainer.setup()
    line = str(exit_info.value.code)
    assert line.startswith(f"continual-ngp: error: {message}")
    assert "\n" not in line


def test_ns_train_prints_one_line_and_no_traceback(tmp_path: Path):
    ns_train = Path(sys.executable).with_name("ns-train")
    result = subprocess.run(
        [str(ns_train), "continual-ngp", "--machine.device-type", "cpu", "--vis", "tensorboard",
         "--output-dir", str(tmp_path), "--pipeline.datamanager.num-tasks", "0",
         "continual-demo", "--data", str(DEMO_CACHE), "--num-frames", "12", "--width", "16", "--height", "12"],
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode != 0
    assert "Traceback" not in result.stderr + result.stdout
    assert result.stderr.strip().splitlines()[-1] == (
        "continual-ngp: error: --pipeline.datamanager.num-tasks must be at least 1, got 0"
    )
