"""Download and conversion as Ray tasks on a real two-node cluster (one CPU each, on 127.0.0.1):
the same bytes as the local path, both nodes at work, and a worker node removed while it runs a
shard without changing the output. Shards come from an HTTP server on 127.0.0.1 that holds the
first two requests until both arrived: two tasks in flight at once, on two one-CPU nodes, so both
nodes took a shard (no sleep, no timing)."""

from __future__ import annotations

import http.server
import threading
from pathlib import Path

import pytest

from rlu.cli import main
from rlu.data.release import catalog
from rlu.data.release import families as Fm
from rlu.data.release.jobs import DatasetJob, Fetch, convert_release
from rlu.data.release.load import load_release_dataset, release_dataset_path
from rlu.workers import Backend, run_jobs, send
from tests.release.ray_cluster import loopback_cluster, remove_node_now
from tests.release.test_convert import _windows
from tests.release.test_jobs import same_bytes
from tests.servers import direct, serve

ray = pytest.importorskip("ray")

TASKS = ("control_suite/walker_walk", "control_suite/cheetah_run")
WAIT = 120  # seconds a held request waits for its pair before the test fails (never reached)


class _Bucket(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):
        pass

    def do_GET(self):  # noqa: N802
        srv = self.server
        name = self.path.lstrip("/")
        body = srv.files.get(name)
        if body is None:
            self.send_error(404)
            return
        with srv.lock:
            srv.requests.append(name)
            held = srv.hold and len(srv.requests) <= 2
        if held:  # the first two requests wait for each other
            if srv.pair.wait(WAIT) == 0:  # exactly one of the two gets 0
                srv.on_pair()
                srv.released.set()
            srv.released.wait(WAIT)
        try:
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)
        except OSError:  # the client was on the node the test removed
            pass


@pytest.fixture
def bucket(monkeypatch, tmp_path):
    direct(monkeypatch)
    files = {}
    for t, task in enumerate(TASKS):
        for i, obj in enumerate(catalog.select(task, shards="0-2").objects):
            p = tmp_path / "shard"
            Fm.write_shard(p, "dm_control_suite", _windows(task, 16, seed=10 * t + i))
            files[obj] = p.read_bytes()
    with serve(
        _Bucket, files=files, requests=[], lock=threading.Lock(), hold=True,
        pair=threading.Barrier(2), released=threading.Event(), on_pair=lambda: None,
    ) as srv:  # fmt: skip
        yield srv
        srv.pair.abort()  # a handler still waiting for its pair returns
        srv.released.set()


def local_datasets(bucket, tmp_path: Path) -> list[Path]:
    """What the local path makes of the same shards: load_dataset(source="release")."""
    return [
        load_release_dataset(
            task, cache_dir=tmp_path / "local", base_url=bucket.url, shards="0-2", progress=False
        ).path
        for task in TASKS
    ]


def test_two_nodes_convert_many_tasks_to_the_local_bytes(tmp_path, bucket):
    cache = tmp_path / "shared"
    with loopback_cluster((1, 1)) as (cluster, nodes):
        code = main(
            ["download", *TASKS, "--shards", "0-2", "--cache-dir", str(cache), "--base-url",
             bucket.url, "--backend", "ray", "--ray-address", cluster.address, "-q"]
        )  # fmt: skip
        assert code == 0  # then the conversion's shard jobs reuse them, verified
        code = main(
            ["convert", "--family", "dm_control_suite", "--task", ",".join(TASKS), "--download",
             "--shards", "0-2", "--cache-dir", str(cache), "--base-url", bucket.url,
             "--backend", "ray", "--ray-address", cluster.address, "-q"]
        )  # fmt: skip
        assert code == 0
        # what jobs send comes back to the driver, every message before the job's result
        got, results = [], []
        run_jobs(
            send,
            [((f"m{i}", i),) for i in range(4)],
            Backend("ray", address=cluster.address),
            on_result=lambda i, r: results.append(len(got)),
            on_message=got.append,
        )
        assert sorted(got) == [(f"m{i}", i) for i in range(4)] and len(results) == 4
        assert all(seen >= k + 1 for k, seen in enumerate(results))
    assert len(bucket.requests) == 6  # each shard fetched once; the first two at the same time
    bucket.hold = False  # the local path takes its shards one at a time
    for want, task in zip(local_datasets(bucket, tmp_path), TASKS, strict=True):
        sel = catalog.select(task, shards="0-2")
        same_bytes(want, Path(release_dataset_path(sel, cache, all_shards=False)))


def test_a_node_removed_mid_job_changes_nothing(tmp_path, bucket):
    cache = tmp_path / "shared"
    objects = [o for task in TASKS for o in catalog.select(task, shards="0-2").objects]
    jobs = [
        DatasetJob(
            task, "dm_control_suite",
            release_dataset_path(catalog.select(task, shards="0-2"), cache, all_shards=False),
            tuple(catalog.select(task, shards="0-2").objects), "",
        )
        for task in TASKS
    ]  # fmt: skip
    with loopback_cluster((1, 1)) as (cluster, nodes):
        ray.init(address=cluster.address, log_to_driver=False)
        driver = ray.get_runtime_context().get_node_id()
        victim = next(n for n in nodes if n.node_id != driver)
        # both nodes hold a shard's download: remove one of them, then let the downloads go on
        bucket.on_pair = lambda: remove_node_now(cluster, victim)
        report = convert_release(
            jobs, Backend("ray", address=cluster.address), fetch=Fetch(str(cache), bucket.url)
        )
        ray.shutdown()
    # the victim's shard was lost with it and run again on the other node: no result came
    # from the victim, every shard has its part, the datasets are the local bytes
    assert victim.node_id not in report.nodes
    assert report.shards == len(objects) and sum(n["shards"] for n in report.nodes.values()) == 6
    assert all(d.status == "converted" for d in report.datasets)
    bucket.hold = False
    for want, job in zip(local_datasets(bucket, tmp_path), jobs, strict=True):
        same_bytes(want, Path(job.out))
