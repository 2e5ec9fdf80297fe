"""One validation convention for every config of the plugin: `validate()` runs when the config is set up."""

from __future__ import annotations

from typing import Any

from nerfstudio.configs.base_config import InstantiateConfig


class ValidatedConfig(InstantiateConfig):
    """Mixin for nerfstudio configs: `setup()` first calls `validate()`, which each config class overrides once.

    An override checks the class's own fields, calls `super().validate()` for its parents' fields, and raises
    `ContinualConfigError` with one line naming the option (`--pipeline.datamanager.num-tasks must be ...`).
    Validating at set-up rather than at construction lets tyro and `dataclasses.replace` build any config, and
    checks the values the run will really use.
    """

    def validate(self) -> None:
        """Raise ContinualConfigError, naming the option, for a value this config cannot run with."""

    def setup(self, **kwargs: Any) -> Any:
        self.validate()
        return super().setup(**kwargs)
