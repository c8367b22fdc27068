"""`telefringe patterns` and `telefringe decode` end to end (files, errors)."""

import json
import shutil

import numpy as np
import pytest

from telefringe.cli import main
from telefringe.io.coords_npz import read_coords
from telefringe.io.images import read_image, write_png
from telefringe.io.scan_json import read_scan


def test_patterns_then_decode_round_trip(tmp_path, capsys):
    pats = tmp_path / "pats"
    code = main(["patterns", str(pats), "--width", "160", "--height", "120", "--steps", "4",
                 "--periods", "1,4,16", "--axes", "u,v"])
    assert code == 0, capsys.readouterr().err
    doc = json.loads((pats / "scan.json").read_text())
    assert [(g["axis"], g["periods"]) for g in doc["patterns"]] == [
        ("u", 1), ("u", 4), ("u", 16), ("v", 1), ("v", 4), ("v", 16)]
    img = read_image(pats / doc["patterns"][2]["images"][1])
    assert img.dtype == np.uint8 and img.shape == (120, 160)
    # a "capture" of the patterns by a camera that sees projector pixel (x, y) at (x, y),
    # dimmed so that nothing saturates
    scan = read_scan(pats)
    for g in doc["patterns"]:
        for name in g["images"]:
            im = read_image(pats / name).astype(float)
            write_png(pats / name, np.round(20 + 0.8 * im).astype(np.uint8))
    out = tmp_path / "c.npz"
    assert main(["decode", str(pats), "-o", str(out)]) == 0
    c = read_coords(out)
    assert set(c) == {"u_p", "v_p", "mask", "modulation", "sigma_u_p", "sigma_v_p"}
    yy, xx = np.mgrid[0:120, 0:160]
    assert c["mask"].mean() > 0.99
    ok = c["mask"]
    # quantised 8-bit patterns: errors of a few hundredths of a pixel
    assert np.max(np.abs(c["u_p"][ok] - xx[ok])) < 0.1
    assert np.max(np.abs(c["v_p"][ok] - yy[ok])) < 0.1
    assert np.all(np.isnan(c["u_p"][~ok]) | ~c["mask"][~ok])
    assert scan.white is not None
    # no overwrite without --force, a one-line error naming the file
    capsys.readouterr()
    assert main(["decode", str(pats), "-o", str(out)]) == 2
    assert "already exists" in capsys.readouterr().err
    assert main(["decode", str(pats), "-o", str(out), "--force"]) == 0


def test_patterns_gray_and_precompensation(tmp_path):
    out = tmp_path / "g"
    assert main(["patterns", str(out), "--width", "64", "--height", "32", "--periods", "16",
                 "--axes", "u", "--gray", "4", "--precompensate-gamma", "2.2"]) == 0
    doc = json.loads((out / "scan.json").read_text())
    kinds = [g.get("type", "phase") for g in doc["patterns"]]
    assert kinds == ["phase", "gray"] and len(doc["patterns"][1]["images"]) == 5
    # pre-compensated fringes: level**2.2 is the wanted sinusoid (to 8-bit rounding)
    im = read_image(out / doc["patterns"][0]["images"][0]).astype(float)[0] / 255
    x = np.arange(64)
    want = 0.5 + 0.5 * np.cos(2 * np.pi * 16 * x / 64)
    assert np.max(np.abs(im ** 2.2 - want)) < 0.02


@pytest.mark.parametrize("args, token", [
    (["--periods", "8,64"], "cannot unwrap"),
    (["--periods", "1,x"], "--periods"),
    (["--axes", "w"], "--axes"),
    (["--steps", "2"], "--steps"),
    (["--gray", "3", "--periods", "1,16"], "add 8 to --periods"),
])
def test_patterns_bad_options(tmp_path, capsys, args, token):
    code = main(["patterns", str(tmp_path / "p"), *args])
    err = capsys.readouterr().err
    assert code == 2 and token in err and "Traceback" not in err
    assert not (tmp_path / "p").exists()


def _small_scan(tmp_path, periods="1,8"):
    pats = tmp_path / "s"
    assert main(["patterns", str(pats), "--width", "64", "--height", "48", "--periods",
                 periods, "--axes", "u", "--no-white-black"]) == 0
    return pats


def test_decode_user_errors(tmp_path, capsys):
    pats = _small_scan(tmp_path)
    doc = json.loads((pats / "scan.json").read_text())
    out = tmp_path / "c.npz"
    # every pixel saturated: the projector images themselves reach 255... make all 255
    for g in doc["patterns"]:
        for name in g["images"]:
            write_png(pats / name, np.full((48, 64), 255, np.uint8))
    capsys.readouterr()
    assert main(["decode", str(pats), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "saturated" in err and str(pats) in err and not out.exists()
    # a ladder that cannot unwrap the finest group
    bad = tmp_path / "bad"
    shutil.copytree(pats, bad)
    doc2 = dict(doc)
    doc2["patterns"] = [doc["patterns"][1]]
    (bad / "scan.json").write_text(json.dumps(doc2))
    assert main(["decode", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot unwrap" in err and str(bad) in err
    # wrong number of images for steps
    doc3 = json.loads((pats / "scan.json").read_text())
    doc3["patterns"][0]["images"] = doc3["patterns"][0]["images"][:3]
    (bad / "scan.json").write_text(json.dumps(doc3))
    assert main(["decode", str(bad), "-o", str(out)]) == 2
    assert "needs 4 images" in capsys.readouterr().err
    # sizes differ
    (bad / "scan.json").write_text(json.dumps(doc))
    write_png(bad / doc["patterns"][0]["images"][0], np.zeros((10, 10), np.uint8))
    assert main(["decode", str(bad), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert "sizes differ" in err and doc["patterns"][0]["images"][0] in err
    # bit depths differ
    write_png(bad / doc["patterns"][0]["images"][0], np.zeros((48, 64), np.uint16))
    assert main(["decode", str(bad), "-o", str(out)]) == 2
    assert "bit depths differ" in capsys.readouterr().err
    assert not out.exists()
