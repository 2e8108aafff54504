"""Identify a lot of recordings on a Dask cluster.

    pip install "./python[dask]"
    python python/examples/identify_lot_on_dask.py lot/ 0.0145 [tcp://scheduler:8786]

Each WAV in the directory (voltage and current, as `coilscope identify` reads it) is one task;
Dask schedules them on the cluster's workers. Without a scheduler's address a local cluster of
this machine's cores is started. Each result is the one `coilscope identify REC.wav --mms KG`
gives; one JSON file per record is written beside it, and a line per record says whether its
fit is trustworthy.
"""

import json
import pathlib
import sys

from dask.distributed import Client, LocalCluster

import coilscope


def main(directory, mms, address=None):
    paths = sorted(pathlib.Path(directory).glob("*.wav"))
    if not paths:
        sys.exit(f"{directory}: no .wav recordings")
    if address is None:
        with LocalCluster(threads_per_worker=1) as cluster, Client(cluster) as client:
            results = coilscope.identify_lot(paths, mms, client)
    else:
        with Client(address) as client:
            results = coilscope.identify_lot(paths, mms, client)
    for path, r in zip(paths, results):
        path.with_suffix(".result.json").write_text(json.dumps(r, indent=1))
        trusted = r["fit"].get("trustworthy", True)
        bl0 = r["parameters"]["Bl"][0] if isinstance(r["parameters"]["Bl"], list) else r["parameters"]["Bl"]
        print(f"{path.name}: Bl(0) {bl0:.4f} T m, Re {r['parameters']['Re']:.4f} ohm, {'trusted' if trusted else 'NOT TRUSTED'}")


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(__doc__)
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3] if len(sys.argv) == 4 else None)
