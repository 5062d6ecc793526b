"""`recon` entry point: a click group whose commands live one per module."""

from __future__ import annotations

import ast
import importlib
import importlib.util
import sys

import click

import recon
from recon.cli.common import fail

# command name -> (module under recon.cli, attribute): each command's module (and what it
# imports: torch, trimesh, pycolmap) is loaded only when that command runs or help lists it.
COMMANDS = {
    "run": ("run_cmd", "command"),
    "sfm": ("sfm_cmd", "sfm"),
    "mvs": ("mvs_cmd", "command"),
    "train": ("train_cmd", "command"),
    "render": ("render_cmd", "command"),
    "mesh": ("mesh_cmd", "command"),
    "eval": ("eval_cmd", "command"),
    "export": ("export_cmd", "command"),
    "status": ("status_cmd", "status"),
    "view": ("view_cmd", "command"),
}


def command_short_help(name: str, limit: int = 45) -> str:
    """The short help click would show for command `name` (the first sentence of its function's
    docstring, cut to `limit`), read from its module's source without importing the module."""
    module, attr = COMMANDS[name]
    origin = importlib.util.find_spec(f"recon.cli.{module}").origin
    tree = ast.parse(open(origin, encoding="utf-8").read())  # noqa: SIM115 (read at once)
    for node in tree.body:
        if isinstance(node, ast.FunctionDef) and node.name == attr:
            doc = ast.get_docstring(node) or ""
            return click.Command(name, help=doc).get_short_help_str(limit)
    return ""


class ReconGroup(click.Group):
    """Loads each subcommand on demand (`COMMANDS`) and turns every exception into one clear
    line on stderr and a non-zero exit."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        """`recon --help` lists the commands without importing them (torch alone takes seconds):
        each one's short help comes from its function's docstring, read from the source."""
        width = formatter.width - 6 - max(len(name) for name in COMMANDS)
        rows = [(name, command_short_help(name, width)) for name in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr = COMMANDS[name]
        return getattr(importlib.import_module(f"recon.cli.{module}"), attr)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.Abort, SystemExit):
            raise
        except KeyboardInterrupt as e:
            click.echo(f"interrupted: {e}" if str(e) else "interrupted", err=True)
            sys.exit(130)
        except Exception as e:  # noqa: BLE001 - the CLI boundary
            fail(e, verbose=ctx.obj.get("verbose", False) if ctx.obj else False)
            sys.exit(1)


@click.group(cls=ReconGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(recon.__version__, prog_name="recon")
@click.option("-v", "--verbose", is_flag=True, help="Show tracebacks and the libraries' own logs.")
@click.pass_context
def cli(ctx: click.Context, verbose: bool) -> None:
    """recon: photos -> camera poses -> trained scene -> renders, meshes, honest metrics.

    Stages share one workspace directory (-w WS) and can be rerun on their own:
    sfm -> [mvs] -> train -> render / mesh / export -> eval; `recon status` shows what is stale.
    """
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


def main() -> None:
    cli(prog_name="recon")
