"""The viewer listens on 127.0.0.1 by default: while training, and with the command the README gives for a finished
run (nerfstudio's own default is 0.0.0.0)."""

from __future__ import annotations

import re
import shlex
from importlib.metadata import entry_points
from pathlib import Path

import pytest
import tyro
import yaml
from nerfstudio.scripts.viewer.run_viewer import RunViewer

README = Path(__file__).parents[1] / "README.md"

METHODS = sorted(
    (entry.name, entry)
    for entry in entry_points(group="nerfstudio.method_configs")
    if entry.value.startswith("continual")
)
"""The methods this plugin registers with nerfstudio."""


@pytest.mark.parametrize("entry", [entry for _, entry in METHODS], ids=[name for name, _ in METHODS])
def test_a_registered_method_s_saved_config_binds_localhost(entry):
    config = entry.load().config
    saved = yaml.load(yaml.dump(config), Loader=yaml.Loader)  # config.yml, as ns-train writes and ns-viewer reads it
    assert saved.viewer.websocket_host == "127.0.0.1"


def test_the_readme_s_command_for_a_finished_run_binds_localhost():
    commands = re.findall(r"^ns-viewer .*$", README.read_text(), flags=re.MULTILINE)
    assert commands, "the README names the command that opens a finished run"
    for command in commands:
        viewer = tyro.cli(RunViewer, args=shlex.split(command)[1:])
        assert viewer.viewer.as_viewer_config().websocket_host == "127.0.0.1", command
