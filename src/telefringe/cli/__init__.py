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


def _plain_coercion() -> None:
    """Typer (>= 0.2x) converts every option's text through a Pydantic TypeAdapter:
    importing Pydantic and building the adapters took ~0.12 s CPU of each command's start
    (a third of what ``telefringe reconstruct`` spends before it reads its files). Options
    of exactly ``str``, ``int``, ``float`` or ``Path`` without constraints, given plain
    text (a decimal number, a non-empty path) or absent (their default), and absent
    ``bool`` ones, are converted here to the same values; anything else (bounds, choices,
    files, lists, other types and texts) goes through typer's own coercion, with its
    messages. A no-op where typer differs."""
    import re

    core = getattr(typer, "core", None)
    param_cls = getattr(core, "_TyperParameter", None)
    coercion = sys.modules.get("typer._coercion")
    param_types = sys.modules.get("typer._param_types")
    base = getattr(coercion, "RuntimeParam", None)
    build = getattr(coercion, "build_runtime_param", None)
    coerce_path = getattr(param_types, "coerce_cli_path", None)
    original = getattr(param_cls, "get_runtime_param", None)
    if None in (base, build, coerce_path, original) or getattr(original, "_telefringe",
                                                                    False):
        return
    from dataclasses import dataclass
    from pathlib import Path

    number = {int: re.compile(r"-?(?:0|[1-9][0-9]*)"),
              float: re.compile(r"-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][-+]?[0-9]+)?")}
    path_defaults = {"exists": False, "resolve_path": False, "allow_dash": False,
                     "path_type": None}

    def plain(annotation, info):
        """'str', 'int', 'float', 'path' or None: the kinds converted here."""
        if getattr(info, "parser", None) is not None or getattr(info, "click_type", None):
            return None
        if annotation in (str, bool):  # (a bool only when absent: None stays None)
            return annotation.__name__
        if annotation in number and all(getattr(info, k, None) in (None, False)
                                        for k in ("min", "max", "clamp")):
            return annotation.__name__
        if annotation is Path and all(getattr(info, k, None) == v
                                      for k, v in path_defaults.items()):
            return "path"
        return None

    @dataclass(frozen=True)
    class PlainRuntimeParam(base):
        kind: str = "str"

        def _coerce_value(self, value, param, ctx):
            if isinstance(value, str):
                if self.kind == "str":
                    return value
                if self.kind in ("int", "float"):
                    cls = int if self.kind == "int" else float
                    if number[cls].fullmatch(value):
                        return cls(value)
                elif self.kind == "path" and value:
                    # as typer's path coercion of a Path (its checks, resolve_path, ...)
                    return coerce_path(Path(value), self.parameter_info, path_type=Path,
                                       param=param, ctx=ctx)
            elif self.kind in ("int", "float") and type(value).__name__ == self.kind:
                return value  # a default
            return build(param.type_descriptor)._coerce_value(value, param=param, ctx=ctx)

    def get_runtime_param(self):
        if self._runtime_param is None:
            desc = getattr(self, "type_descriptor", None)
            kind = (None if desc is None or getattr(desc, "file_annotation", None) is not None
                    or self.multiple or self.nargs != 1
                    else plain(desc.annotation, desc.parameter_info))
            if kind is None:
                return original(self)
            self._runtime_param = PlainRuntimeParam(parameter_info=desc.parameter_info,
                                                    annotation=desc.annotation, kind=kind)
        return self._runtime_param

    get_runtime_param._telefringe = True
    param_cls.get_runtime_param = get_runtime_param


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
_plain_coercion()
_register_all()


#: the collector's first threshold while the command runs as a program (Python's default
#: is 700 allocations): the start-up's ~100 000 objects are long-lived, and collecting
#: every 700 allocations among them took ~0.1 s CPU of a cold ``telefringe reconstruct``
_GC_THRESHOLD_0 = 10_000


def main(argv: list[str] | None = None) -> int:
    """Entry point: run the app; user errors end with one line and exit status 2.

    Without ``argv`` (the ``telefringe`` command, ``python -m telefringe``: the process
    ends after it), the garbage collector is tuned for a short-lived process: the objects
    made so far (the imports) are frozen and collections come less often while the command
    runs, and everything is frozen at its end, so that the collections of the
    interpreter's shutdown do not walk numba's hundred thousand objects (~0.4 s CPU at
    exit). Finalisation is otherwise unchanged (atexit handlers, flushed streams). With
    ``argv`` (tests, programs calling it), the caller's collector is left alone.

    Without ``argv``, Python warnings (a fit that did not converge, a noise estimate that
    fell back to its default...) are printed as the command's own warnings, one line
    each on stderr (:func:`telefringe.cli._common.show_warning`); with ``argv`` the
    caller's warning machinery is left alone (pytest records them).
    """
    if argv is not None:
        return _run(argv)
    import gc
    import warnings

    from telefringe.cli._common import show_warning

    warnings.showwarning = show_warning

    gc.freeze()
    gc.set_threshold(max(gc.get_threshold()[0], _GC_THRESHOLD_0), *gc.get_threshold()[1:])
    try:
        return _run(sys.argv[1:])
    finally:
        gc.freeze()


#: the global flags also accepted after a sub-command (``telefringe decode SCAN -o X -q``)
_ANYWHERE = {"quiet": "quiet", "verbose": "verbose", "debug": "debug"}


def _flags_anywhere(root) -> None:
    """Give every sub-command (and group) of the click command ``root`` copies of the
    global ``-q``/``-v``/``--debug`` options, so that they work where users put them: after
    the command and its arguments as well as before it (the README promises them for every
    command). A flag given anywhere turns its setting on; none turns one off."""
    import copy

    originals = [p for p in root.params if p.name in _ANYWHERE]

    def turn_on(ctx, param, value):
        if value:
            setattr(state, _ANYWHERE[param.name], True)

    def walk(cmd):
        for sub in (getattr(cmd, "commands", None) or {}).values():
            names = {o for p in sub.params for o in (*p.opts, *p.secondary_opts)}
            for orig in originals:
                if names.isdisjoint(orig.opts):
                    flag = copy.copy(orig)
                    flag.expose_value = False
                    flag.callback = turn_on
                    sub.params.append(flag)
            walk(sub)

    walk(root)


def _run(argv: list[str]) -> int:
    """:func:`main` with its arguments."""
    import typer.main

    from telefringe.io.errors import InputError

    state.debug = "--debug" in argv
    try:
        root = typer.main.get_command(app)
        _flags_anywhere(root)
        rv = root.main(args=argv, prog_name="telefringe", standalone_mode=False)
    except InputError as exc:
        if state.debug:
            raise
        from rich.markup import escape

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
        from rich.markup import escape

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
