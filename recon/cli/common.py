"""Shared CLI plumbing: error reporting, JSON output, workspace option."""

from __future__ import annotations

import json
import sys
import traceback

import click

from recon.workspace import WorkspaceError

# Errors a user can act on: printed as one line, exit code 1.
USER_ERRORS: tuple[type[BaseException], ...] = (
    WorkspaceError,
    ValueError,
    FileNotFoundError,
    PermissionError,
    OSError,
)

workspace_option = click.option(
    "-w",
    "--workspace",
    "workspace",
    required=True,
    type=click.Path(file_okay=False),
    help="Workspace directory (created by `recon sfm`).",
)
json_option = click.option(
    "--json",
    "as_json",
    is_flag=True,
    help="Print a machine-readable JSON result on stdout (no progress output).",
)


def emit_json(obj) -> None:
    click.echo(json.dumps(obj, indent=2, default=str))


def fail(exc: BaseException, verbose: bool) -> None:
    if verbose:
        traceback.print_exception(exc, file=sys.stderr)
    msg = str(exc).strip().splitlines()[0] if str(exc).strip() else exc.__class__.__name__
    click.echo(f"error: {msg}", err=True)
    if not verbose and not isinstance(exc, USER_ERRORS):
        click.echo("(run with --verbose for the traceback)", err=True)
