"""A lot of recordings identified on a Dask cluster: the results equal the single runs."""

import json

import numpy as np
from dask.distributed import Client, LocalCluster

import coilscope

FS = 48000


def _lot(tmp_path, n):
    """``n`` records of SB17 (2.5 s of pink noise each, levels and seeds of their own)."""
    p = coilscope.parameters("sb17cac35-4")
    paths = []
    for k in range(n):
        u = coilscope.generate("pink", FS, 2.5, 1.6 + 0.1 * k, seed=40 + k, band=(10, 8000))
        t = coilscope.simulate(p, u, FS)
        path = tmp_path / f"unit{k}.wav"
        coilscope.write_recording(path, u, t["i"], FS)
        paths.append(path)
    return p, paths


def _same(a, b):
    """The figures of two results, compared to the last bit (timings and the like aside)."""
    for key in ("parameters", "uncertainty"):
        assert json.dumps(a[key], sort_keys=True) == json.dumps(b[key], sort_keys=True), key
    assert a["fit"]["trustworthy"] == b["fit"]["trustworthy"]
    assert a["recording"] == b["recording"]


def test_a_recording_round_trips_through_its_file(tmp_path):
    u = np.sin(np.arange(4800) * 0.01)
    i = 0.1 * np.cos(np.arange(4800) * 0.01)
    coilscope.write_recording(tmp_path / "r.wav", u, i, FS)
    r = coilscope.read_recording(tmp_path / "r.wav")
    assert r["fs"] == FS and r["x"] is None
    # 32-bit float samples.
    assert np.max(np.abs(r["u"] - u)) < 1e-7 and np.max(np.abs(r["i"] - i)) < 1e-8


def test_eight_records_on_a_local_dask_cluster_equal_the_single_runs(tmp_path):
    p, paths = _lot(tmp_path, 8)
    single = [coilscope.identify_file(path, p["Mms"]) for path in paths]
    for r in single:
        lo, hi = r["fit"]["x_range"]
        xs = np.linspace(0.8 * lo, 0.8 * hi, 21)
        err = np.max(np.abs(coilscope.poly(r["parameters"]["Bl"], xs) / coilscope.poly(p["Bl"], xs) - 1))
        assert err < 0.01, (r["recording"], err)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        with Client(cluster) as client:
            on_cluster = coilscope.identify_lot(paths, p["Mms"], client)
            # The tasks ran on the workers, not here.
            assert sum(len(v) for v in client.has_what().values()) >= 1
    assert len(on_cluster) == len(single)
    for a, b in zip(single, on_cluster):
        _same(a, b)
    # Without a client: one after the other, the same again.
    for a, b in zip(single[:2], coilscope.identify_lot(paths[:2], p["Mms"])):
        _same(a, b)
