"""Atomic outputs (telefringe.io.atomic): a failed or interrupted write leaves nothing
partial and the previous output untouched; an existing output needs force."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from telefringe.io.atomic import atomic_dir, atomic_file, check_can_write, write_json_atomic
from telefringe.io.errors import InputError


class Boom(Exception):
    pass


def _listing(folder):
    """Every path under folder (relative), with file contents: a full snapshot."""
    out = {}
    for root, dirs, files in os.walk(folder):
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), folder)] = None
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, folder)] = fh.read()
    return out


def _mode(path):
    return os.stat(path).st_mode & 0o777


def _umask():
    m = os.umask(0o022)
    os.umask(m)
    return m


# --------------------------------------------------------------------------- files
def test_atomic_file_writes_with_normal_permissions(tmp_path):
    with atomic_file(tmp_path / "out.txt") as tmp:
        assert tmp.parent == tmp_path and tmp.name.startswith(".out.txt.")
        tmp.write_text("hello")
        assert not (tmp_path / "out.txt").exists()  # nothing visible until done
    assert (tmp_path / "out.txt").read_text() == "hello"
    assert _mode(tmp_path / "out.txt") == 0o666 & ~_umask()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


@pytest.mark.parametrize("exc", [Boom, KeyboardInterrupt])
@pytest.mark.parametrize("existing", [False, True])
def test_atomic_file_failure_leaves_nothing_and_original_untouched(tmp_path, exc, existing):
    if existing:
        (tmp_path / "out.txt").write_text("original")
    before = _listing(tmp_path)
    with pytest.raises(exc):
        with atomic_file(tmp_path / "out.txt", force=True) as tmp:
            tmp.write_text("half a fi")
            raise exc()
    assert _listing(tmp_path) == before


def test_atomic_file_refuses_existing_output_without_force(tmp_path):
    (tmp_path / "out.txt").write_text("original")
    before = _listing(tmp_path)
    with pytest.raises(InputError, match=r"out.txt: already exists; pass --force"):
        with atomic_file(tmp_path / "out.txt", force=False) as tmp:
            tmp.write_text("new")
    assert _listing(tmp_path) == before
    with atomic_file(tmp_path / "out.txt", force=True) as tmp:
        tmp.write_text("new")
    assert (tmp_path / "out.txt").read_text() == "new"


def test_atomic_file_does_not_clobber_an_output_that_appears_meanwhile(tmp_path):
    with pytest.raises(InputError, match="appeared while writing"):
        with atomic_file(tmp_path / "out.txt", force=False) as tmp:
            tmp.write_text("mine")
            (tmp_path / "out.txt").write_text("someone else's")
    assert _listing(tmp_path) == {"out.txt": b"someone else's"}


def test_atomic_file_refuses_a_folder_and_a_missing_parent(tmp_path):
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "keep").write_text("x")
    with pytest.raises(InputError, match="is a folder"):
        with atomic_file(tmp_path / "d", force=True):
            pass
    with pytest.raises(InputError, match="does not exist"):
        with atomic_file(tmp_path / "nope" / "out.txt"):
            pass
    assert _listing(tmp_path) == {"d": None, "d/keep": b"x"}


def test_write_json_atomic(tmp_path):
    write_json_atomic(tmp_path / "a.json", {"mm": 0.5, "name": "Ø ball"})
    assert json.loads((tmp_path / "a.json").read_text(encoding="utf-8")) == \
        {"mm": 0.5, "name": "Ø ball"}
    before = _listing(tmp_path)
    for bad in ({"x": float("nan")}, {"x": float("inf")}, {"x": object()}):
        with pytest.raises((ValueError, TypeError)):
            write_json_atomic(tmp_path / "a.json", bad)
    assert _listing(tmp_path) == before
    with pytest.raises(InputError, match="already exists"):
        write_json_atomic(tmp_path / "a.json", {}, force=False)


# --------------------------------------------------------------------------- folders
def _fill(folder, n, *, fail_at=None):
    for k in range(n):
        if k == fail_at:
            raise Boom(f"failed after {k} files")
        (folder / f"f{k}.txt").write_text(str(k))


def test_atomic_dir_writes_with_normal_permissions(tmp_path):
    with atomic_dir(tmp_path / "out") as tmp:
        _fill(tmp, 3)
        assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["f0.txt", "f1.txt",
                                                                    "f2.txt"]
    assert _mode(tmp_path / "out") == 0o777 & ~_umask()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


@pytest.mark.parametrize("fail_at", [0, 1, 4])
@pytest.mark.parametrize("existing", [False, True])
def test_atomic_dir_failure_leaves_nothing_and_original_untouched(tmp_path, fail_at,
                                                                  existing):
    if existing:
        (tmp_path / "out").mkdir()
        (tmp_path / "out" / "old.txt").write_text("original")
    before = _listing(tmp_path)
    with pytest.raises(Boom):
        with atomic_dir(tmp_path / "out", force=True) as tmp:
            _fill(tmp, 5, fail_at=fail_at)
    assert _listing(tmp_path) == before


def test_atomic_dir_keyboard_interrupt(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(tmp_path / "out") as tmp:
            _fill(tmp, 2)
            raise KeyboardInterrupt
    assert _listing(tmp_path) == {}


def test_atomic_dir_refuses_existing_output_without_force(tmp_path):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("original")
    before = _listing(tmp_path)
    with pytest.raises(InputError, match="already exists; pass --force"):
        with atomic_dir(tmp_path / "out") as tmp:
            _fill(tmp, 2)
    assert _listing(tmp_path) == before
    with atomic_dir(tmp_path / "out", force=True) as tmp:
        _fill(tmp, 2)
    assert _listing(tmp_path) == {"out": None, "out/f0.txt": b"0", "out/f1.txt": b"1"}


def test_atomic_dir_does_not_clobber_an_output_that_appears_meanwhile(tmp_path):
    with pytest.raises(InputError, match="appeared while writing"):
        with atomic_dir(tmp_path / "out") as tmp:
            _fill(tmp, 2)
            (tmp_path / "out").mkdir()
            (tmp_path / "out" / "theirs").write_text("x")
    assert _listing(tmp_path) == {"out": None, "out/theirs": b"x"}


def test_atomic_dir_refuses_to_replace_a_file(tmp_path):
    (tmp_path / "out").write_text("a file")
    with pytest.raises(InputError, match="is a file"):
        with atomic_dir(tmp_path / "out", force=True):
            pass
    assert _listing(tmp_path) == {"out": b"a file"}


def test_atomic_dir_restores_the_original_if_the_swap_fails(tmp_path, monkeypatch):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "old.txt").write_text("original")
    before = _listing(tmp_path)
    real_replace = os.replace
    calls = []

    def flaky_replace(src, dst):
        calls.append((src, dst))
        if len(calls) == 2:  # the new folder onto the target
            raise OSError("disk on fire")
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", flaky_replace)
    with pytest.raises(OSError, match="disk on fire"):
        with atomic_dir(tmp_path / "out", force=True) as tmp:
            _fill(tmp, 3)
    monkeypatch.undo()
    assert _listing(tmp_path) == before


def test_check_can_write(tmp_path):
    assert check_can_write(tmp_path / "new", force=False) == tmp_path / "new"
    (tmp_path / "x").write_text("")
    with pytest.raises(InputError, match="already exists"):
        check_can_write(tmp_path / "x", force=False)
    assert check_can_write(tmp_path / "x", force=True) == tmp_path / "x"
    os.symlink(tmp_path / "missing", tmp_path / "dangling")
    with pytest.raises(InputError, match="already exists"):
        check_can_write(tmp_path / "dangling", force=False)


def _readline_within(stream, seconds: float) -> str | None:
    """One line from ``stream``, or None when none comes within ``seconds``."""
    import threading

    box = []
    reader = threading.Thread(target=lambda: box.append(stream.readline()), daemon=True)
    reader.start()
    reader.join(seconds)
    return box[0] if box else None


#: Generous bounds for a loaded machine (the suite runs beside other work): the child's
#: start-up (interpreter and imports) and its exit after Ctrl-C (unwinding, removing the
#: temporary folder). Neither makes the test unable to fail: the child sleeps far longer
#: than both, so a Ctrl-C that is not honoured runs into the bound and fails.
_START_S = 300.0
_EXIT_S = 120.0
_CHILD_SLEEP_S = 3600.0


def test_sigint_during_a_write_leaves_nothing(tmp_path):
    """A real Ctrl-C in another process, in the middle of writing a folder. The child says
    when it is inside the write (a readiness line, no fixed sleep), then gets SIGINT."""
    script = textwrap.dedent(f"""
        import pathlib, signal, sys, time
        signal.signal(signal.SIGINT, signal.default_int_handler)  # even if inherited ignored
        from telefringe.io.atomic import atomic_dir
        out = pathlib.Path({str(tmp_path / "out")!r})
        with atomic_dir(out) as tmp:
            (tmp / "a.txt").write_text("a")
            print("writing", flush=True)
            time.sleep({_CHILD_SLEEP_S})
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        line = _readline_within(proc.stdout, _START_S)
        assert line is not None and line.strip() == "writing", (
            f"the child did not reach the write within {_START_S:.0f} s: {line!r}")
        assert _listing(tmp_path) != {}  # the temporary folder exists while writing
        proc.send_signal(signal.SIGINT)
        t0 = time.monotonic()
        try:
            proc.wait(timeout=_EXIT_S)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the child did not stop within {_EXIT_S:.0f} s of Ctrl-C")
        exit_s = time.monotonic() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    err = proc.stderr.read()
    proc.stdout.close()
    proc.stderr.close()
    assert proc.returncode != 0 and "KeyboardInterrupt" in err, (proc.returncode, err)
    assert exit_s < _CHILD_SLEEP_S / 2  # it stopped on the signal, not at the sleep's end
    # the child removed its temporary folder itself before exiting: nothing to wait for
    assert _listing(tmp_path) == {}
