"""MkDocs hook: the reference pages, made at build time from the code, never written to disk.

One page per `recon` command (its usage line, docstring and options: flag, type, default, help,
read from the click command, whose defaults and help come from the config dataclasses through
`recon.options.config_option`), one page per training method (its config dataclass's fields and
its presets, read from `recon.models.registry`) and an index of both. `on_config` fills the nav's
"Reference" entry with them, so a new command or method gets its page and its nav entry with no
edit here.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import re

import click

REFERENCE = "Reference"  # the nav entry the hook fills


def commands() -> dict[str, click.Command]:
    """{name: click command} of `recon`, in the order `recon --help` lists them."""
    from recon.cli.main import cli

    ctx = click.Context(cli, info_name="recon")
    return {name: cli.get_command(ctx, name) for name in cli.list_commands(ctx)}


def method_specs() -> dict:
    """{method name: MethodSpec} of every registered training method."""
    from recon.models.registry import METHOD_NAMES, method_spec

    return {name: method_spec(name) for name in METHOD_NAMES}


def escape(text: str) -> str:
    """Markdown-safe prose: `<`, `|`, `*`, `_` and `[` outside code spans are escaped, so help
    text such as `auto | cpu | cuda` or `images_<K>` stays one table cell and reads as written."""
    parts = re.split(r"(`[^`]*`)", text)
    for i in range(0, len(parts), 2):
        parts[i] = re.sub(r"([|*_\[\\])", r"\\\1", parts[i]).replace("<", "&lt;")
    return "".join(parts)


def cell(text: str) -> str:
    return escape(" ".join(text.split()))


def code(value, python: bool = False) -> str:
    """`value` as inline code: as Python writes it (`python`, a config field's value) or as
    typed on the command line."""
    text = repr(value) if python else str(value)
    if text == "":
        return "`''`"
    return f"`{text}`" if "|" not in text else f"<code>{text.replace('|', '&#124;')}</code>"


def _bounds(t: click.IntRange | click.FloatRange) -> str:
    low = None if t.min is None else f"{t.min} {'<' if t.min_open else '≤'} x"
    high = None if t.max is None else f"x {'<' if t.max_open else '≤'} {t.max}"
    if low and high:
        return low + high[1:]
    return low or high or ""


def option_type(param: click.Parameter) -> str:
    """The kind of value a parameter takes, in words: flag, a choice, a number range, text."""
    if getattr(param, "is_flag", False):
        return "flag"
    t = param.type
    if isinstance(t, click.Choice):
        kind = " \\| ".join(code(c) for c in t.choices)
    elif isinstance(t, (click.IntRange, click.FloatRange)):
        kind = f"{'integer' if isinstance(t, click.IntRange) else 'number'}, {_bounds(t)}"
    elif isinstance(t, click.Path):
        kind = "directory" if not t.file_okay else "file" if not t.dir_okay else "path"
    else:
        kind = {"integer": "integer", "float": "number", "path": "path"}.get(t.name, "text")
    return kind + (", repeatable" if getattr(param, "multiple", False) else "")


def option_default(param: click.Parameter) -> str:
    """The value a command gets when the flag is not given, as `--help` would show it."""
    if param.required:
        return "required"
    default = param.default
    if getattr(param, "is_flag", False):
        if param.secondary_opts:
            return code(param.opts[-1] if default else param.secondary_opts[-1])
        return "off"
    if default is None or default == "" or default is getattr(click.core, "UNSET", None):
        return "–"
    return code(default)


def option_name(param: click.Parameter) -> str:
    names = ", ".join(f"`{o}`" for o in param.opts)
    if param.secondary_opts:
        names += " / " + ", ".join(f"`{o}`" for o in param.secondary_opts)
    return names


def command_page(name: str, command: click.Command) -> str:
    """The reference page of `recon NAME`."""
    ctx = click.Context(command, info_name=f"recon {name}")
    usage = " ".join([f"recon {name}", *command.collect_usage_pieces(ctx)])
    lines = [f"# recon {name}", "", "```", usage, "```", "", help_text(command.help), ""]
    arguments = [p for p in command.params if isinstance(p, click.Argument)]
    if arguments:
        lines += ["## Arguments", "", "| argument | type | required |", "|---|---|---|"]
        lines += [
            f"| `{p.make_metavar(ctx)}` | {option_type(p)} | {'yes' if p.required else 'no'} |"
            for p in arguments
        ]
        lines.append("")
    lines += ["## Options", "", "| option | type | default | help |", "|---|---|---|---|"]
    for p in command.params:
        if isinstance(p, click.Option):
            lines.append(
                f"| {option_name(p)} | {option_type(p)} | {option_default(p)} | {cell(p.help or '')} |"
            )
    lines += ["| `-h`, `--help` | flag | off | Show the command's help and exit. |", ""]
    return "\n".join(lines)


def help_text(doc: str | None) -> str:
    """A command's docstring as markdown: prose paragraphs escaped, click's `\\b` (keep as
    written) paragraphs as code blocks."""
    out = []
    for para in inspect.cleandoc(doc or "").split("\n\n"):
        if para.startswith("\b"):
            out.append("```\n" + para[1:].strip("\n") + "\n```")
        else:
            out.append(escape(" ".join(para.split())))
    return "\n\n".join(out)


def _doc_paragraph(doc: str | None) -> str:
    """The first paragraph of a docstring, on one line."""
    return " ".join((doc or "").strip().split("\n\n")[0].split())


def method_page(name: str, spec) -> str:
    """The reference page of `recon train --method NAME`: its options and presets."""
    from recon.train.config import TrainConfig

    cls = spec.config_cls
    module = importlib.import_module(cls.__module__)
    preset_help = {f.name: f for f in dataclasses.fields(TrainConfig)}["preset"].metadata["help"]
    lines = [f"# --method {name}", "", escape(_doc_paragraph(module.__doc__)), ""]
    if cls.__doc__ and not cls.__doc__.startswith(f"{cls.__name__}("):  # not dataclass's own
        lines += [escape(" ".join(cls.__doc__.split())), ""]
    lines += [
        (
            f"Set any option with `recon train --method {name} --set KEY=VALUE`; "
            f"`recon train --method {name} --list-options` prints this list. "
            f"The defaults below are `{cls.__name__}`'s; a preset (`--preset`: "
            f"{escape(preset_help)}) changes some of them."
        ),
        "",
        "## Options",
        "",
        "| option | type | default | help |",
        "|---|---|---|---|",
    ]
    for f in dataclasses.fields(cls):
        kind = f.metadata.get("choices")
        kind = " \\| ".join(code(c, True) for c in kind) if kind else f"`{f.type}`"
        help_ = cell(f.metadata.get("help", ""))
        lines.append(f"| `{f.name}` | {kind} | {code(f.default, True)} | {help_} |")
    lines += ["", "## Presets", ""]
    for preset, overrides in spec.presets.items():
        lines.append(f"### {preset}")
        lines.append("")
        if not overrides:
            lines += ["The defaults above, unchanged.", ""]
            continue
        lines += ["| option | value |", "|---|---|"]
        lines += [f"| `{k}` | {code(v, True)} |" for k, v in overrides.items()]
        lines.append("")
    return "\n".join(lines)


def index_page(cmds: dict[str, click.Command], specs: dict) -> str:
    lines = [
        "# Reference",
        "",
        (
            "Made from the code at every docs build: each command's options, defaults and help "
            "come from its click command, which takes them from the config dataclasses, so "
            "these pages, `recon CMD --help` and `recon train --list-options` always agree."
        ),
        "",
        "## Commands",
        "",
        "| command | what it does |",
        "|---|---|",
    ]
    lines += [
        f"| [recon {n}]({n}.md) | {cell(c.get_short_help_str(300))} |" for n, c in cmds.items()
    ]
    lines += ["", "## Training methods", "", "| method | config |", "|---|---|"]
    lines += [f"| [{n}](methods/{n}.md) | `{s.config_cls.__name__}` |" for n, s in specs.items()]
    return "\n".join(lines) + "\n"


def pages() -> dict[str, str]:
    """{path under docs/: markdown} of every generated page."""
    cmds, specs = commands(), method_specs()
    out = {"reference/index.md": index_page(cmds, specs)}
    out.update({f"reference/{n}.md": command_page(n, c) for n, c in cmds.items()})
    out.update({f"reference/methods/{n}.md": method_page(n, s) for n, s in specs.items()})
    return out


def nav() -> list:
    """The "Reference" nav section: the index, the commands, the methods."""
    from recon.cli.main import COMMANDS
    from recon.models.registry import METHOD_NAMES

    return [
        {"Overview": "reference/index.md"},
        *({f"recon {n}": f"reference/{n}.md"} for n in COMMANDS),
        {"Methods": [{n: f"reference/methods/{n}.md"} for n in METHOD_NAMES]},
    ]


def on_config(config):
    for i, item in enumerate(config["nav"] or []):
        if isinstance(item, dict) and REFERENCE in item:
            config["nav"][i] = {REFERENCE: nav()}
    return config


def on_files(files, config):
    from mkdocs.structure.files import File

    for uri, text in pages().items():
        files.append(File.generated(config, uri, content=text))
    return files
