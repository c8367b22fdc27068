"""Hostile input for the scan and calibration-set loaders (issue 6, "Bad input").

Every broken manifest must end in an InputError whose message names the file and the
field; a valid manifest must load to exactly what it says. Hypothesis draws valid
manifests, then breaks one field at a time with values drawn from what that field must
not be (missing, wrong type, bool for int, NaN/inf, zero/negative, out of range, paths
leaving the folder, extra fields, wrong counts, duplicates).
"""

from __future__ import annotations

import copy
import json
import math
import os
import struct
import zlib

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from telefringe.calibration.manifest import CalibrationSetManifest
from telefringe.fringes.scan import GrayGroup, PhaseGroup, Scan, ScanManifest
from telefringe.io.calibration_json import (
    CALIB_FORMAT,
    load_calibration_set,
    parse_calibration_manifest,
    write_calibration_manifest,
)
from telefringe.io.errors import InputError
from telefringe.io.images import write_png
from telefringe.io.scan_json import (
    SCAN_FORMAT,
    load_scan_manifest,
    parse_scan_manifest,
    read_scan,
    scan_manifest_to_json,
    write_scan,
)
from telefringe.targets.grid import CircleGridTarget

FAST = settings(max_examples=80, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture])
NAN, INF = float("nan"), float("inf")
WHERE = "some/dir/scan.json"
CWHERE = "cal/calibration.json"


# --------------------------------------------------------------------------- valid docs
@st.composite
def valid_scan_docs(draw):
    """A valid scan.json document (image names unique, no files checked)."""
    W = draw(st.integers(2, 3000))
    H = draw(st.integers(2, 3000))
    L = {"u": W, "v": H}
    groups, keys, n_img = [], set(), 0

    def names(n):
        nonlocal n_img
        out = [f"img_{n_img + k:03d}.png" for k in range(n)]
        n_img += n
        return out

    for _ in range(draw(st.integers(1, 4))):
        axis = draw(st.sampled_from("uv"))
        g = {"axis": axis, "periods": draw(st.integers(1, L[axis] // 2)),
             "steps": draw(st.integers(3, 8))}
        if draw(st.booleans()):
            g["exposure"] = draw(st.floats(1e-3, 1e3))
        if draw(st.booleans()):
            g["offset"] = draw(st.floats(-10, 10))
        if draw(st.booleans()):
            g["type"] = "phase"
        key = (axis, g["periods"], g["steps"], g.get("offset", 0.0), g.get("exposure", 1.0))
        if key in keys:
            continue
        keys.add(key)
        g["images"] = names(g["steps"])
        groups.append(g)
    # a Gray-code group and its phase group (periods = 2**bits)
    axis = draw(st.sampled_from("uv"))
    maxbits = min(16, int(math.log2(L[axis] // 2))) if L[axis] >= 4 else 0
    if maxbits >= 1 and draw(st.booleans()):
        bits = draw(st.integers(1, maxbits))
        comp = draw(st.booleans())
        key = (axis, 2**bits, 4, 0.0, 1.0)
        if key not in keys:
            groups.append({"axis": axis, "periods": 2**bits, "steps": 4, "images": names(4)})
        gg = {"type": "gray", "axis": axis, "bits": bits, "images": names(bits + comp)}
        if comp or draw(st.booleans()):
            gg["complementary"] = comp
        groups.insert(draw(st.integers(0, len(groups))), gg)
    doc = {"format": SCAN_FORMAT, "version": 1, "projector": {"width": W, "height": H},
           "patterns": groups}
    for key in ("white", "black"):
        if draw(st.booleans()):
            doc[key] = names(1)[0]
    if draw(st.booleans()):
        doc["meta"] = {"camera": "virtual", "note": draw(st.text(max_size=10))}
    return doc


def _normalised(doc):
    """A valid doc as scan_manifest_to_json writes it (defaults filled / dropped)."""
    out = {"format": doc["format"], "version": 1, "projector": dict(doc["projector"]),
           "patterns": []}
    for g in doc["patterns"]:
        if g.get("type", "phase") == "phase":
            d = {"axis": g["axis"], "periods": g["periods"], "steps": g["steps"],
                 "exposure": float(g.get("exposure", 1.0))}
            if g.get("offset", 0.0):
                d["offset"] = float(g["offset"])
        else:
            d = {"type": "gray", "axis": g["axis"], "bits": g["bits"],
                 "complementary": g.get("complementary", False),
                 "exposure": float(g.get("exposure", 1.0))}
        d["images"] = list(g["images"])
        out["patterns"].append(d)
    for key in ("white", "black"):
        if doc.get(key):
            out[key] = doc[key]
    return out


@FAST
@given(doc=valid_scan_docs())
def test_valid_scan_manifests_load_exactly(doc):
    man = parse_scan_manifest(copy.deepcopy(doc), where=WHERE)
    assert scan_manifest_to_json(man) == _normalised(doc)
    assert all(type(x) is int for x in (man.projector_width, man.projector_height))
    for g in man.groups:
        assert type(g.count) is int and len(g.images) == g.count


# --------------------------------------------------------------------------- invalid values
junk = st.one_of(st.none(), st.booleans(), st.text(max_size=4),
                 st.lists(st.integers(0, 3), max_size=2),
                 st.dictionaries(st.text(max_size=2), st.integers(0, 3), max_size=1))
non_finite = st.sampled_from([NAN, INF, -INF, 10**400])


def bad_int(lo, hi=None):
    """Anything but an integer in [lo, hi]: floats (8.0 too), bools, NaN, out of range."""
    out = st.integers(max_value=lo - 1)
    if hi is not None:
        out = st.one_of(out, st.integers(min_value=hi + 1))
    return st.one_of(junk, non_finite, out, st.floats(allow_nan=False, allow_infinity=False))


bad_positive = st.one_of(junk, non_finite, st.floats(max_value=0.0, allow_nan=False),
                         st.integers(max_value=0))
bad_finite = st.one_of(junk, non_finite)
bad_name = st.one_of(
    st.none(), st.booleans(), st.integers(), st.lists(st.text(max_size=2), max_size=1),
    st.sampled_from(["", ".", "./", "../x.png", "a/../../x.png", "..", "/etc/passwd",
                     "/tmp/x.png", "C:\\x.png", "C:/x.png", "a\\b.png", "x\x00.png",
                     "\udc80.png", "sub/./../../x.png"]),
)


@st.composite
def broken_scan_docs(draw):
    """(doc, field tokens the message must contain) with exactly one field broken."""
    doc = draw(valid_scan_docs())
    gi = draw(st.integers(0, len(doc["patterns"]) - 1))
    g = doc["patterns"][gi]
    gw = f"patterns[{gi}]"
    is_gray = g.get("type") == "gray"
    cases = ["format", "version", "projector", "width", "height", "patterns", "group",
             "type", "axis", "exposure", "images", "image_name", "count", "duplicate",
             "extra_top", "extra_projector", "extra_group", "missing", "meta", "white"]
    cases += ["bits", "complementary"] if is_gray else ["periods", "steps", "offset"]
    case = draw(st.sampled_from(cases))
    if case == "format":
        doc["format"] = draw(st.one_of(junk, st.just("telefringe-calibration-set")))
        return doc, ["'format'"]
    if case == "version":
        doc["version"] = draw(st.one_of(junk.filter(lambda x: x is not True), st.just(True),
                                        st.just(1.0), st.integers(2, 9), st.just(0)))
        return doc, ["'version'"]
    if case == "projector":
        doc["projector"] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, ["'projector'"]
    if case in ("width", "height"):
        doc["projector"][case] = draw(bad_int(1, 100_000))
        return doc, [f"'projector.{case}'"]
    if case == "patterns":
        doc["patterns"] = draw(st.one_of(junk.filter(lambda x: not isinstance(x, list)),
                                         st.just([])))
        return doc, ["'patterns'"]
    if case == "group":
        doc["patterns"][gi] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, [gw]
    if case == "type":
        g["type"] = draw(junk.filter(lambda x: x not in ("phase", "gray")))
        return doc, [gw, "'type'"]
    if case == "axis":
        g["axis"] = draw(st.one_of(junk, st.sampled_from(["x", "U", "uv"]))
                         .filter(lambda x: x not in ("u", "v")))
        return doc, [gw, "'axis'"]
    if case == "exposure":
        g["exposure"] = draw(bad_positive)
        return doc, [gw, "'exposure'"]
    if case == "periods":
        L = doc["projector"]["width" if g["axis"] == "u" else "height"]
        g["periods"] = draw(bad_int(1, L // 2))
        return doc, [gw, "'periods'"]
    if case == "steps":
        g["steps"] = draw(bad_int(3, 1000))
        return doc, [gw, "'steps'"]
    if case == "offset":
        g["offset"] = draw(bad_finite)
        return doc, [gw, "'offset'"]
    if case == "bits":
        g["bits"] = draw(bad_int(1, 16))
        return doc, [gw, "'bits'"]
    if case == "complementary":
        g["complementary"] = draw(st.one_of(st.none(), st.integers(0, 1), st.text(max_size=3),
                                            st.just(NAN)))
        return doc, [gw, "'complementary'"]
    if case == "images":
        g["images"] = draw(junk.filter(lambda x: not isinstance(x, list)))
        return doc, [gw, "'images'"]
    if case == "image_name":
        j = draw(st.integers(0, len(g["images"]) - 1))
        g["images"][j] = draw(bad_name)
        return doc, [f"{gw}.images[{j}]"]
    if case == "count":
        if draw(st.booleans()) and len(g["images"]) > 1:
            g["images"].pop(draw(st.integers(0, len(g["images"]) - 1)))
        else:
            g["images"].append("one_more.png")
        return doc, [gw, "needs"]
    if case == "duplicate":
        j = draw(st.integers(0, len(g["images"]) - 1))
        other = [n for h in doc["patterns"] for n in h["images"] if n != g["images"][j]]
        g["images"][j] = draw(st.sampled_from(other)) if other else "./" + g["images"][1 - j]
        return doc, [f"{gw}.images[{j}]", "same file"]
    if case.startswith("extra"):
        key = draw(st.sampled_from(["Format", "exposures", "colour", "z", "", "images2"]))
        obj = {"extra_top": doc, "extra_projector": doc["projector"], "extra_group": g}[case]
        obj[key] = draw(junk)
        return doc, ["unknown field", repr(key)]
    if case == "missing":
        required = [("format", doc, "'format'"), ("version", doc, "'version'"),
                    ("projector", doc, "'projector'"), ("patterns", doc, "'patterns'"),
                    ("width", doc["projector"], "'projector.width'"),
                    ("height", doc["projector"], "'projector.height'"),
                    ("axis", g, "'axis'"), ("images", g, "'images'")]
        required += [("bits", g, "'bits'")] if is_gray else [("periods", g, "'periods'"),
                                                             ("steps", g, "'steps'")]
        key, obj, token = draw(st.sampled_from(required))
        del obj[key]
        return doc, [token]
    if case == "meta":
        doc["meta"] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, ["'meta'"]
    if case == "white":
        key = draw(st.sampled_from(["white", "black"]))
        doc[key] = draw(bad_name.filter(lambda x: x is not None))
        return doc, [f"'{key}'"]
    raise AssertionError(case)


@settings(max_examples=200, deadline=None, derandomize=True)
@given(case=broken_scan_docs())
def test_broken_scan_manifests_are_refused_naming_file_and_field(case):
    doc, tokens = case
    with pytest.raises(InputError) as info:
        parse_scan_manifest(doc, where=WHERE)
    msg = str(info.value)
    assert msg.startswith(WHERE + ":")
    for token in tokens:
        assert token in msg, (token, msg)
    assert "\n" not in msg


@settings(max_examples=120, deadline=None, derandomize=True)
@given(doc=st.recursive(st.none() | st.booleans() | st.floats() | st.integers() | st.text(),
                        lambda c: st.lists(c, max_size=3)
                        | st.dictionaries(st.sampled_from(["format", "version", "projector",
                                                           "patterns", "width", "images",
                                                           "axis", "target", "poses"]), c,
                                          max_size=4), max_leaves=12))
def test_arbitrary_json_never_crashes_the_parsers(doc):
    for parse in (parse_scan_manifest, parse_calibration_manifest):
        with pytest.raises(InputError):
            parse(doc)


def test_all_problems_are_listed_at_once():
    doc = {"format": SCAN_FORMAT, "version": 1, "projector": {"width": -5, "height": 1.5},
           "patterns": [{"axis": "w", "periods": 0, "steps": 2, "images": []}]}
    msg = str(pytest.raises(InputError, parse_scan_manifest, doc, where=WHERE).value)
    for token in ("5 problems", "'projector.width'", "'projector.height'", "'axis'",
                  "'periods'", "'steps'"):
        assert token in msg


def test_long_values_are_shortened_in_messages():
    doc = {"format": "x" * 10_000, "version": 1, "projector": {"width": 10, "height": 10},
           "patterns": [{"axis": "u", "periods": 1, "steps": 3,
                         "images": ["a.png", "b.png", "c.png"]}]}
    msg = str(pytest.raises(InputError, parse_scan_manifest, doc, where=WHERE).value)
    assert len(msg) < 300


# --------------------------------------------------------------------------- on disk
@pytest.fixture(scope="module")
def stub_scan_dir(tmp_path_factory):
    """A folder with empty files img_000.png .. img_199.png (load_* does not decode)."""
    folder = tmp_path_factory.mktemp("stub_scan")
    for k in range(200):
        (folder / f"img_{k:03d}.png").write_bytes(b"")
    for k in ("white", "black", "one_more"):
        (folder / f"{k}.png").write_bytes(b"")
    return folder


@settings(max_examples=100, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=broken_scan_docs())
def test_broken_scan_manifests_on_disk(stub_scan_dir, case):
    """The same through load_scan_manifest: JSON text (NaN / Infinity literals from
    json.dumps), image paths checked against a real folder."""
    doc, tokens = case
    path = stub_scan_dir / "scan.json"
    path.write_text(json.dumps(doc))
    msg = str(pytest.raises(InputError, load_scan_manifest, stub_scan_dir).value)
    assert msg.startswith(str(path) + ":")
    for token in tokens:
        assert token in msg, (token, msg)


@settings(max_examples=40, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(doc=valid_scan_docs())
def test_valid_scan_manifests_on_disk(stub_scan_dir, doc):
    (stub_scan_dir / "scan.json").write_text(json.dumps(doc))
    assert scan_manifest_to_json(load_scan_manifest(stub_scan_dir)) == _normalised(doc)


def png_bytes(width, height, depth, color, rows):
    """A hand-made PNG (any header, any rows) so that hostile headers can be written."""
    def chunk(kind, data):
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data)))
    ihdr = struct.pack(">IIBBBBB", width, height, depth, color, 0, 0, 0)
    raw = b"".join(b"\0" + r for r in rows)
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw))
            + chunk(b"IEND", b""))


IMG = np.arange(48, dtype=np.uint8).reshape(6, 8) * 5


def _doc(names):
    return {"format": SCAN_FORMAT, "version": 1, "projector": {"width": 64, "height": 48},
            "patterns": [{"axis": "u", "periods": 8, "steps": 3, "images": names[:3]},
                         {"axis": "u", "periods": 1, "steps": 3, "images": names[3:6]}],
            "white": names[6]}


def _make_scan(folder, image=IMG, names=None, doc=None):
    folder.mkdir(parents=True, exist_ok=True)
    names = names or [f"i{k}.png" for k in range(7)]
    for n in names:
        write_png(folder / n, image)
    doc = doc if doc is not None else _doc(names)
    (folder / "scan.json").write_text(json.dumps(doc))
    return folder


@pytest.fixture
def scan_dir(tmp_path):
    return _make_scan(tmp_path / "scan")


def test_read_scan_reads_what_it_says(scan_dir):
    scan = read_scan(scan_dir)
    assert [s.shape for s in scan.stacks] == [(3, 6, 8), (3, 6, 8)]
    assert scan.max_value == 255.0 and scan.white.shape == (6, 8) and scan.black is None
    assert np.array_equal(scan.stacks[1][2], IMG)


def _write_text(folder, text, encoding="utf-8"):
    (folder / "scan.json").write_bytes(text if isinstance(text, bytes) else
                                       text.encode(encoding))


@pytest.mark.parametrize("text, token", [
    ("", "malformed JSON"),
    ("{", "malformed JSON"),
    ('{"format": "telefringe-scan",}', "malformed JSON at line 1"),
    ("[1, 2]", "JSON object"),
    ("null", "JSON object"),
    ('"scan"', "JSON object"),
    (b"\xff\xfe{}", "not UTF-8"),
    ("[" * 100_000 + "]" * 100_000, "malformed JSON"),
    ('{"version": 1' + "1" * 5000 + "}", "malformed JSON"),
])
def test_malformed_json_is_refused(scan_dir, text, token):
    _write_text(scan_dir, text)
    msg = str(pytest.raises(InputError, load_scan_manifest, scan_dir).value)
    assert str(scan_dir / "scan.json") in msg and token in msg


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e400"])
@pytest.mark.parametrize("field", ["exposure", "offset", "periods"])
def test_json_nan_and_infinity_literals(scan_dir, literal, field):
    doc = json.loads((scan_dir / "scan.json").read_text())
    doc["patterns"][0][field] = "@@"
    _write_text(scan_dir, json.dumps(doc).replace('"@@"', literal))
    msg = str(pytest.raises(InputError, load_scan_manifest, scan_dir).value)
    assert "patterns[0]" in msg and f"'{field}'" in msg
    assert "nan" in msg or "inf" in msg


def test_duplicate_keys_are_refused(scan_dir):
    text = (scan_dir / "scan.json").read_text()
    _write_text(scan_dir, text.replace('"version": 1', '"version": 1, "version": 1'))
    msg = str(pytest.raises(InputError, load_scan_manifest, scan_dir).value)
    assert "'version' appears twice" in msg


def test_a_byte_order_mark_is_accepted(scan_dir):
    _write_text(scan_dir, b"\xef\xbb\xbf" + (scan_dir / "scan.json").read_bytes())
    assert load_scan_manifest(scan_dir).projector_width == 64


def test_a_huge_manifest_is_refused_before_parsing(scan_dir):
    with open(scan_dir / "scan.json", "ab") as f:
        f.truncate(17 * 1024 * 1024)
    assert "too large" in str(pytest.raises(InputError, load_scan_manifest, scan_dir).value)


def test_missing_folder_or_manifest(tmp_path, scan_dir):
    for arg, token in [(tmp_path / "nope", "not a folder"),
                       (scan_dir / "scan.json", "give the folder that holds scan.json"),
                       (tmp_path, "no scan.json")]:
        assert token in str(pytest.raises(InputError, read_scan, arg).value)


def _edit(folder, fn):
    doc = json.loads((folder / "scan.json").read_text())
    fn(doc)
    _write_text(folder, json.dumps(doc))


@pytest.mark.parametrize("name, token", [
    ("missing.png", "is missing"),
    ("../outside.png", "leaves the folder"),
    ("sub", "is not a file"),
    ("/etc/hostname", "absolute path"),
    ("link_out.png", "outside the folder"),
    ("loop.png", "cannot"),
    ("./i1.png", "same file"),
    ("alias.png", "same file"),
])
def test_image_paths_on_disk(tmp_path, scan_dir, name, token):
    write_png(tmp_path / "outside.png", IMG)
    (scan_dir / "sub").mkdir()
    os.symlink(tmp_path / "outside.png", scan_dir / "link_out.png")
    os.symlink("loop.png", scan_dir / "loop.png")
    os.symlink("i1.png", scan_dir / "alias.png")

    def put(doc):
        doc["patterns"][0]["images"][0] = name
    _edit(scan_dir, put)
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert str(scan_dir / "scan.json") in msg and "patterns[0].images[0]" in msg
    assert token in msg


def test_symlink_inside_the_folder_and_subfolders_are_fine(scan_dir):
    (scan_dir / "sub").mkdir()
    write_png(scan_dir / "sub" / "x.png", IMG[::-1])
    os.symlink("i0.png", scan_dir / "link_in.png")

    def put(doc):
        doc["patterns"][0]["images"][:2] = ["link_in.png", "sub/x.png"]
    _edit(scan_dir, put)
    scan = read_scan(scan_dir)
    assert np.array_equal(scan.stacks[0][1], IMG[::-1])


def test_the_scan_folder_itself_may_be_a_symlink(tmp_path, scan_dir):
    os.symlink(scan_dir, tmp_path / "alias")
    assert read_scan(tmp_path / "alias").stacks[0].shape == (3, 6, 8)


def test_images_of_different_sizes_are_refused_before_decoding(scan_dir):
    write_png(scan_dir / "i4.png", np.zeros((7, 8), np.uint8))
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert "image sizes differ" in msg and "i4.png is 8 x 7" in msg


def test_mixed_bit_depths_are_refused(scan_dir):
    write_png(scan_dir / "i2.png", IMG.astype(np.uint16) * 256)
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert "bit depths differ" in msg and "i2.png is 16-bit" in msg


def test_a_decompression_bomb_in_a_scan_is_refused(scan_dir):
    (scan_dir / "i0.png").write_bytes(png_bytes(100_000, 100_000, 8, 0, rows=[b"\0"]))
    (scan_dir / "i1.png").write_bytes(png_bytes(100_000, 100_000, 8, 0, rows=[b"\0"]))
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert "i0.png" in msg and "refused before decoding" in msg


def test_a_scan_too_large_for_memory_is_refused_before_decoding(scan_dir, monkeypatch):
    import telefringe.io.scan_json as io_scan

    monkeypatch.setattr(io_scan, "MAX_SCAN_BYTES", 7 * 48 - 1)
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert "7 images of 8 x 6" in msg and "limit" in msg
    monkeypatch.setattr(io_scan, "MAX_SCAN_BYTES", 7 * 48)
    assert read_scan(scan_dir).stacks[0].shape == (3, 6, 8)


def test_a_broken_image_in_a_scan_names_the_image(scan_dir):
    data = (scan_dir / "i5.png").read_bytes()
    (scan_dir / "i5.png").write_bytes(data[: len(data) // 2])
    msg = str(pytest.raises(InputError, read_scan, scan_dir).value)
    assert "i5.png" in msg and "truncated" in msg


def test_sixteen_bit_scans_and_meta(tmp_path):
    folder = _make_scan(tmp_path / "s16", image=IMG.astype(np.uint16) * 257)
    _edit(folder, lambda d: d.update(meta={"camera": "acA1300", "gain_db": 0}))
    scan = read_scan(folder)
    assert scan.max_value == 65535.0 and scan.stacks[0].dtype == np.uint16
    assert scan.meta == {"camera": "acA1300", "gain_db": 0}


def test_progress_is_reported(scan_dir):
    calls = []
    read_scan(scan_dir, progress=lambda done, total: calls.append((done, total)))
    assert calls == [(k, 7) for k in range(1, 8)]


# --------------------------------------------------------------------------- write_scan
def _scan(stack_dtype=np.uint8, images=((), ())):
    groups = (PhaseGroup("u", 8, 3, images=images[0]), GrayGroup("u", 3, True,
                                                                 images=images[1]))
    man = ScanManifest(64, 48, groups)
    rng = np.random.default_rng(0)
    stacks = tuple(rng.integers(0, 255, (g.count, 6, 8)).astype(stack_dtype) for g in groups)
    return Scan(man, stacks, white=stacks[0][0], meta={"seed": np.int64(3)})


def test_write_scan_round_trip(tmp_path):
    scan = _scan()
    out = write_scan(tmp_path / "w", scan)
    back = read_scan(out)
    assert all(np.array_equal(a, b) for a, b in zip(scan.stacks, back.stacks, strict=True))
    assert np.array_equal(back.white, scan.white) and back.meta == {"seed": 3}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["w"]  # no temporary left
    with pytest.raises(InputError, match="already exists"):
        write_scan(tmp_path / "w", scan)
    write_scan(tmp_path / "w", scan, force=True)


@pytest.mark.parametrize("bad", ["../x.png", "/tmp/x.png", "a\\b.png"])
def test_write_scan_refuses_names_leaving_the_folder(tmp_path, bad):
    scan = _scan(images=((bad, "b.png", "c.png"), ()))
    with pytest.raises(ValueError, match="write_scan"):
        write_scan(tmp_path / "w", scan)
    assert list(tmp_path.iterdir()) == []


def test_write_scan_failure_leaves_nothing(tmp_path):
    scan = _scan(stack_dtype=np.float64)  # write_png refuses float images
    with pytest.raises(ValueError):
        write_scan(tmp_path / "w", scan)
    assert list(tmp_path.iterdir()) == []


# --------------------------------------------------------------------------- calibration
def _cal_doc(poses=("pose_00", "pose_01")):
    return {"format": CALIB_FORMAT, "version": 1,
            "target": {"type": "circle-grid", "rows": 9, "cols": 11, "pitch_mm": 3.0,
                       "diameter_mm": 1.5, "circles": "dark-on-light"},
            "camera": {"pixel_size_mm": [0.0052, 0.0052]},
            "projector": {"pixel_size_mm": [0.0137, 0.0137]},
            "poses": list(poses), "reference_pose": poses[0]}


@st.composite
def broken_cal_docs(draw):
    doc = _cal_doc()
    t = doc["target"]
    case = draw(st.sampled_from([
        "format", "version", "target", "ttype", "rows", "cols", "pitch", "diameter",
        "circles", "dia_ge_pitch", "device", "pixel_size", "poses", "pose_name",
        "dup_pose", "reference", "extra", "missing", "meta"]))
    if case == "format":
        doc["format"] = draw(st.one_of(junk, st.just(SCAN_FORMAT)))
        return doc, ["'format'"]
    if case == "version":
        doc["version"] = draw(st.one_of(st.just(True), st.just(1.0), st.just(2), junk)
                              .filter(lambda v: not (type(v) is int and v == 1)))
        return doc, ["'version'"]
    if case == "target":
        doc["target"] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, ["'target'"]
    if case == "ttype":
        t["type"] = draw(st.one_of(junk, st.sampled_from(["checkerboard", "Circle-Grid"])))
        return doc, ["'target.type'"]
    if case in ("rows", "cols"):
        t[case] = draw(bad_int(2, 1000))
        return doc, [f"'target.{case}'"]
    if case in ("pitch", "diameter"):
        key = f"{case}_mm"
        t[key] = draw(bad_positive)
        return doc, [f"'target.{key}'"]
    if case == "circles":
        t["circles"] = draw(st.one_of(junk, st.just("dark")))
        return doc, ["'target.circles'"]
    if case == "dia_ge_pitch":
        t["diameter_mm"] = t["pitch_mm"] * draw(st.floats(1.0, 10.0))
        return doc, ["'target.diameter_mm'"]
    if case == "device":
        dev = draw(st.sampled_from(["camera", "projector"]))
        doc[dev] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, [f"'{dev}'"]
    if case == "pixel_size":
        dev = draw(st.sampled_from(["camera", "projector"]))
        doc[dev]["pixel_size_mm"] = draw(st.one_of(
            junk, st.lists(st.floats(0.001, 0.01), min_size=0, max_size=1),
            st.lists(st.floats(0.001, 0.01), min_size=3, max_size=4),
            st.tuples(bad_positive, st.just(0.005)).map(list),
            st.tuples(st.just(0.005), st.floats(1.0, 1e3)).map(list)))
        return doc, [f"'{dev}.pixel_size_mm'"]
    if case == "poses":
        doc["poses"] = draw(st.one_of(junk.filter(lambda x: not isinstance(x, list)),
                                      st.just([])))
        return doc, ["'poses'"]
    if case == "pose_name":
        doc["poses"][1] = draw(bad_name)
        return doc, ["poses[1]"]
    if case == "dup_pose":
        doc["poses"][1] = draw(st.sampled_from(["pose_00", "./pose_00", "pose_00/",
                                                "pose_00/."]))
        return doc, ["poses[1]", "same folder"]
    if case == "reference":
        doc["reference_pose"] = draw(st.one_of(junk, st.just("pose_02")))
        return doc, ["'reference_pose'"]
    if case == "extra":
        obj = draw(st.sampled_from([doc, t, doc["camera"], doc["projector"]]))
        obj["pixel_pitch"] = 1
        return doc, ["unknown field", "'pixel_pitch'"]
    if case == "missing":
        key, obj, token = draw(st.sampled_from([
            ("format", doc, "'format'"), ("version", doc, "'version'"),
            ("target", doc, "'target'"), ("camera", doc, "'camera'"),
            ("projector", doc, "'projector'"), ("poses", doc, "'poses'"),
            ("rows", t, "'target.rows'"), ("pitch_mm", t, "'target.pitch_mm'"),
            ("type", t, "'target.type'"),
            ("pixel_size_mm", doc["camera"], "'camera.pixel_size_mm'")]))
        del obj[key]
        return doc, [token]
    if case == "meta":
        doc["meta"] = draw(junk.filter(lambda x: not isinstance(x, dict)))
        return doc, ["'meta'"]
    raise AssertionError(case)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(case=broken_cal_docs())
def test_broken_calibration_manifests_are_refused(case):
    doc, tokens = case
    msg = str(pytest.raises(InputError, parse_calibration_manifest, doc, where=CWHERE).value)
    assert msg.startswith(CWHERE + ":")
    for token in tokens:
        assert token in msg, (token, msg)


@pytest.fixture(scope="module")
def stub_cal_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("stub_cal")
    for p in ("pose_00", "pose_01"):
        _make_scan(folder / p)
    return folder


@settings(max_examples=120, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=broken_cal_docs())
def test_broken_calibration_manifests_on_disk(stub_cal_dir, case):
    doc, tokens = case
    path = stub_cal_dir / "calibration.json"
    path.write_text(json.dumps(doc))
    msg = str(pytest.raises(InputError, load_calibration_set, stub_cal_dir).value)
    assert msg.startswith(str(path) + ":")
    for token in tokens:
        assert token in msg, (token, msg)


def test_valid_calibration_manifest_defaults():
    doc = _cal_doc()
    del doc["reference_pose"], doc["target"]["circles"]
    man = parse_calibration_manifest(doc)
    assert man.reference_pose == "pose_00" and man.target.circles == "dark-on-light"
    assert man.camera_pixel_size == (0.0052, 0.0052) and man.poses == ("pose_00", "pose_01")
    assert man.target.points_target().shape == (99, 3)


@pytest.fixture
def cal_dir(tmp_path):
    folder = tmp_path / "cal"
    for p in ("pose_00", "pose_01"):
        _make_scan(folder / p)
    (folder / "calibration.json").write_text(json.dumps(_cal_doc()))
    return folder


def test_load_calibration_set(cal_dir):
    man = load_calibration_set(cal_dir)
    assert man.poses == ("pose_00", "pose_01") and man.folder == str(cal_dir)


def _cal_edit(folder, fn):
    doc = json.loads((folder / "calibration.json").read_text())
    fn(doc)
    (folder / "calibration.json").write_text(json.dumps(doc))


@pytest.mark.parametrize("pose, token", [
    ("pose_09", "is missing"),
    ("../elsewhere", "leaves the folder"),
    ("out_link", "outside the folder"),
    ("afile", "is not a folder"),
    ("empty", "no scan.json"),
    ("pose_alias", "same folder"),
])
def test_pose_folders_on_disk(tmp_path, cal_dir, pose, token):
    _make_scan(tmp_path / "elsewhere")
    os.symlink(tmp_path / "elsewhere", cal_dir / "out_link")
    os.symlink("pose_00", cal_dir / "pose_alias")
    (cal_dir / "afile").write_text("x")
    (cal_dir / "empty").mkdir()
    _cal_edit(cal_dir, lambda d: d["poses"].__setitem__(1, pose))
    msg = str(pytest.raises(InputError, load_calibration_set, cal_dir).value)
    assert str(cal_dir / "calibration.json") in msg and "poses[1]" in msg and token in msg


def test_a_broken_pose_manifest_names_the_pose(cal_dir):
    _edit(cal_dir / "pose_01", lambda d: d.update(version=2))
    msg = str(pytest.raises(InputError, load_calibration_set, cal_dir).value)
    assert str(cal_dir / "pose_01" / "scan.json") in msg and "'version'" in msg


def test_poses_of_different_sizes_are_refused(cal_dir):
    _edit(cal_dir / "pose_01", lambda d: d["projector"].update(width=80))
    msg = str(pytest.raises(InputError, load_calibration_set, cal_dir).value)
    assert "poses differ" in msg and "pose_01" in msg
    _edit(cal_dir / "pose_01", lambda d: d["projector"].update(width=64))
    for k in range(7):
        write_png(cal_dir / "pose_01" / f"i{k}.png", np.zeros((5, 8), np.uint8))
    msg = str(pytest.raises(InputError, load_calibration_set, cal_dir).value)
    assert "poses differ" in msg and "8 x 5" in msg


def test_write_calibration_manifest_round_trip(cal_dir):
    man = CalibrationSetManifest(CircleGridTarget(9, 11, 3.0, 1.5), (0.0052, 0.0052),
                                 (0.0137, 0.0137), ("pose_01", "pose_00"), "pose_01")
    write_calibration_manifest(cal_dir, man)
    back = load_calibration_set(cal_dir)
    assert back.poses == man.poses and back.target == man.target
    assert [p.name for p in cal_dir.iterdir() if p.name.startswith(".")] == []


@pytest.mark.parametrize("kw", [dict(rows=1), dict(cols=2.5), dict(pitch_mm=0.0),
                                dict(diameter_mm=float("nan")), dict(diameter_mm=3.0),
                                dict(circles="dark"), dict(rows=True)])
def test_circle_grid_target_validates(kw):
    args = {"rows": 9, "cols": 11, "pitch_mm": 3.0, "diameter_mm": 1.5, **kw}
    with pytest.raises(ValueError, match="CircleGridTarget"):
        CircleGridTarget(**args)
