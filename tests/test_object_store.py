"""Datasets on an S3 object store: a real S3 API (moto's server) on 127.0.0.1, written through pyarrow URIs."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

moto_server = pytest.importorskip("moto.server")

from roken.data import fs  # noqa: E402
from roken.data.shards import read_table  # noqa: E402
from roken.data.store import read_json, read_run  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CREDS = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}


@pytest.fixture(scope="module")
def bucket_uri():
    import pyarrow.fs as pafs

    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    old = {k: os.environ.get(k) for k in CREDS}
    os.environ.update(CREDS)
    pafs.S3FileSystem(endpoint_override=f"{host}:{port}", scheme="http", region="us-east-1",
                      allow_bucket_creation=True).create_dir("roken")
    yield lambda prefix: f"s3://roken/{prefix}?endpoint_override={host}:{port}&scheme=http&region=us-east-1"
    for k, v in old.items():
        if v is None:
            os.environ.pop(k, None)
        else:
            os.environ[k] = v
    server.stop()


def test_generate_into_s3_and_read_back(bucket_uri):
    uri = bucket_uri("ds")
    cmd = [sys.executable, str(ROOT / "pipelines" / "generate.py"), "--num-maps", "2", "--episodes-per-map", "2",
           "--set", "dataset.maps_per_unit=1", "--out", uri, "--workers", "0"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, **CREDS})
    assert r.returncode == 0, r.stderr
    assert [f.rsplit("/", 1)[1].split("?")[0] for f in fs.list_files(fs.join(uri, "episodes"), ".parquet")] \
        == ["unit-00000.parquet", "unit-00001.parquet"]
    manifest = read_json(fs.join(uri, "manifest.json"))
    maps, eps = read_run(uri)
    assert manifest["status"] == "complete" and manifest["episodes"] == len(eps) > 0 and len(maps) == 2
    assert read_table(uri).num_rows == len(eps)
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env={**os.environ, **CREDS})
    assert r.returncode == 0 and "2 finished earlier, 0 to run" in r.stderr  # resume works on S3 too
    assert json.loads(json.dumps(read_json(fs.join(uri, "manifest.json"))))["throughput"]["episodes_run"] == 0
