"""`recon` entry point: a click group whose commands live one per module."""

from __future__ import annotations

import sys

import click

import recon
from recon.cli.common import fail


class ReconGroup(click.Group):
    """Turns every exception into one clear line on stderr and a non-zero exit."""

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
    sfm -> train -> render / mesh / export -> eval; `recon status` shows what is stale.
    """
    ctx.ensure_object(dict)
    ctx.obj["verbose"] = verbose


def _register_commands() -> None:
    from recon.cli import eval_cmd, export_cmd, mesh_cmd, render_cmd, sfm_cmd, status_cmd, train_cmd

    for command in (
        sfm_cmd.sfm,
        train_cmd.command,
        render_cmd.command,
        mesh_cmd.command,
        eval_cmd.command,
        export_cmd.command,
        status_cmd.status,
    ):
        cli.add_command(command)


_register_commands()


def main() -> None:
    cli(prog_name="recon")
