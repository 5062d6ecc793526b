"""`recon view -w WS [--run RUN]`: the workspace's report (or one run's 3D view) served on
localhost, for a browser on this machine or, through an SSH tunnel, on another."""

from __future__ import annotations

import functools
import http.server
import os
import sys
import threading
import webbrowser

import click

from recon.cli.common import workspace_option
from recon.workspace import Workspace, WorkspaceError

DEFAULT_PORT = 7007  # when it is taken, a free one is used instead (a given --port is kept)


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):
        pass


def serve(root, port: int) -> http.server.ThreadingHTTPServer:
    handler = functools.partial(QuietHandler, directory=str(root))
    try:
        return http.server.ThreadingHTTPServer(("127.0.0.1", port), handler)
    except OSError:
        if port != DEFAULT_PORT:
            raise OSError(f"port {port} is in use: choose another with --port") from None
        return http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)


def has_display() -> bool:
    return sys.platform in ("darwin", "win32") or bool(
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    )


@click.command()
@workspace_option
@click.option("--run", default="", help="One run's 3D view (default: the workspace's report).")
@click.option(
    "--port", type=click.IntRange(0, 65535), default=DEFAULT_PORT, show_default=True,
    help="Port on 127.0.0.1 (0: any free one).",
)  # fmt: skip
@click.option(
    "--browser/--no-browser", default=True, help="Open a browser (when there is a display)."
)
def command(workspace, run, port, browser):
    """Serve the report (or a run's 3D view) on localhost and print its URL; Ctrl-C stops."""
    ws = Workspace.open(workspace)
    if run:
        from recon.eval.viewer import run_page

        page = run_page(ws, run)
    elif ws.report_html.exists():
        page = ws.report_html
    else:
        raise WorkspaceError(
            f"{ws.root} has no report.html yet: run `recon eval -w {workspace}`, or give --run"
        )
    server = serve(ws.root, port)
    url = f"http://127.0.0.1:{server.server_port}/{page.relative_to(ws.root).as_posix()}"
    click.echo(f"view: {url}  (Ctrl-C stops)", nl=True)
    sys.stdout.flush()
    if browser and has_display():
        threading.Timer(0.3, webbrowser.open, (url,)).start()
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
