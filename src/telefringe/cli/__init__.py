"""The ``telefringe`` command. Each sub-command lives in its own module and registers
itself on :data:`app`; this module handles global options and user errors."""

from __future__ import annotations

import sys

import typer

from telefringe import __version__
from telefringe.cli._common import err_console, state

app = typer.Typer(
    name="telefringe",
    help="Telecentric fringe-projection profilometry: simulate, decode, calibrate, "
    "reconstruct and measure.\n\nExample: telefringe demo",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)


def _version(value: bool):
    if value:
        typer.echo(f"telefringe {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    quiet: bool = typer.Option(False, "-q", "--quiet", help="Print only errors."),
    verbose: bool = typer.Option(False, "-v", "--verbose", help="Print more detail."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks for errors."),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True,
                                 help="Print the version and exit."),
):
    """Telecentric fringe-projection profilometry."""
    state.quiet, state.verbose, state.debug = quiet, verbose, debug


def _flags_show_no_type() -> None:
    """A flag takes no value, yet recent typer versions print a '<bool>' type beside it in
    --help; drop that column entry for flags (no-op where typer differs)."""
    option = getattr(getattr(typer, "core", None), "TyperOption", None)
    shown = getattr(option, "display_type_rich", None)
    if shown is None or getattr(shown, "_telefringe", False):
        return

    def display_type_rich(self, ctx):
        return None if getattr(self, "is_flag", False) else shown(self, ctx)

    display_type_rich._telefringe = True
    option.display_type_rich = display_type_rich


def _register_all():
    from telefringe.cli import (
        accept,
        batch,
        calibrate,
        capture,
        decode,
        demo,
        measure,
        paper,
        patterns,
        reconstruct,
        simulate,
    )
    from telefringe.cli import rig as rig_cli

    for mod in (simulate, decode, patterns, calibrate, reconstruct, measure, paper, demo,
                accept):
        mod.register(app)
    rig_cli.register(app)
    capture.register(app)
    batch.register(app)
    # one-line summaries in `telefringe --help`: the first paragraph of each docstring,
    # its hard line breaks joined
    for cmd in app.registered_commands:
        doc = cmd.help or (cmd.callback.__doc__ if cmd.callback else None)
        if cmd.short_help is None and doc:
            cmd.short_help = " ".join(doc.strip().split("\n\n")[0].split())
    for grp in app.registered_groups:
        info = grp.typer_instance.info if grp.typer_instance else None
        doc = grp.help or (info.help if info else None)
        if grp.short_help is None and isinstance(doc, str):
            grp.short_help = " ".join(doc.strip().split("\n\n")[0].split())


_flags_show_no_type()
_register_all()


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the app; user errors end with one line and exit status 2."""
    from rich.markup import escape

    from telefringe.io.errors import InputError

    if argv is None:
        argv = sys.argv[1:]
    state.debug = "--debug" in argv
    try:
        rv = app(args=argv, prog_name="telefringe", standalone_mode=False)
    except InputError as exc:
        if state.debug:
            raise
        # escaped: messages quote fields like "[du, dv]", which are not rich markup
        err_console.print(f"[bold red]error:[/bold red] {escape(str(exc))}", soft_wrap=True)
        return 2
    except typer.Exit as exc:
        return exc.exit_code
    except typer.Abort:
        err_console.print("aborted")
        return 130
    except KeyboardInterrupt:
        err_console.print("interrupted: nothing was written")
        return 130
    except OSError as exc:  # a file system problem (permission, disk full): no traceback
        if state.debug:
            raise
        err_console.print(f"[bold red]error:[/bold red] {escape(str(exc))}", soft_wrap=True)
        return 1
    except Exception as exc:
        # click usage errors (typer >= 0.16 vendors click: no `import click`)
        if callable(getattr(exc, "show", None)) and isinstance(getattr(exc, "exit_code", None),
                                                                int):
            exc.show()
            return exc.exit_code
        raise
    # with standalone_mode=False, click returns the exit code of a typer.Exit (typer turns
    # a KeyboardInterrupt inside a command into Exit(130))
    code = rv if isinstance(rv, int) and not isinstance(rv, bool) else 0
    if code == 130:
        err_console.print("interrupted: nothing was written")
    return code


if __name__ == "__main__":
    sys.exit(main())
