"""The task budget: iterations or training seconds per task, "Next task now", and what a checkpoint keeps."""

import pytest

from continual_nerf.core.task_budget import TaskBudget, TaskState


def test_an_iteration_budget_is_spent_after_its_iterations_and_a_new_task_starts_afresh():
    budget = TaskBudget(iterations=3)
    for _ in range(2):
        budget.count(0.5)
        assert not budget.spent()
    assert budget.progress_text() == "iteration 2 of 3"
    budget.count(0.5)
    assert budget.spent() and budget.progress_text() == "budget spent"
    budget.start_task()
    assert not budget.spent() and budget.iterations_done == 0 and budget.seconds_done == 0.0
    assert budget.total_seconds == pytest.approx(1.5), "the run's training time is kept across tasks"


def test_a_seconds_budget_counts_training_seconds_not_iterations():
    budget = TaskBudget(iterations=1, seconds=2.0)
    budget.count(1.5)
    assert not budget.spent(), "one iteration, but the seconds budget decides"
    assert budget.progress_text() == "0 s left of 2 s"
    budget.count(0.5)
    assert budget.spent()


def test_next_task_now_spends_the_budget_until_the_next_task_starts():
    budget = TaskBudget(iterations=100)
    budget.request_next_task()
    assert budget.spent() and budget.progress_text() == "ending the task (next task now)"
    budget.start_task()
    assert not budget.spent()


def test_checkpoint_state_round_trips_and_the_options_come_from_the_run():
    budget = TaskBudget(iterations=10)
    for seconds in (0.25, 0.5):
        budget.count(seconds)
    resumed = TaskBudget(iterations=20)
    resumed.load_state(budget.state())
    assert (resumed.iterations_done, resumed.seconds_done, resumed.total_seconds) == (2, 0.75, 0.75)
    assert resumed.iterations == 20
    task = TaskState(current=3)
    restored = TaskState()
    restored.load_state(task.state())
    assert restored.current == 3 and restored.released_tasks == 4


def test_progress_runs_from_0_to_1_over_the_budget():
    budget = TaskBudget(iterations=4)
    assert budget.progress() == 0.0
    budget.count(1.0)
    assert budget.progress() == 0.25
    for _ in range(5):
        budget.count(1.0)
    assert budget.progress() == 1.0, "refining past the budget (a capture still running) stays at 1"
    timed = TaskBudget(iterations=1, seconds=8.0)
    timed.count(2.0)
    assert timed.progress() == 0.25
