"""Shared command-line plumbing: console, verbosity, progress bars, reading a scan."""

from __future__ import annotations

import contextlib
import threading
from dataclasses import dataclass

__all__ = ["state", "console", "err_console", "progress_bar", "info", "detail",
           "read_scan_with_progress", "warn_nonlinearity_kept", "show_warning"]


class _Console:
    """A ``rich.console.Console(**options)`` made at its first use (attributes are its),
    so that a command that prints nothing (``--quiet``) does not import rich (~0.05-0.1 s
    CPU of its start). ``real()`` is the Console itself."""

    def __init__(self, **options):
        object.__setattr__(self, "_options", options)
        object.__setattr__(self, "_console", None)
        object.__setattr__(self, "_lock", threading.Lock())

    def real(self):
        made = self._console
        if made is None:
            with self._lock:
                made = self._console
                if made is None:
                    from rich.console import Console

                    made = Console(**self._options)
                    object.__setattr__(self, "_console", made)
        return made

    def __getattr__(self, name):
        return getattr(self.real(), name)

    def __setattr__(self, name, value):
        setattr(self.real(), name, value)


console = _Console(highlight=False)
err_console = _Console(stderr=True, highlight=False)


@dataclass
class _State:
    quiet: bool = False
    verbose: bool = False
    debug: bool = False


state = _State()


def info(msg: str) -> None:
    """Print a normal message (suppressed by --quiet)."""
    if not state.quiet:
        console.print(msg)


def show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """A Python warning as the command shows it (``warnings.showwarning``'s signature):
    one line on stderr, ``warning: <message>``, without the source file and line that
    Python prints (which tell a user nothing); suppressed by --quiet; with --debug,
    Python's own format (source file and line)."""
    if state.debug:
        import sys
        import warnings

        (file or sys.stderr).write(warnings.formatwarning(message, category, filename,
                                                          lineno, line))
        return
    if state.quiet:
        return
    from rich.markup import escape

    err_console.print(f"[yellow]warning:[/yellow] {escape(str(message))}", soft_wrap=True)


def detail(msg: str) -> None:
    """Print a verbose-only message."""
    if state.verbose and not state.quiet:
        console.print(f"[dim]{msg}[/dim]")


@contextlib.contextmanager
def progress_bar(description: str, total: int | None):
    """A rich progress bar; yields ``advance(n=1)``. Silent with --quiet."""
    if state.quiet:
        yield lambda n=1: None
        return
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    with Progress(TextColumn("[progress.description]{task.description}"), BarColumn(),
                  MofNCompleteColumn(), TimeElapsedColumn(), TimeRemainingColumn(),
                  console=err_console.real(), transient=False) as prog:
        task = prog.add_task(description, total=total)
        try:
            yield lambda n=1: prog.advance(task, n)
        except BaseException:
            # a failed step leaves no half-drawn bar: the error stays the one line shown
            prog.live.transient = True
            raise


def read_scan_with_progress(folder, manifest=None):
    """Read a scan folder (:func:`telefringe.io.scan_json.read_scan`) under a progress bar
    of its images.

    Parameters
    ----------
    folder : path-like, the scan folder.
    manifest : its :class:`~telefringe.fringes.scan.ScanManifest` when already loaded (to
        count the images), else it is read here.

    Returns
    -------
    telefringe.fringes.scan.Scan

    Raises
    ------
    InputError
        As ``read_scan`` does.
    """
    from telefringe.io.scan_json import load_scan_manifest, read_scan, scan_image_names

    man = load_scan_manifest(folder) if manifest is None else manifest
    with progress_bar("reading images", len(scan_image_names(man))) as advance:
        done = 0

        def tick(k, total):
            nonlocal done
            advance(k - done)
            done = k

        return read_scan(folder, progress=tick)


def warn_nonlinearity_kept(axes, gamma: bool) -> None:
    """Print :func:`telefringe.fringes.decode.nonlinearity_kept`'s messages as warnings
    (the projector nonlinearity asked to be removed but left in, per axis)."""
    from telefringe.fringes.decode import nonlinearity_kept

    for msg in nonlinearity_kept(axes, gamma):
        msg = msg.replace("no gamma correction", "--no-gamma-correction")
        info(f"[yellow]warning:[/yellow] {msg}")
