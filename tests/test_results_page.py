"""docs/results.md regenerated section by section: the sections asked for are replaced, the others kept word for word."""

from __future__ import annotations

from pathlib import Path
from typing import List

import pytest

from continual_nerf.bench import quality, results
from continual_nerf.bench.results import HEADER, SECTION_TITLES, SECTIONS, Results


def section(name: str, body: str) -> List[str]:
    return [f"## {SECTION_TITLES[name]}", "", body, ""]


def page(tmp_path: Path, body: str) -> Path:
    """A results page whose every section holds `body` (two for the real-capture flaws, as the generator writes)."""
    lines = ["# Results", "", "an older header", ""]
    for name in SECTIONS:
        lines += section(name, f"{name} {body}")
        if name == "real-capture":
            lines += [f"## {SECTION_TITLES[name]}: street", "", f"{name} street {body}", ""]
    path = tmp_path / "results.md"
    path.write_text("\n".join(lines))
    return path


def fresh(name: str):
    return lambda _self: section(name, f"{name} new")


class FinishedQuality:
    def measure(self) -> dict:
        return {"room": {}}


@pytest.fixture
def no_training(monkeypatch: pytest.MonkeyPatch) -> None:
    """Each section's builder returns fixed lines instead of training its benchmark; the quality grid's finished runs
    give the README a fixed table."""
    for name, method in zip(
        SECTIONS, ("quality", "default_budget", "distillation", "depth", "sweep", "capture", "sessions")
    ):
        monkeypatch.setattr(Results, f"{method}_lines", fresh(name))
    monkeypatch.setattr(Results, "quality", lambda _self: FinishedQuality())
    monkeypatch.setattr(results, "summary_table", lambda grid: f"table of {sorted(grid)}")


def readme(tmp_path: Path) -> Path:
    path = tmp_path / "README.md"
    path.write_text("intro\n<!-- results: begin -->\nold table\n<!-- results: end -->\nend\n")
    return path


def test_the_sections_asked_for_are_replaced_and_the_others_kept_word_for_word(tmp_path: Path, no_training) -> None:
    docs = page(tmp_path, "old")
    Results(docs=docs, readme=readme(tmp_path), sections=("depth", "sessions")).main()
    assert "old table" in (tmp_path / "README.md").read_text(), "the README's table comes with the quality section"
    text = docs.read_text()
    assert text.startswith("\n".join(HEADER))
    assert "an older header" not in text
    for name in ("quality", "sweep", "real-capture"):
        assert f"{name} old" in text and f"{name} new" not in text
    assert "real-capture street old" in text
    for name in ("depth", "sessions"):
        assert f"{name} new" in text and f"{name} old" not in text
    order = [text.index(f"## {SECTION_TITLES[name]}") for name in SECTIONS]
    assert order == sorted(order)


def test_every_section_regenerated_needs_no_page(tmp_path: Path, no_training) -> None:
    docs = tmp_path / "results.md"
    Results(docs=docs, readme=readme(tmp_path)).main()
    assert all(f"{name} new" in docs.read_text() for name in SECTIONS)
    assert "\ntable of ['room']\n" in (tmp_path / "README.md").read_text()


def test_a_section_to_keep_that_the_page_lacks_is_a_one_line_error(tmp_path: Path, no_training) -> None:
    docs = page(tmp_path, "old")
    docs.write_text(docs.read_text().replace(f"## {SECTION_TITLES['sweep']}", "## Something else"))
    with pytest.raises(SystemExit, match=r"results\.md has no section '## Long captures.*--sections \.\.\. sweep"):
        Results(docs=docs, sections=("depth",)).main()
    with pytest.raises(SystemExit, match="does not exist"):
        Results(docs=tmp_path / "missing.md", sections=("depth",)).main()


def test_an_unknown_section_is_refused_before_anything_trains(tmp_path: Path, no_training) -> None:
    docs = page(tmp_path, "old")
    with pytest.raises(SystemExit, match="sections"):
        Results(docs=docs, sections=("depth", "colour")).main()
    assert "depth old" in docs.read_text()


def test_provenance_names_the_commits_runs_were_trained_at_once_each() -> None:
    line = Results(jobs=2).provenance(["b", "a", "b"])
    assert "from runs trained at `a`, `b`;" in line
    assert "2 run(s) at once" in line
    assert "runs trained" not in Results().provenance([])
    assert results.grid_commits([]) == []


def test_every_grid_section_names_recipes_the_quality_benchmark_knows() -> None:
    sections = {
        "quality": results.QUALITY_RECIPES,
        "default-budget": results.DEFAULT_BUDGET_RECIPES,
        "distillation-weight": results.DISTILLATION_RECIPES,
        "depth": results.DEPTH_RECIPES,
        "sweep": results.SWEEP_RECIPES,
    }
    for name, recipes in sections.items():
        unknown = set(recipes) - set(quality.RECIPES)
        assert not unknown, f"section {name}: {unknown} are not the quality benchmark's recipes"
    # the task-count sweep prices replay by distillation against keeping every pixel at every task count
    assert {"continual-ngp", "every pixel kept"} <= set(results.SWEEP_RECIPES)


@pytest.mark.parametrize("section", ["depth", "sweep"])
def test_a_section_names_its_commit_before_its_plot_changes_the_checkout(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, section: str
) -> None:
    calls: List[str] = []
    monkeypatch.setattr(Results, "quality", lambda _self, *args: FinishedQuality())
    monkeypatch.setattr(quality, "plot_quality", lambda *args: calls.append("plot"))
    monkeypatch.setattr(Results, "provenance", lambda _self, commits: calls.append("provenance") or "provenance")
    monkeypatch.setattr(results, "quality_section", lambda *args: [])
    getattr(Results(docs=tmp_path / "results.md"), f"{section}_lines")()
    assert calls == ["provenance", "plot"], "a plot written first would make every section's commit read -dirty"
