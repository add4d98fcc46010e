"""``rlu.load_dataset(TASK)``: the shipped dataset, a converted or downloaded one in the cache, or
one line naming the command that fetches it. Never the network (a server on 127.0.0.1 serves the
one download the test makes itself, and is emptied before the load)."""

from __future__ import annotations

import functools
import http.server

import pytest

import rlu
from rlu.data.release import catalog
from rlu.data.release.download import Downloader
from rlu.data.release.load import release_dataset_path
from rlu.data.store import Schema
from rlu.data.synthetic import write_synthetic
from rlu.tasks import get_task
from rlu.types import RluError
from tests.servers import serve

SHARD = "dm_control_suite/cartpole_swingup/train-00000-of-00001"  # in the fixtures
OBJECT = "dm_control_suite/cartpole_swingup/train-00000-of-00100"  # its name in the bucket


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("RLU_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_the_shipped_dataset_loads_by_its_task_id():
    ds = rlu.load_dataset("control_suite/cartpole_swingup")
    assert ds.schema.task_id == "control_suite/cartpole_swingup"
    assert (len(ds), ds.num_steps) == (40, 40040)
    assert ds.path.parent.name == "control_suite" and ds.path.parent.parent.name == "datasets"


def test_a_converted_dataset_in_the_cache_is_found(cache):
    sel = catalog.select("control_suite/walker_walk")
    dest = release_dataset_path(sel, None, all_shards=True)
    schema = Schema.for_task(get_task("control_suite/walker_walk"))
    write_synthetic(dest, schema, num_episodes=3, episode_length=5)
    ds = rlu.load_dataset("control_suite/walker_walk")
    assert str(ds.path) == dest and len(ds) == 3
    # a TFDS name of a release dataset finds the converted one of its family and run
    sel = catalog.select("atari/Pong", family="atari_episodes_ordered", run=2)
    dest = release_dataset_path(sel, None, all_shards=True)
    write_synthetic(dest, Schema.for_task(get_task("atari/Pong")), 2, 4)
    assert str(rlu.load_dataset("rlu_atari/Pong_run_2").path) == dest


def test_nothing_on_this_machine_names_the_download_command_and_writes_nothing(cache):
    with pytest.raises(RluError) as e:
        rlu.load_dataset("control_suite/walker_walk")
    msg = str(e.value)
    assert "`rlu download control_suite/walker_walk`" in msg and "\n" not in msg
    assert "rlu ships control_suite/cartpole_swingup only" in msg
    with pytest.raises(RluError, match="`rlu download atari/Pong --family atari_episodes_ordered"):
        rlu.load_dataset("rlu_atari/Pong_run_4")
    with pytest.raises(RluError, match="--run 4`"):
        rlu.load_dataset("rlu_atari/Pong_run_4")
    with pytest.raises(RluError, match="`rlu download rwrl/walker_walk --challenge easy --size"):
        rlu.load_dataset("rlu_rwrl/walker_walk_combined_challenge_easy_100_percent")
    # the shipped cartpole is rlu's own data: a TFDS name asks for the release's episodes
    with pytest.raises(RluError, match="rlu ships is rlu-generated, not this release dataset"):
        rlu.load_dataset("rlu_control_suite/cartpole_swingup")
    with pytest.raises(RluError, match="--family dm_control_suite_episodes`"):
        rlu.load_dataset("rlu_control_suite/cartpole_swingup")
    assert not cache.exists()


def test_a_missing_folder_says_so_and_a_real_one_still_opens(tmp_path):
    says = "'runs/quickstart/synthetic': no such folder .* check the path"
    with pytest.raises(RluError, match=says):
        rlu.load_dataset("runs/quickstart/synthetic")
    dest = tmp_path / "mine"
    write_synthetic(dest, Schema.for_task(get_task("control_suite/cartpole_swingup")), 2, 3)
    assert len(rlu.load_dataset(str(dest))) == 2
    assert len(rlu.load_dataset(dest, source="local")) == 2
    with pytest.raises(RluError, match="use 'auto', 'local' or 'release'"):
        rlu.load_dataset("control_suite/cartpole_swingup", source="tfds")


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def test_downloaded_shards_are_converted_without_the_network(fixtures, tmp_path, cache):
    pytest.importorskip("google_crc32c")
    served = tmp_path / "bucket"
    (served / OBJECT).parent.mkdir(parents=True)
    (served / OBJECT).write_bytes((fixtures / "data" / SHARD).read_bytes())
    handler = functools.partial(_Quiet, directory=str(served))
    with serve(handler) as srv:
        Downloader(base_url=srv.url, progress=False).fetch([OBJECT])  # what `rlu download` does
    (served / OBJECT).unlink()  # and the server is gone: only the cache can serve now
    ds = rlu.load_dataset("control_suite/cartpole_swingup", shards="0", workers=1)
    assert ds.manifest["provenance"]["family"] == "dm_control_suite"
    assert (len(ds), ds.num_steps) == (30, 60)
    again = rlu.load_dataset("control_suite/cartpole_swingup", shards="0")  # now converted
    assert again.path == ds.path
    # without `shards`, the shipped dataset (the release one has 99 shards still missing)
    assert len(rlu.load_dataset("control_suite/cartpole_swingup")) == 40
