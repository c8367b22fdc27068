"""The command line's own conversion of plain options (telefringe.cli._plain_coercion,
which spares the start of every command Pydantic's import) gives what typer's gives."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import typer

import telefringe.cli as cli

_coercion = pytest.importorskip("typer._coercion")  # typer's internals (not telefringe's)

_TEXTS = ["0", "7", "-3", "1.5", "-0.25", "1e-3", "2E+2", "007", "+1", "1_000", " 1", "nan",
          "inf", "abc", "", "x/y", "scan folder", "-"]


def _params():
    """(command name, parameter) of every command and sub-command of the app."""
    group = typer.main.get_command(cli.app)
    stack = [(name, cmd) for name, cmd in group.commands.items()]
    while stack:
        name, cmd = stack.pop()
        for sub, c in getattr(cmd, "commands", {}).items():
            stack.append((f"{name} {sub}", c))
        for p in cmd.params:
            if isinstance(p, typer.core._TyperParameter):
                yield name, cmd, p


def _outcome(runtime, value, param, ctx):
    try:
        v = runtime.coerce(value, param=param, ctx=ctx)
    except Exception as exc:  # noqa: BLE001 - compared below
        return ("error", type(exc).__name__, str(exc))
    return ("value", type(v).__name__, v)


def test_plain_options_are_converted_as_typer_converts_them():
    """Every option the fast path takes (str, int, float, Path without constraints; absent
    bools) gives, for plain and odd texts, absent values and its default, the value (and
    type) or the error typer's own Pydantic-based conversion gives."""
    n_fast = 0
    for name, cmd, p in _params():
        p._runtime_param = None
        rp = p.get_runtime_param()
        if type(rp).__name__ != "PlainRuntimeParam":
            continue
        n_fast += 1
        ref = _coercion.build_runtime_param(p.type_descriptor)
        ctx = typer._click.Context(cmd)
        values = [None, p.default] + ([] if rp.kind == "bool" else _TEXTS)
        for value in values:
            got = _outcome(rp, value, p, ctx)
            want = _outcome(ref, value, p, ctx)
            assert got == want or (got[0] == want[0] == "value" and got[1] == want[1] == "float"
                                   and got[2] != got[2] and want[2] != want[2]), (
                name, p.name, value, got, want)
    # the reconstruct command's options are all taken (none builds a Pydantic adapter)
    assert n_fast >= 12


def test_reconstruct_parses_without_pydantic(tmp_path):
    """`telefringe reconstruct`'s options are parsed without importing Pydantic (here up to
    the missing rig.json's error, which comes after the parsing)."""
    code = ("import sys\n"
            "import telefringe.cli as cli\n"
            "rc = cli.main(['-q', 'reconstruct', 'scan', '--rig', 'rig.json', '-o', 'out',"
            " '--pixel-mm', '0.05', '--max-residual', '2', '--method', 'auto'])\n"
            "print(rc, 'pydantic' in sys.modules)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path, check=True,
                         env={"PYTHONPATH": str(Path(cli.__file__).parents[2])})
    assert "rig.json" in out.stderr
    assert out.stdout.split() == ["2", "False"], out.stderr
