"""Configs are flat frozen dataclasses whose fields carry their default and their help as data
(`opt`); command-line options are made from those fields (`config_option`), so every default
and every help text has one source, and `--help`, `--list-options` and `run.json` agree.

    @dataclass(frozen=True)
    class MeshConfig:
        resolution: int = opt(256, "samples or voxels along the box's longest side")

    @config_option(MeshConfig, "resolution")   # --resolution, default 256, that help
"""

from __future__ import annotations

import dataclasses
from typing import Any


def opt(default: Any, help: str, **extra: Any) -> Any:
    """A config field with its help text. extra: `choices=(...)` for a value from a fixed set,
    `flag="--name"` when the command-line flag is not the field name with dashes."""
    return dataclasses.field(default=default, metadata={"help": help, **extra})


def config_field(cls, name: str) -> dataclasses.Field:
    for f in dataclasses.fields(cls):
        if f.name == name:
            return f
    raise KeyError(f"{cls.__name__} has no field {name!r}")


def field_help(cls) -> dict[str, str]:
    """{field name: help} of a config dataclass (empty for a field without help)."""
    return {f.name: f.metadata.get("help", "") for f in dataclasses.fields(cls)}


def config_option(cls, name: str, *decls: str, **overrides: Any):
    """A click option for the field `name` of config `cls`: its flag (`--field-name`, or the
    field's `flag`, or `decls`), default, help, and choices or type come from the field; the
    command receives the value under the field's name. `overrides` go to `click.option`."""
    import click

    f = config_field(cls, name)
    flag = f.metadata.get("flag", "--" + name.replace("_", "-"))
    kwargs: dict[str, Any] = {
        "default": f.default,
        "show_default": True,
        "help": _sentence(f.metadata.get("help", "")),
    }
    if "choices" in f.metadata:
        kwargs["type"] = click.Choice(list(f.metadata["choices"]))
    if isinstance(f.default, bool) and not decls:
        decls = (f"{flag}/--no-{flag[2:]}",)
    kwargs.update(overrides)
    return click.option(*(decls or (flag,)), name, **kwargs)


def from_options(cls, values: dict[str, Any], **more: Any):
    """The config `cls` from a command's keyword arguments: the fields present in `values`
    (keys that are no field of `cls` are ignored), then `more`."""
    names = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in values.items() if k in names}, **more)


def on_off_auto(value: str, name: str, auto: bool) -> bool:
    """An on | off | auto option: True for on, False for off, `auto` for auto (what the scene
    calls for); anything else is a ValueError naming the option."""
    if value not in ("on", "off", "auto"):
        raise ValueError(f"{name} must be on, off or auto, got {value!r}")
    return value == "on" or (value == "auto" and auto)


def _sentence(text: str) -> str:
    return text[:1].upper() + text[1:]
