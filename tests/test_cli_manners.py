"""Command-line manners (issue 6): the real ``telefringe`` command, run in a subprocess.

Version, help with an example, unknown commands and options, and user errors: one line,
exit status 2, no traceback (``--debug`` shows it). Every registered command is also
checked for ``--help`` with an example, so commands added later keep the manners.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

import telefringe

EXE = Path(sys.executable).with_name("telefringe")
COMMAND = [str(EXE)] if EXE.exists() else [sys.executable, "-m", "telefringe.cli"]


def run(*args, cwd=None, script=None):
    cmd = [sys.executable, "-c", script, *args] if script else [*COMMAND, *args]
    return subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, timeout=120)


def _no_traceback(out):
    assert "Traceback" not in out.stdout + out.stderr, out.stderr


def test_version(tmp_path):
    out = run("--version", cwd=tmp_path)
    assert out.returncode == 0 and out.stdout.strip() == f"telefringe {telefringe.__version__}"
    assert list(tmp_path.iterdir()) == []  # and nothing is written


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_has_an_example_and_the_global_options(tmp_path, flag):
    out = run(flag, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    for token in ("Example", "telefringe", "--quiet", "--verbose", "--debug", "--version"):
        assert token in out.stdout, token
    _no_traceback(out)


@pytest.mark.parametrize("args, token", [
    (["frobnicate"], "No such command"),
    (["--frobnicate"], "No such option"),
    (["-q", "frobnicate", "x"], "No such command"),
])
def test_unknown_command_or_option(tmp_path, args, token):
    out = run(*args, cwd=tmp_path)
    assert out.returncode == 2
    assert token in out.stderr
    _no_traceback(out)
    assert list(tmp_path.iterdir()) == []


# A temporary command registered on the real app, then the real entry point.
_SCRIPT = textwrap.dedent("""
    import sys, typer
    from telefringe.cli import app, main
    from telefringe.io.errors import InputError

    @app.command("tf-test-fail")
    def _fail(kind: str = typer.Argument(...)):
        if kind == "input":
            raise InputError("scans/a/scan.json: 'patterns[0].images[2]' must be [du, dv] "
                             "in mm; " + "x" * 200)
        if kind == "interrupt":
            raise KeyboardInterrupt
        if kind == "exit3":
            raise typer.Exit(3)
        if kind == "oserror":
            open("/nonexistent-dir/out.txt", "w")
        if kind == "bug":
            raise ZeroDivisionError("a bug")

    sys.exit(main(sys.argv[1:]))
""")


def test_input_error_is_one_line_exit_2_without_traceback(tmp_path):
    out = run("tf-test-fail", "input", script=_SCRIPT, cwd=tmp_path)
    assert out.returncode == 2
    _no_traceback(out)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1, out.stderr  # not wrapped, however long
    assert lines[0].startswith("error: scans/a/scan.json: 'patterns[0].images[2]' must be "
                               "[du, dv] in mm")  # brackets are not eaten as markup
    assert out.stdout == ""


def test_debug_shows_the_traceback(tmp_path):
    out = run("--debug", "tf-test-fail", "input", script=_SCRIPT, cwd=tmp_path)
    assert out.returncode != 0
    assert "Traceback" in out.stderr and "InputError" in out.stderr


@pytest.mark.parametrize("kind, code, token", [
    ("interrupt", 130, "interrupted"),
    ("exit3", 3, None),
    ("oserror", 1, "No such file or directory"),
])
def test_other_endings(tmp_path, kind, code, token):
    out = run("tf-test-fail", kind, script=_SCRIPT, cwd=tmp_path)
    assert out.returncode == code, out.stderr
    _no_traceback(out)
    if token:
        assert token in out.stderr and len(out.stderr.strip().splitlines()) == 1


def test_a_bug_still_shows_its_traceback(tmp_path):
    """Only user errors are reduced to one line; a bug must stay visible."""
    out = run("tf-test-fail", "bug", script=_SCRIPT, cwd=tmp_path)
    assert out.returncode == 1 and "ZeroDivisionError" in out.stderr


def test_the_console_script_is_installed():
    assert EXE.exists() or shutil.which("telefringe"), "the `telefringe` command is missing"


# --------------------------------------------------------------------------- every command
def _commands():
    import typer.main

    from telefringe.cli import app

    root = typer.main.get_command(app)
    found = []

    def walk(cmd, path):
        subs = getattr(cmd, "commands", None)
        if subs:
            for name, sub in subs.items():
                walk(sub, [*path, name])
        elif path:
            found.append(path)

    walk(root, [])
    return found


_CMDS = _commands()


@pytest.mark.skipif(not _CMDS, reason="no sub-command is registered yet")
@pytest.mark.parametrize("path", _CMDS or [["none"]], ids=" ".join)
def test_every_command_has_help_with_an_example(path, capsys):
    from telefringe.cli import main

    code = main([*path, "--help"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "Example" in out.out, f"`telefringe {' '.join(path)} --help` shows no example"
