"""Shared fixtures; shared helper functions live in tests/helpers.py."""

from __future__ import annotations

import signal
from pathlib import Path

import pytest
import torch


def pytest_configure(config: pytest.Config) -> None:
    """Tests press Ctrl-C on their runs: a suite started in the background (`... &`, where a shell without job control
    starts it ignoring SIGINT) would hand that on to every run it starts, which would then ignore the Ctrl-C."""
    if signal.getsignal(signal.SIGINT) == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture
def single_thread():
    """In-process training on one thread, as the training subprocesses run (SUBPROCESS_ENV)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def run_dir(tmp_path: Path) -> Path:
    return tmp_path / "outputs"
