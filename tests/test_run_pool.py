"""The benchmarks' process pool: each run takes its share of the cores unless OMP_NUM_THREADS says otherwise."""

from __future__ import annotations

import os

import torch

from continual_nerf.bench.run_pool import run_pool, threads_per_run


def test_each_of_the_runs_at_once_trains_with_its_share_of_the_cores(monkeypatch):
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    cores = os.cpu_count() or 1
    assert threads_per_run(1) == cores
    assert threads_per_run(2) == max(1, cores // 2)
    assert threads_per_run(cores + 1) == 1, "more runs than cores still get a thread each"
    with run_pool(cores + 1) as pool:
        assert pool.submit(torch.get_num_threads).result() == 1


def test_omp_num_threads_decides_where_it_is_set(monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    assert threads_per_run(1) is None
    # one run alone would take every core
    with run_pool(1) as pool:
        assert pool.submit(torch.get_num_threads).result() == 1
