"""The downloader against HTTP servers on 127.0.0.1 that misbehave: a cut connection, HTTP 500s,
a wrong byte, an HTML page served with 200, a body longer than its Content-Length, a redirect to
another host, a server that accepts and never answers. Final files equal the source; nothing
partial or unverified is left under a final name or recorded in the cache manifest."""

from __future__ import annotations

import base64
import gzip
import hashlib
import http.server
import os
import socket
import urllib.error

import google_crc32c
import numpy as np
import pytest

from rlu.cli import main
from rlu.data.release import framing as F
from rlu.data.release.download import Downloader, DownloadError
from rlu.locks import LockBusy, OutputLock
from tests.servers import direct, serve


class _Handler(http.server.BaseHTTPRequestHandler):
    def log_message(self, *a):  # quiet
        pass

    def do_GET(self):  # noqa: N802
        srv = self.server
        name = self.path.lstrip("/")
        srv.requests.append((name, self.headers.get("Range")))
        body = srv.files.get(name)
        if body is None:
            self.send_error(404)
            return
        plan = srv.plans.get(name, [])
        action = plan.pop(0) if plan else "ok"
        if action in ("403", "500", "503"):
            self.send_error(int(action), {"403": "Forbidden"}.get(action, "try again"))
            return
        if action.startswith("redirect:"):  # to the same path on another host name
            self.send_response(302)
            self.send_header("Location", f"http://{action[9:]}:{srv.server_address[1]}/{name}")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        if action in ("html", "html-as-bytes"):
            page = b"<!doctype html><html><body>Sign in to continue</body></html>"
            self.send_response(200)
            ctype = "text/html; charset=utf-8" if action == "html" else "application/octet-stream"
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(page)))
            self.end_headers()
            self.wfile.write(page)
            return
        start = 0
        rng = self.headers.get("Range")
        if rng and srv.ranges:
            start = int(rng.split("=")[1].split("-")[0])
        data = body[start:]
        if action == "flip":
            data = bytearray(data)
            data[len(data) // 2] ^= 0x01
            data = bytes(data)
        self.send_response(206 if start else 200)
        self.send_header("Content-Length", str(len(data)))
        if start:
            self.send_header("Content-Range", f"bytes {start}-{len(body) - 1}/{len(body)}")
        if srv.hashes:
            md5 = base64.b64encode(hashlib.md5(body).digest()).decode()
            crc = base64.b64encode(google_crc32c.Checksum(body).digest()).decode()
            self.send_header("x-goog-hash", f"crc32c={crc}")
            self.send_header("x-goog-hash", f"md5={md5}")
        self.send_header("ETag", '"v1"')
        self.end_headers()
        if action == "long":  # the announced bytes, then more, before closing
            self.wfile.write(data + b"trailing bytes the header did not announce")
            return
        if action == "cut":
            self.wfile.write(data[: len(data) // 3])
            self.wfile.flush()
            self.close_connection = True
            self.connection.shutdown(2)
            return
        self.wfile.write(data)


@pytest.fixture(autouse=True)
def _direct(monkeypatch):
    direct(monkeypatch)


@pytest.fixture
def server():
    with serve(_Handler, files={}, plans={}, requests=[], ranges=True, hashes=True) as srv:
        yield srv


def _blob(n=300_000, seed=0):
    """A gzip TFRecord shard of about ``n`` bytes of random records (what the release holds)."""
    rng = np.random.default_rng(seed)
    raw = b"".join(F.frame(rng.bytes(1000)) for _ in range(n // 1016))
    return gzip.compress(raw, mtime=0)


def _downloader(tmp_path, server, **kw):
    d = Downloader(cache_dir=tmp_path / "cache", base_url=server.url, progress=False, **kw)
    d.sleeps = []
    d.sleep = d.sleeps.append  # record the backoff instead of waiting
    return d


def _no_partials(root):
    for dirpath, _, names in os.walk(root):
        for n in names:
            assert not n.endswith((".part", ".part.json")), os.path.join(dirpath, n)


def test_cut_connection_resumes_with_range(tmp_path, server):
    obj = "dm_control_suite/x/train-00000-of-00001"
    server.files[obj] = body = _blob()
    server.plans[obj] = ["cut"]
    d = _downloader(tmp_path, server)
    (f,) = d.fetch([obj])
    assert open(f.path, "rb").read() == body
    assert f.sha256 == hashlib.sha256(body).hexdigest() and f.size == len(body)
    (first, r1), (second, r2) = server.requests
    assert r1 is None and r2 is not None and r2.startswith("bytes=") and r2 != "bytes=0-"
    _no_partials(d.root)
    assert d.manifest.get(obj)["sha256"] == f.sha256


def test_server_that_ignores_range_restarts(tmp_path, server):
    obj = "a/b-00000-of-00001"
    server.files[obj] = body = _blob(seed=1)
    server.plans[obj] = ["cut"]
    server.ranges = False
    (f,) = _downloader(tmp_path, server).fetch([obj])
    assert open(f.path, "rb").read() == body


def test_http_500_twice_then_ok_with_backoff(tmp_path, server):
    obj = "a/c-00000-of-00001"
    server.files[obj] = body = _blob(seed=2)
    server.plans[obj] = ["500", "500"]
    d = _downloader(tmp_path, server, backoff=0.5)
    (f,) = d.fetch([obj])
    assert open(f.path, "rb").read() == body
    assert d.sleeps == [0.5, 1.0] and len(server.requests) == 3


def test_wrong_byte_is_caught_by_the_checksum(tmp_path, server):
    obj = "a/d-00000-of-00001"
    server.files[obj] = body = _blob(seed=3)
    server.plans[obj] = ["flip"]
    d = _downloader(tmp_path, server)
    (f,) = d.fetch([obj])
    assert open(f.path, "rb").read() == body and len(server.requests) == 2
    _no_partials(d.root)


def test_persistent_corruption_fails_and_leaves_no_final_file(tmp_path, server):
    obj = "a/e-00000-of-00001"
    server.files[obj] = _blob(seed=4)
    server.plans[obj] = ["flip"] * 10
    d = _downloader(tmp_path, server, retries=2)
    with pytest.raises(DownloadError, match="MD5 mismatch"):
        d.fetch([obj])
    assert not os.path.exists(d.path_of(obj))
    assert d.manifest.get(obj) is None


def test_missing_object_is_a_clear_error(tmp_path, server):
    with pytest.raises(DownloadError, match="404"):
        _downloader(tmp_path, server).fetch(["nope-00000-of-00001"])


def test_reuse_verifies_sha256(tmp_path, server):
    objs = [f"g/run_1-{i:05d}-of-00004" for i in range(4)]
    for i, o in enumerate(objs):
        server.files[o] = _blob(50_000, seed=10 + i)
    d = _downloader(tmp_path, server, workers=4)
    got = d.fetch(objs)  # parallel
    assert [open(f.path, "rb").read() for f in got] == [server.files[o] for o in objs]
    n = len(server.requests)
    again = _downloader(tmp_path, server).fetch(objs)
    assert all(f.reused for f in again) and len(server.requests) == n
    # local damage after the download: caught by the recorded sha256, fetched again
    p = got[1].path
    data = bytearray(open(p, "rb").read())
    data[100] ^= 0xFF
    open(p, "wb").write(bytes(data))
    third = _downloader(tmp_path, server).fetch(objs)
    assert not third[1].reused and open(p, "rb").read() == server.files[objs[1]]
    assert len(server.requests) == n + 1


def test_mirror_without_hashes_checks_size(tmp_path, server):
    obj = "m/h-00000-of-00001"
    server.files[obj] = body = _blob(seed=5)
    server.hashes = False
    server.plans[obj] = ["cut", "cut"]
    (f,) = _downloader(tmp_path, server).fetch([obj])
    assert open(f.path, "rb").read() == body


def test_cache_dir_from_environment(tmp_path, monkeypatch, server):
    monkeypatch.setenv("RLU_CACHE_DIR", str(tmp_path / "envcache"))
    d = Downloader(base_url=server.url, progress=False)
    assert d.root == str(tmp_path / "envcache" / "release")


def test_load_release_dataset_downloads_converts_then_reuses(fixtures, tmp_path, server):
    from rlu.data.release.load import load_release_dataset

    obj = "dm_control_suite/cartpole_swingup/train-00000-of-00100"
    shard = fixtures / "data" / "dm_control_suite/cartpole_swingup/train-00000-of-00001"
    server.files[obj] = shard.read_bytes()
    kw = dict(cache_dir=tmp_path / "c", base_url=server.url, shards="0", workers=1)
    ds = load_release_dataset("control_suite/cartpole_swingup", **kw)
    assert len(ds) == 30 and ds.num_steps == 60
    assert ds.manifest["provenance"]["family"] == "dm_control_suite"
    n = len(server.requests)
    server.files.clear()  # a second call needs no network
    ds2 = load_release_dataset("control_suite/cartpole_swingup", **kw)
    assert ds2.path == ds.path and len(server.requests) == n
    import rlu

    ds3 = rlu.load_dataset("control_suite/cartpole_swingup", source="release", **kw)
    assert ds3.path == ds.path


# --- hostile and unlucky servers ----------------------------------------------------------------
OBJ = "dm_control_suite/y/train-00000-of-00001"  # a family the catalog knows: gzip TFRecords


@pytest.mark.parametrize("kind", ["html", "html-as-bytes"])
def test_html_page_with_200_is_never_recorded(tmp_path, server, kind):
    server.files[OBJ] = body = _blob(seed=20)
    server.plans[OBJ] = [kind] * 3
    d = _downloader(tmp_path, server, retries=2)
    why = "web page" if kind == "html" else "not a gzip file"
    with pytest.raises(DownloadError, match=why):
        d.fetch([OBJ])
    # a page that says it is one is no transfer error: refused at once; bytes that are not a
    # shard could be a damaged transfer: tried again
    assert len(server.requests) == (1 if kind == "html" else 3)
    assert not os.path.exists(d.path_of(OBJ)) and d.manifest.get(OBJ) is None
    _no_partials(d.root)
    server.plans[OBJ] = []
    (f,) = _downloader(tmp_path, server).fetch([OBJ])  # the real file once the server is sane
    assert open(f.path, "rb").read() == body


def test_body_longer_than_content_length_is_refused_then_fetched_whole(tmp_path, server):
    server.files[OBJ] = body = _blob(seed=21)
    server.hashes = False  # only the length can tell
    server.plans[OBJ] = ["long"]
    d = _downloader(tmp_path, server)
    (f,) = d.fetch([OBJ])
    assert open(f.path, "rb").read() == body and len(server.requests) == 2
    server.plans[OBJ] = ["long"] * 3
    with pytest.raises(DownloadError, match="more bytes than its Content-Length"):
        _downloader(tmp_path / "again", server, retries=2).fetch([OBJ])


def test_redirect_to_another_host_only_when_allowed(tmp_path, server):
    server.files[OBJ] = body = _blob(seed=22)
    server.plans[OBJ] = ["redirect:localhost"]
    d = _downloader(tmp_path, server)
    with pytest.raises(DownloadError, match="another host, localhost.*--allow-redirects"):
        d.fetch([OBJ])
    assert len(server.requests) == 1  # refused, not retried
    server.plans[OBJ] = ["redirect:localhost"]
    (f,) = _downloader(tmp_path, server, allow_redirects=True).fetch([OBJ])
    assert open(f.path, "rb").read() == body
    server.plans[OBJ] = ["redirect:127.0.0.1"]  # the same host: always followed
    (f,) = _downloader(tmp_path / "same", server).fetch([OBJ])
    assert open(f.path, "rb").read() == body


@pytest.fixture
def stalled():
    """A server that accepts connections (the kernel's backlog) and never says a word."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen(8)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    sock.close()


def test_stalled_server_fails_within_the_timeout(tmp_path, stalled, capsys):
    d = Downloader(cache_dir=tmp_path / "c", base_url=stalled, progress=False, timeout=0.2)
    d.retries, d.sleep = 1, lambda s: None
    with pytest.raises(DownloadError, match=r"no answer within --timeout 0.2 s"):
        d.fetch([OBJ])
    args = ["download", "control_suite/cartpole_swingup", "--shards", "0", "--retries", "0"]
    code = main([*args, "--base-url", stalled, "--timeout", "0.2", "--cache-dir", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "--timeout 0.2" in err and "Traceback" not in err


def test_reused_entry_that_fails_verification_is_fetched_again(tmp_path, server):
    server.files[OBJ] = body = _blob(seed=23)
    d = _downloader(tmp_path, server)
    path = d.path_of(OBJ)
    os.makedirs(os.path.dirname(path))
    page = b"<html>an error page an older downloader recorded</html>"
    open(path, "wb").write(page)
    d.manifest.put(OBJ, {"size": len(page), "sha256": hashlib.sha256(page).hexdigest()})
    (f,) = _downloader(tmp_path, server).fetch([OBJ])
    assert not f.reused and open(f.path, "rb").read() == body and len(server.requests) == 1


def test_a_cache_entry_being_fetched_is_in_use(tmp_path, server):
    server.files[OBJ] = _blob(seed=24)
    d = _downloader(tmp_path, server)
    with OutputLock(d.path_of(OBJ), "cache entry"):  # another fetch of it, live
        with pytest.raises(LockBusy, match=rf"in use by PID {os.getpid()}"):
            d.fetch([OBJ])
    assert server.requests == []
    (f,) = d.fetch([OBJ])  # released: fetched
    assert f.size > 0


# --- failing fast: permanent errors end the command at once, in one line -----------------------
TASK = "control_suite/cartpole_swingup"
SHARD0 = "dm_control_suite/cartpole_swingup/train-00000-of-00100"


@pytest.fixture
def refused():
    """A port on 127.0.0.1 where nothing listens (bound, then closed)."""
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()
    return f"http://127.0.0.1:{port}"


def _cli(base, cache, capsys, *extra):
    code = main(["download", TASK, "--base-url", base, "--cache-dir", str(cache), *extra])
    out, err = capsys.readouterr()
    return code, err.strip().split("\n") if err.strip() else []  # a bar's \r is no new line


def test_refused_port_ends_the_download_in_one_line(tmp_path, refused, capsys):
    code, lines = _cli(refused, tmp_path, capsys, "--shards", "0-7")
    assert code == 2 and len(lines) == 1, lines
    (line,) = lines
    assert line.startswith(f"rlu: error: cannot download {refused}/dm_control_suite/")
    assert "connection refused by 127.0.0.1" in line
    assert "--base-url" in line and "HTTPS_PROXY" in line
    assert "kept" not in line  # no byte arrived: nothing is kept
    assert "0 of 8 files done" in line
    _no_partials(tmp_path)


@pytest.mark.parametrize("status", ["403", "404"])
def test_http_403_and_404_end_the_download_in_one_line(tmp_path, server, capsys, status):
    objs = [f"dm_control_suite/cartpole_swingup/train-{i:05d}-of-00100" for i in range(4)]
    if status == "403":
        for o in objs:
            server.files[o] = b"never sent"
            server.plans[o] = ["403"] * 10
    code, lines = _cli(server.url, tmp_path, capsys, "--shards", "0-3", "--workers", "2")
    assert code == 2 and len(lines) == 1, lines
    want = "access denied by the server (HTTP 403" if status == "403" else "not found (HTTP 404)"
    assert want in lines[0] and f"cannot download {server.url}/dm_control_suite/" in lines[0]
    assert "--base-url" in lines[0]
    assert len(server.requests) <= 2  # one per worker at most: nothing retried
    _no_partials(tmp_path)


def test_load_dataset_fails_fast_in_one_line(tmp_path, refused, server):
    import rlu

    kw = dict(source="release", cache_dir=tmp_path / "c", shards="0-3", progress=False)
    for base, want in ((refused, "connection refused"), (server.url, "HTTP 404")):
        with pytest.raises(DownloadError) as e:
            rlu.load_dataset(TASK, base_url=base, **kw)
        text = str(e.value)
        assert "\n" not in text and want in text and f"cannot download {base}/" in text
        assert "--base-url" in text
    names = [r[0] for r in server.requests]
    assert len(names) == len(set(names)) <= 4  # at most one request per shard: no retries
    server.requests.clear()
    server.files[SHARD0] = b"x"
    server.plans[SHARD0] = ["403"] * 10
    with pytest.raises(DownloadError, match="HTTP 403"):
        rlu.load_dataset(TASK, base_url=server.url, **{**kw, "shards": "0"})
    assert len(server.requests) == 1


def test_tls_to_a_plain_http_server_is_permanent(tmp_path, server, capsys):
    server.files[SHARD0] = _blob(seed=30)
    https = server.url.replace("http://", "https://")
    code, lines = _cli(https, tmp_path, capsys, "--shards", "0")
    assert code == 2 and len(lines) == 1 and "TLS failed with 127.0.0.1" in lines[0], lines
    assert len(server.requests) == 0  # the handshake failed before any request


def test_dns_failure_is_permanent_and_names_the_fix():
    from rlu.data.release.download import classify

    err = urllib.error.URLError(socket.gaierror(socket.EAI_NONAME, "Name or service not known"))
    fail = classify(err, "https://storage.googleapis.com/rl_unplugged/x")
    assert fail.permanent
    assert "storage.googleapis.com cannot be resolved" in fail.why and "--base-url" in fail.why
    assert "HTTPS_PROXY" in fail.why
    for transient in (TimeoutError("timed out"), ConnectionResetError(104, "reset")):
        assert not classify(transient, "http://h/x").permanent
    assert not classify(urllib.error.HTTPError("u", 503, "busy", {}, None), "http://h/x").permanent


def test_a_proxy_is_named_in_the_error(tmp_path, refused, monkeypatch):
    monkeypatch.setenv("http_proxy", refused)  # a proxy that is down
    monkeypatch.setenv("no_proxy", "")
    d = Downloader(cache_dir=tmp_path, base_url="http://mirror.invalid", progress=False)
    with pytest.raises(DownloadError, match=rf"connection refused by the proxy {refused}"):
        d.fetch([SHARD0])


def test_5xx_is_retried_with_bounded_backoff_then_reported(tmp_path, server):
    server.files[OBJ] = _blob(seed=31)
    server.plans[OBJ] = ["503"] * 8
    d = _downloader(tmp_path, server, retries=6, backoff=1.0)
    with pytest.raises(DownloadError) as e:
        d.fetch([OBJ])
    assert d.sleeps == [1.0, 2.0, 4.0, 8.0, 10.0, 10.0]  # capped at MAX_BACKOFF
    text = str(e.value)
    assert "after 7 tries: HTTP 503" in text and "kept" not in text and "again later" in text
    _no_partials(d.root)  # no byte arrived: no .part to resume from


def test_cut_connections_keep_the_bytes_and_say_so(tmp_path, server):
    server.files[OBJ] = _blob(seed=32)
    server.plans[OBJ] = ["cut"] * 3
    server.ranges = False  # every try starts over and is cut again
    d = _downloader(tmp_path, server, retries=2)
    with pytest.raises(DownloadError, match=r"bytes so far are kept in .*\.part: run the"):
        d.fetch([OBJ])
    assert os.path.getsize(d.path_of(OBJ) + ".part") > 0


def test_failed_files_are_counted_as_failed(tmp_path, server, capsys, monkeypatch):
    objs = [f"dm_control_suite/cartpole_swingup/train-{i:05d}-of-00100" for i in range(3)]
    server.files[objs[0]] = _blob(seed=33)  # shard 1 is missing: 404
    server.files[objs[2]] = _blob(seed=34)
    monkeypatch.setenv("RLU_PROGRESS", "bar")
    args = ["--shards", "0-2", "--workers", "1"]
    code, lines = _cli(server.url, tmp_path, capsys, *args)
    assert code == 2
    bar = lines[0].split("\r")[-1]
    assert "files=1/3" in bar and "failed=1" in bar, bar
    assert lines[-1].startswith("rlu: error: cannot download") and "1 of 3 files done" in lines[-1]
    assert [r[0] for r in server.requests] == objs[:2]  # shard 2 never started
    server.files[objs[1]] = _blob(seed=35)
    code, lines = _cli(server.url, tmp_path, capsys, *args, "--quiet")
    assert code == 0 and lines == []  # --quiet: nothing on stderr
