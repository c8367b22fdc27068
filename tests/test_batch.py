"""telefringe.batch and `telefringe batch`: many scans on a real dask.distributed
LocalCluster (worker processes on loopback, no dashboard): the table's schema, a failing
scan among good ones, resuming, an interrupted batch, and a worker killed mid-batch.

Small scans (the fast rig read out in a 120 x 100 px window around the sphere), the
nonlinearity correction off (it is tested elsewhere; here it would only cost time)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import time
import warnings

import distributed
import numpy as np
import pandas as pd
import pytest

import telefringe.simulate.render as sim
from telefringe.batch import FIXED_COLUMNS, FIXED_TYPES, measure_many
from telefringe.batch.scans import expand_scans, scan_names
from telefringe.cli import main
from telefringe.io.errors import InputError
from telefringe.io.rig_json import bare_rig_json
from telefringe.io.scan_json import write_scan
from telefringe.simulate import scenes
from telefringe.simulate.presets import crop_camera, get_preset

OPTS = {"measure": "sphere", "gamma_correction": False}


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Three sphere scans, a folder that is not a valid scan, and the true rig's rig.json."""
    root = tmp_path_factory.mktemp("batch")
    vr = crop_camera(get_preset("fast"), col0=100, row0=80, width=120, height=100)
    for s in range(3):
        scan, _ = sim.render_scan(vr, scenes.make_scene("sphere"), sim.default_groups(vr),
                                  seed=s)
        (root / "runs" / f"s{s}").mkdir(parents=True)
        write_scan(root / "runs" / f"s{s}" / "scan", scan)
    (root / "runs" / "bad" / "scan").mkdir(parents=True)
    (root / "runs" / "bad" / "scan" / "scan.json").write_text("{}")
    (root / "rig.json").write_text(json.dumps(bare_rig_json(vr.rig)))
    return root


@pytest.fixture(scope="module")
def client():
    """A LocalCluster of two single-threaded worker processes on loopback."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cluster = distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address=None, silence_logs=50, env={"NUMBA_NUM_THREADS": "1"})
        c = distributed.Client(cluster)
    yield c
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c.close()
        cluster.close()


def _good(root):
    return [str(root / "runs" / f"s{s}" / "scan") for s in range(3)]


def test_expand_scans_and_names(data, tmp_path):
    lst = tmp_path / "scans.txt"
    lst.write_text(f"# two scans\n{data / 'runs' / 's1' / 'scan'}\n\n"
                   f"{data / 'runs' / 's0' / 'scan'}\n")
    got = expand_scans([str(data / "runs" / "s*" / "scan"), lst])
    assert got == [data / "runs" / f"s{s}" / "scan" for s in range(3)]  # each once
    assert scan_names(got) == ["s0__scan", "s1__scan", "s2__scan"]
    with pytest.raises(InputError, match="matches no folder"):
        expand_scans([str(data / "nothing*")])
    with pytest.raises(InputError, match="no such scan"):
        expand_scans([str(data / "absent")])


def test_table_schema_failing_scan_and_same_as_plain_loop(data, client, tmp_path):
    scans = [str(data / "runs" / "*" / "scan")]
    seen = []
    frame = measure_many(scans, data / "rig.json", output=tmp_path / "out", client=client,
                         progress=lambda done, n, row: seen.append((done, n, row["scan"])),
                         **OPTS)
    assert sorted(s for _, _, s in seen) == ["bad__scan", "s0__scan", "s1__scan", "s2__scan"]
    assert [d for d, _, _ in seen] == [1, 2, 3, 4]
    # the fixed columns first, with their types; then the sphere's figures and their
    # uncertainties
    assert list(frame.columns[:len(FIXED_COLUMNS)]) == list(FIXED_COLUMNS)
    for c, t in FIXED_TYPES.items():
        assert str(frame[c].dtype) == t, c
    for c in ("sphere.radius_mm", "sphere.sigma_radius_mm", "sphere.centre_mm.x",
              "sphere.sigma_centre_mm.z", "sphere.base_plane.sigma_offset_mm"):
        assert frame[c].dtype == np.float64, c
    # rows in the order given (the pattern's matches sorted); the bad folder failed
    # with its one-line reason, the others were measured
    assert list(frame["scan"]) == ["bad__scan", "s0__scan", "s1__scan", "s2__scan"]
    bad = frame.iloc[0]
    assert bad["status"] == "failed" and "scan.json" in bad["error"]
    assert "\n" not in bad["error"] and pd.isna(bad["sphere.radius_mm"])
    ok = frame.iloc[1:]
    assert (ok["status"] == "ok").all() and (ok["error"] == "").all()
    assert not ok["reused"].any()
    assert (ok["t_total_s"] >= ok["t_reconstruct_s"]).all()
    # the sphere (radius 3 mm) within 5 sigma
    z = (ok["sphere.radius_mm"] - 3.0) / ok["sphere.sigma_radius_mm"]
    assert (z.abs() < 5).all(), z
    # the table on disk is the one returned; the journal is gone; each scan's outputs
    back = pd.read_parquet(tmp_path / "out" / "results.parquet")
    pd.testing.assert_frame_equal(back, frame)
    csv = pd.read_csv(tmp_path / "out" / "results.csv")
    np.testing.assert_array_equal(csv["sphere.radius_mm"], frame["sphere.radius_mm"])
    assert not (tmp_path / "out" / "results.partial.jsonl").exists()
    for name in ok["scan"]:
        folder = tmp_path / "out" / "scans" / name
        assert {"points.npz", "measurement.json", "row.json"} <= {p.name for p in
                                                                 folder.iterdir()}
    assert not (tmp_path / "out" / "scans" / "bad__scan").exists()
    # the same figures as one scan after another in this process
    plain = measure_many(_good(data), data / "rig.json", workers=0, **OPTS)
    cols = [c for c in frame.columns if c.startswith("sphere.")]
    pd.testing.assert_frame_equal(plain[cols].reset_index(drop=True),
                                  ok[cols].reset_index(drop=True))


def _touch_image(scan_dir):
    """Change one pixel of one image of a scan (a new capture of the same part)."""
    from telefringe.io.images import read_image, write_png

    p = scan_dir / "u_064_4s_00.png"
    img = read_image(p)
    img[0, 0] = 255 - img[0, 0]
    write_png(p, img)


def test_resume_force_and_changed_inputs(data, client, tmp_path):
    root = tmp_path / "runs"
    shutil.copytree(data / "runs", root, ignore=shutil.ignore_patterns("bad"))
    scans = [str(root / "*" / "scan")]
    out = tmp_path / "out"
    first = measure_many(scans, data / "rig.json", output=out, client=client, **OPTS)
    again = measure_many(scans, data / "rig.json", output=out, client=client, **OPTS)
    assert first["reused"].sum() == 0 and again["reused"].all()
    assert list(again["key"]) == list(first["key"])
    pd.testing.assert_series_equal(again["sphere.radius_mm"], first["sphere.radius_mm"])
    # one scan's images changed: that scan alone is redone
    _touch_image(root / "s1" / "scan")
    third = measure_many(scans, data / "rig.json", output=out, client=client, **OPTS)
    assert list(third["reused"]) == [True, False, True]
    assert third["key"][1] != first["key"][1]
    # other options: every scan is redone; --force too
    other = measure_many(scans, data / "rig.json", output=out, client=client,
                         min_height=0.1, **OPTS)
    assert not other["reused"].any()
    forced = measure_many(scans, data / "rig.json", output=out, client=client, force=True,
                          min_height=0.1, **OPTS)
    assert not forced["reused"].any()
    assert list(forced["key"]) == list(other["key"])


def test_interrupted_batch_keeps_finished_rows(data, tmp_path):
    out = tmp_path / "out"

    def stop_after_two(done, n, row):
        if done == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        measure_many(_good(data), data / "rig.json", output=out, workers=0,
                     progress=stop_after_two, **OPTS)
    assert not (out / "results.parquet").exists()
    rows = [json.loads(line) for line in
            (out / "results.partial.jsonl").read_text().splitlines()]
    assert [r["scan"] for r in rows] == ["s0__scan", "s1__scan"]
    assert all(r["status"] == "ok" for r in rows)
    frame = measure_many(_good(data), data / "rig.json", output=out, workers=0, **OPTS)
    assert list(frame["reused"]) == [True, True, False]


def test_cli_batch_on_a_running_scheduler(data, client, tmp_path, capsys):
    out = tmp_path / "out"
    args = ["batch", str(data / "runs" / "*" / "scan"), "--rig", str(data / "rig.json"),
            "--measure", "sphere", "--no-gamma-correction", "-o", str(out),
            "--scheduler", client.scheduler.address]
    assert main(args) == 1  # the exit status: one scan failed
    text = capsys.readouterr().out
    assert "3 of 4 scans measured" in text and "bad__scan" in text
    frame = pd.read_parquet(out / "results.parquet")
    assert list(frame["status"]) == ["failed", "ok", "ok", "ok"]
    # bad input: exit 2, nothing run
    assert main(["batch", str(data / "absent"), "--rig", str(data / "rig.json"),
                 "-o", str(tmp_path / "o2"), "--workers", "0"]) == 2
    assert not (tmp_path / "o2").exists()
    assert main(["batch", _good(data)[0], "--rig", str(data / "runs"), "-o",
                 str(tmp_path / "o3"), "--workers", "0"]) == 2


def test_worker_killed_mid_batch(data, client, tmp_path):
    """SIGKILL a worker process while it runs a scan: the scan is run again elsewhere,
    every scan has one row and one output folder, nothing half-written is left."""
    root = tmp_path / "runs"
    for k in range(6):  # six scans: copies of the three
        shutil.copytree(data / "runs" / f"s{k % 3}" / "scan", root / f"c{k}" / "scan")
    pids = client.run(os.getpid)
    killed = {}

    def kill_a_busy_worker(done, n, row):
        if killed:
            return
        busy = client.processing()
        for addr, keys in busy.items():
            if keys and addr in pids:
                killed.update(pid=pids[addr], keys=list(keys))
                os.kill(pids[addr], signal.SIGKILL)
                return

    out = tmp_path / "out"
    frame = measure_many([str(root / "*" / "scan")], data / "rig.json", output=out,
                         client=client, progress=kill_a_busy_worker, **OPTS)
    assert killed, "no worker was busy when the first scan finished"
    with pytest.raises(ProcessLookupError):
        os.kill(killed["pid"], 0)  # it is gone
    assert list(frame["scan"]) == [f"c{k}__scan" for k in range(6)]
    assert (frame["status"] == "ok").all(), frame["error"].tolist()
    # the scans that were on the killed worker have their rows: finished by another
    # process, or by the killed one in the instant between the scheduler's snapshot and
    # the signal (a race the test cannot close; under load it happens), never lost
    lost = [int(k.rsplit("-", 1)[1]) for k in killed["keys"]]
    assert all(frame["status"][i] == "ok" and frame["worker"][i] for i in lost)
    names = sorted(p.name for p in (out / "scans").iterdir())
    assert names == [f"c{k}__scan" for k in range(6)]  # no .part folder left
    assert not (out / "results.partial.jsonl").exists()
    pd.testing.assert_frame_equal(pd.read_parquet(out / "results.parquet"), frame)
    # the cluster replaces the worker
    t0 = time.monotonic()
    while len(client.scheduler_info()["workers"]) < 2 and time.monotonic() - t0 < 60:
        time.sleep(0.2)
