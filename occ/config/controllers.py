"""The ``controller`` section: the controller plugins and their parameters."""

from __future__ import annotations

from typing import Any

from pydantic import Field, ValidationInfo, field_validator

from occ.config.base import Name, _Model, _resolve_path


class ControllerConfig(_Model):
    """One controller plugin (occ/controllers): what the robot does while RUNNING."""

    plugin: Name = Field(
        description="Registered controller name: `teleop-master`, `teleop-slave`, `keyframe`, "
        "`hold`, or one added by a package (entry point group `occ.controllers`)."
    )
    params: dict[str, Any] = Field(
        {},
        description="The plugin's parameters, validated against its own model at load (see "
        "'Controller plugins' below). A relative path in a key named `file` or ending in "
        "`_file`, at any depth, is taken relative to the configuration file.",
    )

    @field_validator("params", mode="after")
    @classmethod
    def _resolve_files(cls, value: dict[str, Any], info: ValidationInfo) -> dict[str, Any]:
        def walk(v: Any, key: str = "") -> Any:
            if isinstance(v, dict):
                return {k: walk(x, str(k)) for k, x in v.items()}
            if isinstance(v, list | tuple):
                return [walk(x) for x in v]
            if isinstance(v, str) and (key == "file" or key.endswith("_file")) and v:
                return _resolve_path(v, info)
            return v

        return walk(value)  # type: ignore[no-any-return]
