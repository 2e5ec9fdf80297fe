"""What `ns-train continual-ngp` shows in a terminal: a short summary first, no warnings about nerfstudio's own code,
and nothing about tiny-cuda-nn on a CPU."""

from __future__ import annotations

import re

import pytest
from helpers import ns_train_command, run_ns_train

from continual_nerf.nerfstudio_compat import NERFSTUDIO_WARNINGS

pytestmark = pytest.mark.slow  # runs ns-train

RAISED_WHILE_NS_TRAIN_IMPORTS = {
    "`torch.jit.script` is deprecated",
    "`torch.cuda.amp.custom_fwd(args...)` is deprecated",
    "`torch.cuda.amp.custom_bwd(args...)` is deprecated",
}
"""Raised while ns-train imports nerfstudio, before it loads any plugin: no plugin can keep them out of its terminal."""


def test_a_cpu_run_starts_with_a_summary_and_shows_no_warning_about_nerfstudio_s_code(tmp_path):
    options = ["--pipeline.datamanager.num-tasks", "3", "--pipeline.datamanager.iterations-per-task", "2"]
    options += ["--pipeline.model.compile", "True"]  # torch.compile logs about CUDA on a CPU machine
    run = run_ns_train(ns_train_command(tmp_path, "terminal", options, ["continual-demo"]))
    assert run.returncode == 0, run.stderr[-3000:]
    lines = run.stdout.splitlines()
    assert lines[0].startswith("continual-ngp: 3 tasks x 2 iterations on cpu; data: continual-demo, ")
    assert (
        lines[1]
        == f"Run folder: {tmp_path / 'unnamed' / 'continual-ngp' / 'terminal'} (config.yml there holds every option)"
    )
    assert "ContinualTrainerConfig(" not in run.stdout, "nerfstudio's dump of every option stays in config.yml"
    assert "tcnn" not in run.stdout, "tiny-cuda-nn cannot run on a CPU: nothing to say about it"
    warned = set(re.findall(r"Warning: (.*?)\. ", run.stderr))
    assert warned <= RAISED_WHILE_NS_TRAIN_IMPORTS, f"warnings the plugin could have kept out: {warned}"
    assert {message for _, message, _ in NERFSTUDIO_WARNINGS} >= RAISED_WHILE_NS_TRAIN_IMPORTS
    assert "No CUDA runtime is found" not in run.stderr
