"""The cold start of ``telefringe reconstruct`` (issue 14): what it leaves out must not
change what it computes.

- the chi^2 tails of the noise estimate come from a table instead of scipy.special: the
  table holds scipy's figures bit for bit;
- numba's cached kernels are loaded without its registries (the same machine code; one
  that fails to load so is loaded numba's way), and numba's CPU target, when loaded, is
  loaded without importing scipy.linalg: numba still sees BLAS, compiles and runs BLAS
  calls afterwards;
- the command run as a program (no argv) writes the same files as ``main(argv)`` in this
  process with numba's own cache loads (and the collector untouched), without importing
  scipy.linalg or scipy.special;
- only the program tunes the garbage collector; ``main(argv)`` leaves the caller's alone.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import numpy as np

import telefringe
from telefringe.cli import main
from telefringe.fringes import _chi2_tails, noise


def _python(script: str, *args: str) -> subprocess.CompletedProcess:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(script), *args],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out


def test_chi2_tail_table_is_scipys_bit_for_bit():
    from scipy.special import gammainc, gammaincinv

    assert _chi2_tails.TAIL == noise._TAIL
    assert len(_chi2_tails.TAILS) == 61
    for nu, (c, f) in enumerate(_chi2_tails.TAILS, start=1):
        c_ref = 2.0 * float(gammaincinv(nu / 2.0, 1.0 - noise._TAIL))
        f_ref = float(gammainc(nu / 2.0 + 1.0, c_ref / 2.0))
        assert (c.hex(), f.hex()) == (c_ref.hex(), f_ref.hex()), nu
        assert noise._tail(nu) == (c, f)
    # beyond the table: scipy's figures (the chi^2 quantile grows with nu)
    c62, f62 = noise._tail(62)
    assert c62 == 2.0 * float(gammaincinv(31.0, 1.0 - noise._TAIL))
    assert c62 > _chi2_tails.TAILS[-1][0] and 0.999 < f62 < 1.0


def test_numba_target_without_scipy_linalg_keeps_blas():
    out = _python("""
        import sys
        from telefringe.cli.reconstruct import _load_numba_target
        _load_numba_target()
        assert "scipy.linalg" not in sys.modules
        from numba.np import arraymath, linalg
        assert arraymath._HAVE_BLAS is True
        # numba's own check is back in place, for whatever loads later
        assert arraymath.ensure_blas is linalg.ensure_blas
        assert linalg.ensure_blas.__module__ == "numba.np.linalg"
        import numba
        import numpy as np

        @numba.njit
        def dot(a, b):
            return np.dot(a, b)

        a = np.arange(12.0).reshape(3, 4)
        b = np.arange(4.0)
        print(dot(a, b).tolist(), (a @ b).tolist())
    """)
    got, ref = out.stdout.strip().split("] [")
    assert got + "]" == "[" + ref


def test_light_cache_loads_and_their_fallback():
    """Cached kernels load without numba's registries; one that fails to load so is
    loaded numba's way (its registries then loaded, still without scipy.linalg)."""
    script = """
        import sys
        from telefringe.cli.reconstruct import _light_numba_cache_loads
        from telefringe.geometry._distortion_kernels import undistort_point
        restore = _light_numba_cache_loads()
        if sys.argv[1] == "fail":
            from numba.core.runtime import rtsys

            initialize = rtsys.initialize

            def fail(ctx):  # the light load's call only
                rtsys.initialize = initialize
                raise RuntimeError("a light load that fails")
            rtsys.initialize = fail
        print(undistort_point(0.25, -0.5, 0.1, 0.0, 0.0),
              "numba.np.arraymath" in sys.modules, "scipy.linalg" in sys.modules,
              undistort_point.stats.cache_hits.most_common(1)[0][1],
              sum(undistort_point.stats.cache_misses.values()))
        restore()
        from numba.core import caching
        assert not getattr(caching.Cache.load_overload, "_telefringe", False)
    """
    # the kernel in numba's cache first (a fresh clone compiles it here)
    _python("""
        from telefringe.geometry._distortion_kernels import undistort_point
        undistort_point(0.25, -0.5, 0.1, 0.0, 0.0)
    """)
    light = _python(script, "light").stdout.split()
    fallback = _python(script, "fail").stdout.split()
    # the same result from the cache (a hit, no compilation) either way
    assert light[-3:] == fallback[-3:] == ["False", "1", "0"], (light, fallback)
    assert light[:-4] == fallback[:-4] and light[-4] == "False" and fallback[-4] == "True"


def _scan_and_rig(tmp_path):
    from telefringe.fringes.decode import decode
    from telefringe.io.rig_json import bare_rig_json
    from telefringe.io.scan_json import write_scan
    from telefringe.simulate import scenes
    from telefringe.simulate.presets import get_preset
    from telefringe.simulate.render import default_groups, render_scan

    vr = get_preset("fast")
    groups = default_groups(vr, axes=("u",))
    scan, _ = render_scan(vr, scenes.plate_at_z(-0.5), groups, seed=2)
    write_scan(tmp_path / "scan", scan)
    other, _ = render_scan(vr, scenes.plate_at_z(-0.5), groups, seed=3)
    learned = {("u", m.periods, int(g.steps)): m
               for m, g in zip(decode(other).axes["u"].phase_errors.models,
                               other.manifest.groups, strict=True)}
    (tmp_path / "rig.json").write_text(json.dumps(
        bare_rig_json(vr.rig, reference_pose="truth", phase_errors=learned)))
    return tmp_path / "scan", tmp_path / "rig.json"


def test_reconstruct_program_writes_the_same_files_without_scipy_linalg(tmp_path,
                                                                       monkeypatch):
    import telefringe.cli.reconstruct as command

    scan, rig = _scan_and_rig(tmp_path)
    args = ["-q", "reconstruct", str(scan), "--rig", str(rig), "--force"]
    # first here, with numba's own cache loads: the kernels are then in numba's cache (a
    # fresh clone compiles them here; freshly compiled kernels can differ from cached
    # ones in the last bits, so both runs compared below load them from the cache)
    monkeypatch.setattr(command, "_light_numba_cache_loads", lambda: lambda: None)
    assert main([*args, "-o", str(tmp_path / "first")]) == 0
    script = """
        import gc, sys
        import telefringe.cli.reconstruct as command
        from telefringe.cli import main
        if sys.argv[1] == "numba":  # numba's own cache loads
            command._light_numba_cache_loads = lambda: lambda: None
        sys.argv = ["telefringe", *sys.argv[2:]]
        rc = main()
        print(rc, gc.get_freeze_count() > 0, "numba.np.arraymath" in sys.modules,
              sorted(m for m in sys.modules if m.startswith(("scipy.linalg", "scipy.special"))))
    """
    out = _python(script, "light", *args, "-o", str(tmp_path / "program"))
    assert out.stdout.split(None, 3) == ["0", "True", "False", "[]\n"], out.stdout
    out = _python(script, "numba", *args, "-o", str(tmp_path / "here"))
    assert out.stdout.split(None, 3)[:3] == ["0", "True", "True"], out.stdout
    a, b = tmp_path / "program", tmp_path / "here"
    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    assert {"points.npz", "cloud.ply", "heightmap.tif", "summary.json"} <= set(names)
    for name in names:
        if name == "points.npz":  # the same arrays (the zip's member dates may differ)
            with np.load(a / name) as pa, np.load(b / name) as pb:
                assert sorted(pa.files) == sorted(pb.files)
                for k in pa.files:
                    np.testing.assert_array_equal(pa[k], pb[k], err_msg=k, strict=True)
        elif name == "summary.json":  # the scan's path is the same, the rest too
            assert json.loads((a / name).read_text()) == json.loads((b / name).read_text())
        elif name != "heightmap.x3p":  # (the X3P records when it was written)
            assert (a / name).read_bytes() == (b / name).read_bytes(), name
    assert json.loads((a / "summary.json").read_text()).get("noise_model"), \
        "the scan's noise estimate (the chi^2 tails) was not exercised"


def test_only_the_program_tunes_the_garbage_collector():
    out = _python("""
        import gc, sys
        from telefringe.cli import main
        before = gc.get_threshold()
        assert main(["--version"]) == 0
        assert gc.get_freeze_count() == 0 and gc.get_threshold() == before
        sys.argv = ["telefringe", "--version"]
        assert main() == 0
        print(gc.get_freeze_count() > 0, gc.get_threshold()[0] >= 10_000)
    """)
    version = f"telefringe {telefringe.__version__}"
    assert out.stdout.split("\n") == [version, version, "True True", ""], out.stdout
