"""`recon status -w WS`: one line per stage output: done / stale / missing, with times."""

from __future__ import annotations

import click

from recon.cli.common import emit_json, json_option, workspace_option
from recon.workspace import Workspace


@click.command()
@workspace_option
@json_option
def status(workspace: str, as_json: bool) -> None:
    """Show every stage of the workspace: done, stale (and why) or missing, with durations."""
    ws = Workspace.open(workspace)
    st = ws.status()
    rows = [
        {
            "stage": k,
            "state": v["state"],
            "why": v["why"],
            "ended": v.get("ended"),
            "duration_s": v.get("duration_s"),
        }
        for k, v in st.items()
    ]
    if as_json:
        emit_json({"workspace": str(ws.root), "stages": rows})
        return
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"recon workspace {ws.root}")
    for col in ("stage", "state", "finished", "duration", "note"):
        table.add_column(col)
    colors = {"done": "green", "stale": "yellow", "missing": "red"}
    for r in rows:
        table.add_row(
            r["stage"],
            f"[{colors[r['state']]}]{r['state']}[/]",
            r["ended"] or "",
            f"{r['duration_s']:.1f} s" if r["duration_s"] is not None else "",
            r["why"],
        )
    if not rows:
        click.echo("no stage has run yet")
        return
    Console(width=160).print(table)
