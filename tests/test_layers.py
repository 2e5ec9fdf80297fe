"""The package's layers (CONTRIBUTING.md, Layout), read from the sources with `ast`: which parts import which, and
nerfstudio's private attributes touched in nerfstudio_compat.py alone."""

from __future__ import annotations

import ast
import importlib.util
import re
from pathlib import Path
from typing import Dict, Iterator, Set, Tuple

import pytest

from continual_nerf.nerfstudio_compat import TRAINER_OVERRIDES

PACKAGE = Path(__file__).parent.parent / "continual_nerf"

BASE = {"atomic_files", "errors", "interrupts", "metadata_keys", "run_lock", "untrusted_files", "validated_config"}
"""The lowest layer: what every other part may use, itself using nothing of the package above it."""
MAY_NOT_IMPORT: Dict[str, Set[str]] = {
    "core": {"viewer", "streaming", "dataparsers", "baselines", "experiments", "bench", "method_configs", "recipes"},
    "dataparsers": {"core", "streaming", "viewer", "baselines", "experiments", "bench", "method_configs", "recipes"},
    "streaming": {"viewer", "baselines", "experiments", "bench", "method_configs", "recipes"},
    "baselines": {"viewer", "streaming", "experiments", "bench", "method_configs", "recipes"},
    "viewer": {"streaming", "baselines", "experiments", "bench", "recipes"},
}
"""Parts (subpackages, or top-level modules) that a part never imports."""
NERFSTUDIO_EXTENSION_POINTS = {"_generate_dataparser_outputs"}
"""Private names nerfstudio asks a plugin to define: DataParser's one abstract method."""


def modules() -> Iterator[Tuple[str, ast.Module]]:
    """Every module of the package as (part, syntax tree); a part is a subpackage or a top-level module."""
    for path in sorted(PACKAGE.rglob("*.py")):
        relative = path.relative_to(PACKAGE)
        yield relative.parts[0].removesuffix(".py"), ast.parse(path.read_text(), filename=str(path))


def imported_parts(tree: ast.Module) -> Set[str]:
    """The package's parts a module imports, at the top, inside functions or for type checking alike."""
    names = [node.module or "" for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    names += [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    return {name.split(".")[1] for name in names if name.startswith("continual_nerf.")}


def parts_importing() -> Dict[str, Set[str]]:
    imports: Dict[str, Set[str]] = {}
    for part, tree in modules():
        imports.setdefault(part, set()).update(imported_parts(tree) - {part})
    return imports


@pytest.mark.parametrize("part", sorted(MAY_NOT_IMPORT))
def test_a_part_imports_nothing_from_the_layers_above_it(part):
    assert parts_importing()[part] & MAY_NOT_IMPORT[part] == set()


def test_the_lowest_layer_and_nerfstudio_compat_import_only_the_lowest_layer():
    imports = parts_importing()
    for part in BASE | {"nerfstudio_compat"}:
        assert imports.get(part, set()) <= BASE, part


def nerfstudio_private_names() -> Set[str]:
    """Private attributes and methods nerfstudio's classes define (`self._name =`, `def _name(`)."""
    spec = importlib.util.find_spec("nerfstudio")
    assert spec is not None and spec.submodule_search_locations
    names: Set[str] = set()
    for path in Path(next(iter(spec.submodule_search_locations))).rglob("*.py"):
        source = path.read_text(errors="replace")
        names.update(re.findall(r"self\.(_[A-Za-z]\w*)\s*[:=]", source), re.findall(r"def (_[A-Za-z]\w*)\(", source))
    return names


def test_nerfstudio_internals_are_touched_in_nerfstudio_compat_only():
    private = nerfstudio_private_names() - set(TRAINER_OVERRIDES) - NERFSTUDIO_EXTENSION_POINTS
    touches = set()
    for part, tree in modules():
        if part == "nerfstudio_compat":
            continue
        for node in ast.walk(tree):
            name = node.attr if isinstance(node, ast.Attribute) else getattr(node, "name", None)
            if isinstance(node, (ast.Attribute, ast.FunctionDef)) and name in private:
                touches.add(f"{part}: {name}")
            if isinstance(node, ast.FunctionDef) and node.name == "training_state":  # nerfstudio's attribute
                touches.add(f"{part}: training_state")
    assert touches == set()
