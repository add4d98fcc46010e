"""Conversion as one job per shard (rlu.data.release.jobs) on the local backend: the same bytes as
the local conversion for any number of workers, resume at shard granularity (finished parts
reused, damaged ones made again), downloads in the shard jobs equal to load_dataset's, the CLI
over many tasks. The Ray cluster runs are in test_jobs_ray.py."""

from __future__ import annotations

import gzip
import http.server
import json
from pathlib import Path

import numpy as np
import pytest

from rlu.cli import main
from rlu.data.release import families as Fm
from rlu.data.release.convert import convert
from rlu.data.release.jobs import DatasetJob, Fetch, convert_release, parts_folder
from rlu.data.release.load import load_release_dataset
from rlu.data.store import open_dataset
from rlu.types import RluError
from rlu.workers import Backend
from tests.release.test_convert import _windows
from tests.release.test_families import atari_episode, atari_record
from tests.servers import direct, serve

TASK = "control_suite/walker_walk"


def same_bytes(a: Path, b: Path) -> None:
    """Every file of dataset ``a`` is in ``b`` with the same bytes, and no other."""
    fa = sorted(str(p.relative_to(a)) for p in Path(a).rglob("*") if p.is_file())
    fb = sorted(str(p.relative_to(b)) for p in Path(b).rglob("*") if p.is_file())
    assert fa == fb
    for rel in fa:
        assert (Path(a) / rel).read_bytes() == (Path(b) / rel).read_bytes(), rel


def shards(root: Path, family: str, folder: str, recs: list[list[dict]], base: str) -> list[str]:
    d = root / family / folder
    d.mkdir(parents=True, exist_ok=True)
    out = []
    for i, r in enumerate(recs):
        p = d / f"{base}-{i:05d}-of-{len(recs):05d}"
        Fm.write_shard(p, family, r)
        out.append(str(p))
    return out


CASES = {
    "control": (
        "dm_control_suite",
        TASK,
        "walker_walk",
        "train",
        lambda i: _windows(TASK, 30, seed=i),
    ),
    "atari": (  # frames deflated in the shard jobs
        "atari",
        "atari/Pong",
        "Pong",
        "run_2",
        lambda i: [
            atari_record(np.random.default_rng(10 * i + j), float(j % 5 > 0)) for j in range(8)
        ],
    ),
    "atari_episodes": (  # frame-stacked: the frame index of each part shifted
        "atari_episodes_ordered",
        "atari/Pong",
        "Pong",
        "run_1",
        lambda i: [
            atari_episode(np.random.default_rng(i), 6 + i),
            atari_episode(np.random.default_rng(9 + i), 4, 1.0),
        ],
    ),
}  # fmt: skip


@pytest.mark.parametrize("case", CASES)
def test_job_writes_the_local_conversions_bytes(tmp_path, case):
    family, task, folder, base, make = CASES[case]
    paths = shards(tmp_path / "src", family, folder, [make(i) for i in range(3)], base)
    convert(paths, family, task, tmp_path / "local", workers=1)
    for w in (1, 2):
        out = tmp_path / f"job{w}"
        job = DatasetJob(task, family, str(out), tuple(paths))
        report = convert_release([job], Backend("local", w))
        same_bytes(tmp_path / "local", out)
        assert report.converted == 3 and report.reused == 0
        assert report.datasets[0].status == "converted"
        assert not parts_folder(out).exists()  # the parts go once assembled
    assert len(open_dataset(tmp_path / "job2", verify=True)) > 0


def test_interrupted_job_converts_only_unfinished_shards(tmp_path):
    recs = [_windows(TASK, 30, seed=i) for i in range(4)]
    paths = shards(tmp_path / "src", "dm_control_suite", "walker_walk", recs, "train")
    good = Path(paths[2]).read_bytes()
    raw = bytearray(gzip.decompress(good))
    raw[len(raw) // 2] ^= 0xFF
    Path(paths[2]).write_bytes(gzip.compress(bytes(raw)))
    out = tmp_path / "ds"
    job = DatasetJob(TASK, "dm_control_suite", str(out), tuple(paths))
    with pytest.raises(RluError, match="CRC mismatch"):
        convert_release([job], Backend("local", 1))
    assert not out.exists()
    kept = sorted(p.name for p in parts_folder(out).iterdir() if not p.name.startswith("."))
    assert kept == ["00000", "00001"]  # finished before the damaged shard: kept, complete
    Path(paths[2]).write_bytes(good)  # downloaded again
    report = convert_release([job], Backend("local", 2))
    assert (report.reused, report.converted) == (2, 2)
    convert(paths, "dm_control_suite", TASK, tmp_path / "local", workers=1)
    same_bytes(tmp_path / "local", out)
    # a dataset already made is left as it is; a damaged or foreign part is made again
    again = convert_release([job], Backend("local", 1))
    assert again.datasets[0].status == "existed" and again.shards == 0
    out2 = tmp_path / "ds2"
    job2 = DatasetJob(TASK, "dm_control_suite", str(out2), tuple(paths))
    Path(paths[1]).write_bytes(b"")  # stop the next job after its first shard
    with pytest.raises(RluError):
        convert_release([job2], Backend("local", 1))
    Fm.write_shard(paths[1], "dm_control_suite", recs[1])
    part = parts_folder(out2) / "00000"
    column = next((part / "steps").glob("action.bin"))
    data = bytearray(column.read_bytes())
    data[0] ^= 0xFF
    column.write_bytes(bytes(data))
    report = convert_release([job2], Backend("local", 1))
    assert (report.reused, report.converted) == (0, 4)  # the damaged part failed its sha256
    same_bytes(tmp_path / "local", out2)


class _Bucket(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):
        pass

    def do_GET(self):  # noqa: N802
        body = self.server.files.get(self.path.lstrip("/"))
        if body is None:
            self.send_error(404)
            return
        self.send_response(200)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)


@pytest.fixture
def bucket(monkeypatch):
    direct(monkeypatch)
    with serve(_Bucket, files={}) as srv:
        yield srv


def serve_walker(bucket, tmp_path: Path, n: int = 3) -> None:
    """The walker_walk seq2 dataset as the bucket names it, cut to ``n`` shards."""
    from rlu.data.release import catalog

    sel = catalog.select(TASK, shards=list(range(n)))
    for i, obj in enumerate(sel.objects):
        p = tmp_path / "shard"
        Fm.write_shard(p, "dm_control_suite", _windows(TASK, 20, seed=i))
        bucket.files[obj] = p.read_bytes()


def test_download_in_the_shard_jobs_equals_load_dataset(tmp_path, bucket):
    serve_walker(bucket, tmp_path)
    ds = load_release_dataset(
        TASK, cache_dir=tmp_path / "one", base_url=bucket.url, shards="0-2", progress=False
    )
    cache = tmp_path / "shared"
    code = main(
        ["convert", "--family", "dm_control_suite", "--task", TASK, "--download", "--shards",
         "0-2", "--cache-dir", str(cache), "--base-url", bucket.url, "--workers", "2", "-q"]
    )  # fmt: skip
    assert code == 0
    mine = load_release_dataset(TASK, cache_dir=cache, shards="0-2", progress=False)  # no network
    same_bytes(ds.path, mine.path)
    assert json.loads((mine.path / "manifest.json").read_text())["provenance"]["sha256"]


def test_cli_many_tasks_under_out_root(tmp_path, capsys):
    root = tmp_path / "bucket"
    made = {}
    for game, actions in (("Pong", 6), ("Breakout", 4)):
        recs = [
            [atari_record(np.random.default_rng(j + 7 * i), num_actions=actions) for j in range(3)]
            for i in range(2)
        ]
        made[game] = shards(root, "atari", game, recs, "run_1")
    out = tmp_path / "datasets"
    args = ["convert", "--family", "atari", "--run", "1", "--src", str(root), "-q"]
    code = main([*args, "--task", "atari/Pong,atari/Breakout", "--out-root", str(out)])
    assert code == 0
    text = capsys.readouterr().out
    assert "2 of 2 datasets converted" in text
    for game, paths in made.items():
        convert(paths, "atari", f"atari/{game}", tmp_path / game, workers=1)
        same_bytes(tmp_path / game, out / "atari" / game / "atari" / "run_1")
    # a pattern the registry does not match, and --out for several datasets, are refused
    assert main([*args, "--task", "atari/Nope*", "--out-root", str(out)]) == 2
    assert "no registered task matches" in capsys.readouterr().err
    assert main([*args, "--task", "atari/Pong", "--task", "atari/Breakout", "--out", "x"]) == 2
    assert "--out-root" in capsys.readouterr().err


def test_object_store_urls_are_refused(tmp_path):
    job = DatasetJob(TASK, "dm_control_suite", "s3://bucket/ds", ("x",))
    with pytest.raises(RluError, match="object-store URL"):
        convert_release([job], Backend("local", 1))
    with pytest.raises(RluError, match="object-store URL"):
        convert_release([], Backend("local", 1), fetch=Fetch("gs://rl_unplugged"))
