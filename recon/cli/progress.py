"""Progress for humans and machines: rich bars with ETA on a TTY, plain periodic log lines
otherwise (CI logs, Makefiles), nothing at all with --quiet/--json."""

from __future__ import annotations

import sys
import time


class Progress:
    """`update(phase, done, total, **info)`; also usable as a callback `progress(phase, done, total)`."""

    def __init__(self, enabled: bool = True, interval_s: float = 10.0):
        self.enabled = enabled
        self.tty = enabled and sys.stderr.isatty()
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._rich = None
        self._tasks: dict[str, int] = {}

    def __enter__(self):
        if self.tty:
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                TextColumn,
                TimeElapsedColumn,
                TimeRemainingColumn,
            )
            from rich.progress import Progress as RichProgress

            self._rich = RichProgress(
                TextColumn("[bold]{task.description}"),
                BarColumn(),
                MofNCompleteColumn(),
                TextColumn("{task.fields[info]}"),
                TimeElapsedColumn(),
                TextColumn("ETA"),
                TimeRemainingColumn(),
                transient=False,
                console=None,
            )
            self._rich.__enter__()
        return self

    def __exit__(self, *exc):
        if self._rich is not None:
            self._rich.__exit__(*exc)
            self._rich = None

    def __call__(self, phase: str, done: int, total: int | None = None, **info) -> None:
        self.update(phase, done, total, **info)

    def update(self, phase: str, done: int, total: int | None = None, **info) -> None:
        if not self.enabled:
            return
        text = "  ".join(f"{k}={_fmt(v)}" for k, v in info.items() if v is not None)
        if self._rich is not None:
            if phase not in self._tasks:
                self._tasks[phase] = self._rich.add_task(phase, total=total, info="")
            self._rich.update(self._tasks[phase], completed=done, total=total, info=text)
            return
        now = time.monotonic()
        finished = total is not None and done >= total
        if finished or now - self._last.get(phase, -1e9) >= self.interval_s:
            self._last[phase] = now
            of = f"/{total}" if total is not None else ""
            print(
                f"[{time.strftime('%H:%M:%S')}] {phase} {done}{of} {text}".rstrip(),
                file=sys.stderr,
                flush=True,
            )

    def log(self, message: str) -> None:
        if not self.enabled:
            return
        if self._rich is not None:
            self._rich.console.print(message)
        else:
            print(message, file=sys.stderr, flush=True)


def _fmt(v) -> str:
    return f"{v:.4g}" if isinstance(v, float) else str(v)
