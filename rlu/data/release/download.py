"""Resumable, checksum-recorded HTTPS download of release shards into a cache directory.

- Files land at ``CACHE/release/<object path>`` (bucket-shaped, so ``rlu convert --src`` finds
  them); bytes stream into ``<name>.part`` and are renamed only after every check passed, so a
  final name never holds a partial or unverified file.
- A cut connection resumes from the bytes already on disk with an HTTP ``Range`` request (a
  server that ignores Range makes the download start over); errors and 5xx answers are retried
  with exponential backoff.
- Checks, all before a file is recorded as complete: the size against ``Content-Length`` /
  ``Content-Range`` (a body longer than announced fails too, it is never cut to fit); where the
  bucket sends them (Google Cloud Storage's ``x-goog-hash``), the object's MD5 and CRC-32C; and
  what the catalog knows of the object: its family's framing (a gzip stream, or a plain TFRecord,
  whose first record header carries a valid CRC), so an HTML page served with status 200 is
  refused. The sha256 and size of each file go into ``CACHE/release/manifest.json``; a reused
  file is verified again (size, sha256, framing) and fetched anew when it fails.
- Redirects to another host are refused unless ``allow_redirects=True`` (``--allow-redirects``);
  every socket operation has a ``timeout`` (``--timeout``, default 30 s), so a stalled server fails
  in seconds, not minutes.
- One process per cache entry: fetching an object holds :class:`rlu.locks.OutputLock` on its
  file, so a second ``rlu download`` of the same object fails with "in use by PID N" instead of
  writing into the same ``.part``.
- Cache directory: the ``cache_dir`` argument (``--cache-dir``), else ``$RLU_CACHE_DIR``, else
  ``~/.cache/rlu``. ``base_url`` (``--base-url``) points at a mirror.
"""

from __future__ import annotations

import base64
import fcntl
import hashlib
import http.client
import json
import os
import struct
import sys
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from rlu.data.release.catalog import object_url
from rlu.locks import OutputLock
from rlu.types import RluError

CHUNK = 1 << 20
USER_AGENT = "rlu-release-downloader"
DEFAULT_TIMEOUT = 30.0


class DownloadError(RluError):
    """A file could not be fetched intact after every retry."""


def cache_root(cache_dir: str | os.PathLike | None = None) -> str:
    d = cache_dir or os.environ.get("RLU_CACHE_DIR") or os.path.join("~", ".cache", "rlu")
    return os.path.abspath(os.path.expanduser(os.fspath(d)))


def release_dir(cache_dir: str | os.PathLike | None = None) -> str:
    return os.path.join(cache_root(cache_dir), "release")


@dataclass(frozen=True)
class Fetched:
    object: str
    path: str
    size: int
    sha256: str
    reused: bool


class _Manifest:
    """``manifest.json``: object -> {size, sha256, url, md5?}; written atomically, thread-safe."""

    def __init__(self, root: str):
        self.path = os.path.join(root, "manifest.json")
        self._lock = threading.Lock()
        try:
            with open(self.path) as f:
                self.entries: dict[str, dict] = json.load(f)
        except FileNotFoundError:
            self.entries = {}
        except (OSError, ValueError):
            self.entries = {}  # a damaged manifest only costs re-verification by download

    def get(self, obj: str) -> dict | None:
        with self._lock:
            return self.entries.get(obj)

    def put(self, obj: str, entry: dict) -> None:
        self._update(obj, entry)

    def drop(self, obj: str) -> None:
        self._update(obj, None)

    def _update(self, obj: str, entry: dict | None) -> None:
        """Change one entry of the file as it is now on disk: another process downloading other
        objects into the same cache keeps its entries (a short blocking ``flock``)."""
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        with self._lock, open(self.path + ".lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            current = _read_json(self.path)
            if entry is None:
                if current.pop(obj, None) is None:
                    self.entries.pop(obj, None)
                    return
            else:
                current[obj] = entry
            self.entries = current
            tmp = f"{self.path}.{os.getpid()}.{threading.get_ident()}.tmp"
            with open(tmp, "w") as f:
                json.dump(current, f, indent=1, sort_keys=True)
            os.replace(tmp, self.path)


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK * 4):
            h.update(chunk)
    return h.hexdigest()


def _goog_hashes(headers) -> dict[str, str]:
    """``x-goog-hash: crc32c=..., md5=...`` (one header or several) -> {'md5': b64, ...}."""
    out = {}
    for value in headers.get_all("x-goog-hash") or []:
        for part in value.split(","):
            k, _, v = part.strip().partition("=")
            if k and v:
                out[k.lower()] = v.strip()
    return out


class _Progress:
    """A one-line progress bar on stderr: files done, bytes, rate."""

    def __init__(self, total_files: int, enabled: bool):
        self.enabled = enabled
        self.total_files = total_files
        self.files = 0
        self.bytes = 0
        self.start = time.monotonic()
        self._last = 0.0
        self._lock = threading.Lock()

    def add(self, n: int) -> None:
        with self._lock:
            self.bytes += n
            self._draw()

    def done(self) -> None:
        with self._lock:
            self.files += 1
            self._draw(force=True)

    def _draw(self, force: bool = False) -> None:
        if not self.enabled:
            return
        now = time.monotonic()
        if not force and now - self._last < 0.2:
            return
        self._last = now
        rate = self.bytes / max(now - self.start, 1e-6) / 1e6
        width = 30
        filled = int(width * self.files / max(self.total_files, 1))
        bar = "#" * filled + "-" * (width - filled)
        sys.stderr.write(
            f"\r[{bar}] {self.files}/{self.total_files} files  "
            f"{self.bytes / 1e6:,.1f} MB  {rate:,.1f} MB/s"
        )
        if self.files == self.total_files:
            sys.stderr.write("\n")
        sys.stderr.flush()


class Downloader:
    """Fetch release objects into the cache; see the module docstring for the guarantees."""

    def __init__(
        self,
        cache_dir: str | os.PathLike | None = None,
        base_url: str | None = None,
        workers: int = 4,
        retries: int = 5,
        backoff: float = 1.0,
        timeout: float = DEFAULT_TIMEOUT,
        progress: bool | None = None,
        verify_reuse: bool = True,
        allow_redirects: bool = False,
    ):
        self.root = release_dir(cache_dir)
        self.base_url = base_url or os.environ.get("RLU_RELEASE_BASE_URL") or None
        self.workers = max(1, workers)
        self.retries = retries
        self.backoff = backoff
        self.timeout = timeout
        self.progress = sys.stderr.isatty() if progress is None else progress
        self.verify_reuse = verify_reuse
        self.allow_redirects = allow_redirects
        self.manifest = _Manifest(self.root)
        self.sleep: Callable[[float], None] = time.sleep
        self._opener = urllib.request.build_opener(_Redirects(allow_redirects))

    def path_of(self, obj: str) -> str:
        parts = obj.split("/")
        if not obj or obj.startswith("/") or any(p in ("", ".", "..") for p in parts):
            raise DownloadError(f"{obj!r} is not a release object name (bucket-relative path)")
        return os.path.join(self.root, *parts)

    def fetch(self, objects: Sequence[str]) -> list[Fetched]:
        """Download (or reuse) every object; returns them in order. Raises on any failure."""
        bar = _Progress(len(objects), self.progress)
        results: list[Fetched | None] = [None] * len(objects)
        errors: list[BaseException] = []

        def one(i: int) -> None:
            try:
                results[i] = self._fetch_one(objects[i], bar)
            except BaseException as e:  # collected and re-raised below
                errors.append(e)
            finally:
                bar.done()

        if self.workers == 1 or len(objects) <= 1:
            for i in range(len(objects)):
                one(i)
        else:
            with ThreadPoolExecutor(self.workers) as pool:
                list(pool.map(one, range(len(objects))))
        if errors:
            first = errors[0]
            if isinstance(first, RluError):
                if len(errors) > 1:
                    raise DownloadError(f"{first} (and {len(errors) - 1} more files failed)")
                raise first
            raise first
        return [r for r in results if r is not None]

    # --- one file ---

    def _reuse(self, obj: str, path: str) -> Fetched | None:
        entry = self.manifest.get(obj)
        if entry is None or not os.path.isfile(path):
            return None
        size = os.path.getsize(path)
        bad = size != entry.get("size")
        if not bad and self.verify_reuse:
            # local damage since the download, or an entry an older rlu recorded unverified
            bad = sha256_file(path) != entry.get("sha256") or bool(release_framing(path, obj))
        if bad:
            self.manifest.drop(obj)
            os.remove(path)
            return None
        return Fetched(obj, path, size, entry["sha256"], True)

    def _fetch_one(self, obj: str, bar: _Progress) -> Fetched:
        path = self.path_of(obj)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with OutputLock(path, "cache entry"):
            got = self._reuse(obj, path)
            if got is not None:
                return got
            return self._download(obj, path, bar)

    def _download(self, obj: str, path: str, bar: _Progress) -> Fetched:
        url = object_url(obj, self.base_url)
        part = path + ".part"
        meta_path = part + ".json"
        last_error = ""
        for attempt in range(self.retries + 1):
            if attempt:
                self.sleep(self.backoff * (2 ** (attempt - 1)))
            try:
                ok, why = self._attempt(url, part, meta_path, bar)
                if ok:
                    why = release_framing(part, obj)
                    ok = not why
                    if not ok:
                        _remove(part, meta_path)
            except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as e:
                reason = e.reason if isinstance(e, urllib.error.URLError) else e
                ok, why = False, f"{type(e).__name__}: {reason}"
                if isinstance(reason, TimeoutError):
                    why = f"no answer within --timeout {self.timeout:g} s ({reason})"
            if ok:
                digest = sha256_file(part)
                size = os.path.getsize(part)
                os.replace(part, path)
                meta = _read_json(meta_path)
                if os.path.exists(meta_path):
                    os.remove(meta_path)
                entry = {"size": size, "sha256": digest, "url": url}
                if meta.get("md5"):
                    entry["md5"] = meta["md5"]
                self.manifest.put(obj, entry)
                return Fetched(obj, path, size, digest, False)
            last_error = why
        raise DownloadError(
            f"could not download {url} after {self.retries + 1} attempts: {last_error}. "
            f"Run the command again to resume (the bytes so far are kept in {part}), or point "
            f"--base-url at a mirror"
        )

    def _attempt(self, url: str, part: str, meta_path: str, bar: _Progress) -> tuple[bool, str]:
        """One request; True when ``part`` now holds the whole object, checked against the
        headers (length, hashes); the caller then checks its framing."""
        have = os.path.getsize(part) if os.path.exists(part) else 0
        meta = _read_json(meta_path)
        if have and not meta:
            have = 0  # bytes of unknown origin: start over
        req = urllib.request.Request(url, headers={"User-Agent": USER_AGENT})
        if have:
            req.add_header("Range", f"bytes={have}-")
            if meta.get("etag"):
                req.add_header("If-Range", meta["etag"])
        try:
            resp = self._opener.open(req, timeout=self.timeout)
        except urllib.error.HTTPError as e:
            e.close()
            if e.code == 416:  # our part is no prefix of the object any more
                _remove(part, meta_path)
                return False, "HTTP 416 on resume; starting over"
            if e.code == 404:
                raise DownloadError(
                    f"{url}: not found (HTTP 404); check the task and shards"
                ) from None
            return False, f"HTTP {e.code} {e.reason}"
        with resp:
            status = resp.status
            headers = resp.headers
            ctype = (headers.get("Content-Type") or "").split(";")[0].strip().lower()
            if ctype in ("text/html", "application/xhtml+xml"):
                return False, (
                    f"the server answered {url} with a web page ({ctype}), not a release file; "
                    "check --base-url (a login or error page?)"
                )
            if status == 206 and have:
                total = _content_range_total(headers.get("Content-Range"))
                mode = "ab"
            else:
                have = 0
                total = _int(headers.get("Content-Length"))
                mode = "wb"
                hashes = _goog_hashes(headers)
                meta = {"etag": headers.get("ETag"), "size": total, **hashes}
                with open(meta_path, "w") as f:
                    json.dump(meta, f)
            if total is None:
                total = meta.get("size")
            with open(part, mode) as f:
                longer = _copy_body(resp, f, bar)
        size = os.path.getsize(part)
        if longer:
            _remove(part, meta_path)
            return False, "the server sent more bytes than its Content-Length announced"
        if total is not None and size < total:
            return False, f"connection closed after {size} of {total} bytes"
        if total is not None and size > total:
            _remove(part, meta_path)
            return False, f"received {size} bytes, more than the {total} announced"
        why = _check_hashes(part, meta)
        if why:
            _remove(part, meta_path)
            return False, why
        return True, ""


class _Redirects(urllib.request.HTTPRedirectHandler):
    """Follow redirects on the same host; to another host only when allowed (a mirror that
    redirects to a CDN: ``--allow-redirects``)."""

    def __init__(self, allow: bool):
        self.allow = allow

    def redirect_request(self, req, fp, code, msg, headers, newurl):  # noqa: ANN001
        old = urllib.parse.urlsplit(req.full_url).hostname
        new = urllib.parse.urlsplit(urllib.parse.urljoin(req.full_url, newurl)).hostname
        if old != new and not self.allow:
            raise DownloadError(
                f"{req.full_url}: the server redirects (HTTP {code}) to another host, {new}; "
                "rlu follows redirects to other hosts only with --allow-redirects"
            )
        return super().redirect_request(req, fp, code, msg, headers, newurl)


def _copy_body(resp: http.client.HTTPResponse, f, bar: _Progress) -> bool:
    """Copy the body to ``f``; True when the server sent more than its Content-Length.

    ``http.client`` stops reading at Content-Length and drops the rest silently, so with a length
    the body is read from the connection itself, then one more byte is asked for: the request
    said ``Connection: close``, so an honest server has closed it (EOF) by then.
    """
    declared = resp.length
    if resp.chunked or declared is None:
        while chunk := resp.read(CHUNK):
            f.write(chunk)
            bar.add(len(chunk))
        return False
    fp = resp.fp
    left = declared
    while left > 0:
        chunk = fp.read(min(CHUNK, left))
        if not chunk:
            return False  # cut: the size check names it
        f.write(chunk)
        bar.add(len(chunk))
        left -= len(chunk)
    try:
        return bool(fp.read1(1))
    except TimeoutError:
        return False  # a server that keeps the connection open sent nothing more


def release_framing(path: str, obj: str) -> str:
    """Why ``path`` is not a release file of ``obj``'s family ('' when it looks like one).

    The catalog knows each object's family, so its framing: a gzip stream, or (RWRL) a plain
    TFRecord, whose first record header must carry a valid length CRC. An HTML page, a JSON
    error or a truncated first block fails here, before the file is recorded.
    """
    from rlu.data.release.families import FAMILIES
    from rlu.data.release.framing import GZIP_MAGIC, MAX_RECORD_BYTES, masked_crc32c

    fam = FAMILIES.get(obj.split("/", 1)[0])
    if fam is None:
        return ""  # not a catalog object: nothing is known to check
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    if fam.compression == "gzip":
        if head[:2] != GZIP_MAGIC:
            return f"not a gzip file (it starts with {head[:16]!r}): not a {fam.name} shard"
        try:
            head = zlib.decompressobj(31).decompress(head, 12)
        except zlib.error as e:
            return f"a damaged gzip stream ({e})"
    if len(head) < 12:
        return f"no TFRecord header in the first bytes ({len(head)} bytes): not a {fam.name} shard"
    (length,) = struct.unpack("<Q", head[:8])
    if length > MAX_RECORD_BYTES or struct.unpack("<I", head[8:12])[0] != masked_crc32c(head[:8]):
        return f"its first record header is not TFRecord framing: not a {fam.name} shard"
    return ""


def _check_hashes(path: str, meta: dict) -> str:
    """Compare the file with the bucket's MD5 / CRC-32C (``x-goog-hash``), where sent."""
    md5, crc = meta.get("md5"), meta.get("crc32c")
    if not md5 and not crc:
        return ""
    h = hashlib.md5()
    c = None
    if crc:
        import google_crc32c

        c = google_crc32c.Checksum()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK * 4):
            h.update(chunk)
            if c is not None:
                c.update(chunk)
    if md5 and base64.b64encode(h.digest()).decode() != md5:
        return "MD5 mismatch against the bucket's x-goog-hash (corrupt transfer)"
    if c is not None and base64.b64encode(c.digest()).decode() != crc:
        return "CRC-32C mismatch against the bucket's x-goog-hash (corrupt transfer)"
    return ""


def _read_json(path: str) -> dict:
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return {}


def _remove(*paths: str) -> None:
    for p in paths:
        if os.path.exists(p):
            os.remove(p)


def _int(v: str | None) -> int | None:
    try:
        return int(v) if v is not None else None
    except ValueError:
        return None


def _content_range_total(v: str | None) -> int | None:
    # "bytes 100-199/200"
    if not v or "/" not in v:
        return None
    return _int(v.rsplit("/", 1)[1])


def download(
    objects: Sequence[str],
    cache_dir: str | os.PathLike | None = None,
    base_url: str | None = None,
    **kw,
) -> list[Fetched]:
    """Fetch ``objects`` (bucket-relative names) into the cache; returns where they are."""
    return Downloader(cache_dir=cache_dir, base_url=base_url, **kw).fetch(objects)
