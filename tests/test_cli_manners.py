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
    (["-q", "frobnicate", "x"], "No such command"),
    (["--frobnicate"], "No such option"),
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


# A temporary command that issues a Python warning, run by the real entry point as the
# console script runs it (main() without argv)
_WARN_SCRIPT = textwrap.dedent("""
    import sys, warnings
    from telefringe.cli import app, main

    @app.command("tf-test-warn")
    def _warn():
        warnings.warn("fit for periods [1, 8, 64] (not converged)", RuntimeWarning)

    sys.exit(main())
""")


@pytest.mark.parametrize("flags", [(), ("-q",), ("--debug",)])
def test_a_python_warning_is_one_line_of_the_command(tmp_path, flags):
    """A warning raised in the library (a fit that did not converge) reaches the user as
    the command's own one-line warning on stderr, without Python's source path; -q
    silences it; --debug shows Python's format with the source line."""
    out = run("tf-test-warn", *flags, script=_WARN_SCRIPT, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    err = out.stderr.strip()
    if flags == ("-q",):
        assert err == ""
    elif flags == ("--debug",):
        assert "RuntimeWarning: fit for periods [1, 8, 64] (not converged)" in err
    else:
        assert err == "warning: fit for periods [1, 8, 64] (not converged)"


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

# Every command the README documents. If registration breaks, this fails (the tests
# below are parametrised over _CMDS and would otherwise just shrink).
_DOCUMENTED = [["decode"], ["patterns"], ["calibrate"], ["reconstruct"], ["paper"], ["demo"],
               ["simulate", "calibration"], ["simulate", "scan"], ["measure", "plate"],
               ["measure", "sphere"], ["measure", "bga"], ["measure", "steps"],
               ["accept"], ["simulate", "acceptance"], ["batch"],
               ["rig", "import-opencv"], ["rig", "export-opencv"], ["capture", "scan"],
               ["capture", "calibration"], ["capture", "latency"], ["capture", "devices"]]


def test_every_documented_command_is_registered():
    missing = [" ".join(p) for p in _DOCUMENTED if p not in _CMDS]
    assert not missing, f"not registered: {missing}"


@pytest.mark.parametrize("path", _CMDS, ids=" ".join)
def test_every_command_has_help_with_an_example(path, capsys):
    from telefringe.cli import main

    code = main([*path, "--help"])
    out = capsys.readouterr()
    assert code == 0, out.err
    assert "Example" in out.out, f"`telefringe {' '.join(path)} --help` shows no example"
    # a flag takes no value: no type is shown beside it
    assert "<bool>" not in out.out, f"`telefringe {' '.join(path)} --help` shows <bool>"


# --------------------------------------------------------------------------- real commands
def _snapshot(folder):
    return {p.relative_to(folder): p.read_bytes() if p.is_file() else None
            for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="module")
def pattern_folder(tmp_path_factory):
    """A small scan folder written by `telefringe patterns` (its images stand in for
    captures)."""
    cwd = tmp_path_factory.mktemp("cli")
    out = run("patterns", "pats", "--width", "64", "--height", "48", "--periods", "1,8",
              cwd=cwd)
    assert out.returncode == 0, out.stderr
    return cwd / "pats"


def test_existing_output_is_refused_without_force(pattern_folder):
    cwd = pattern_folder.parent
    before = _snapshot(cwd)
    out = run("patterns", "pats", "--width", "32", "--height", "16", "--periods", "1",
              cwd=cwd)
    assert out.returncode == 2 and "already exists" in out.stderr and "--force" in out.stderr
    _no_traceback(out)
    assert _snapshot(cwd) == before


@pytest.mark.parametrize("breakage, tokens", [
    ("manifest", ["scan.json", "'patterns[0]", "'steps'"]),
    ("image", ["u_008_4s_01.png", "truncated"]),
    ("missing", ["nope", "not a folder"]),
])
def test_a_broken_scan_through_decode(tmp_path, pattern_folder, breakage, tokens):
    import shutil as sh

    scan = tmp_path / "scan"
    sh.copytree(pattern_folder, scan)
    if breakage == "manifest":
        doc = (scan / "scan.json").read_text()
        (scan / "scan.json").write_text(doc.replace('"steps": 4', '"steps": 2.5', 1))
        tokens = [str(scan / "scan.json"), *tokens[1:]]
    elif breakage == "image":
        img = scan / "u_008_4s_01.png"
        img.write_bytes(img.read_bytes()[:100])
    else:
        scan = tmp_path / "nope"
    before = _snapshot(tmp_path)
    out = run("decode", str(scan), "-o", "coords.npz", cwd=tmp_path)
    assert out.returncode == 2, out.stderr
    _no_traceback(out)
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), out.stderr
    for token in tokens:
        assert token.strip("'") in lines[0], (token, lines[0])
    assert _snapshot(tmp_path) == before  # nothing written, no temporary left
    if breakage == "manifest":
        debug = run("--debug", "decode", str(scan), "-o", "coords.npz", cwd=tmp_path)
        assert debug.returncode != 0 and "Traceback" in debug.stderr
        assert "InputError" in debug.stderr
