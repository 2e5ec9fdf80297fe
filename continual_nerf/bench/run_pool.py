"""The process pool benchmarks train their runs in: each run in a fresh process of its own, with its share of the cores."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Optional

import torch


def threads_per_run(jobs: int) -> Optional[int]:
    """Threads each of `jobs` runs at once trains with: cores / jobs, or None where OMP_NUM_THREADS already says."""
    if os.environ.get("OMP_NUM_THREADS"):
        return None
    return max(1, (os.cpu_count() or 1) // jobs)


def _take_threads(threads: Optional[int]) -> None:
    if threads is not None:
        torch.set_num_threads(threads)


def run_pool(jobs: int) -> ProcessPoolExecutor:
    """A pool of `jobs` spawned processes, one per run (its memory is its own). Each takes cores / jobs threads, since
    runs that each take every core's threads oversubscribe them and train several times slower."""
    return ProcessPoolExecutor(
        jobs,
        mp_context=multiprocessing.get_context("spawn"),
        max_tasks_per_child=1,
        initializer=_take_threads,
        initargs=(threads_per_run(jobs),),
    )
