"""`recon` entry point: a click group whose commands live one per module."""

from __future__ import annotations

import importlib
import sys

import click

import recon
from recon.cli.common import fail

# command name -> (module under recon.cli, attribute): each command's module (and what it
# imports: torch, trimesh, pycolmap) is loaded only when that command runs or help lists it.
COMMANDS = {
    "sfm": ("sfm_cmd", "sfm"),
    "mvs": ("mvs_cmd", "command"),
    "train": ("train_cmd", "command"),
    "render": ("render_cmd", "command"),
    "mesh": ("mesh_cmd", "command"),
    "eval": ("eval_cmd", "command"),
    "export": ("export_cmd", "command"),
    "status": ("status_cmd", "status"),
}


class ReconGroup(click.Group):
    """Loads each subcommand on demand (`COMMANDS`) and turns every exception into one clear
    line on stderr and a non-zero exit."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

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
