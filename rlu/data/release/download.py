"""Resumable, checksum-recorded HTTPS download of release shards into a cache directory.

- Files land at ``CACHE/release/<object path>`` (bucket-shaped, so ``rlu convert --src`` finds
  them); bytes stream into ``<name>.part`` and are renamed only after every check passed, so a
  final name never holds a partial or unverified file.
- A cut connection resumes from the bytes already on disk with an HTTP ``Range`` request (a
  server that ignores Range makes the download start over); errors and 5xx answers are retried
  with exponential backoff.
- Checks: the size against ``Content-Length`` / ``Content-Range``, and, where the bucket sends
  them (Google Cloud Storage's ``x-goog-hash``), the object's MD5 and CRC-32C. The sha256 and size
  of each file go into ``CACHE/release/manifest.json`` and are verified whenever the file is
  reused.
- Cache directory: the ``cache_dir`` argument (``--cache-dir``), else ``$RLU_CACHE_DIR``, else
  ``~/.cache/rlu``. ``base_url`` (``--base-url``) points at a mirror.
"""

from __future__ import annotations

import base64
import hashlib
import http.client
import json
import os
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from rlu.data.release.catalog import object_url
from rlu.types import RluError

CHUNK = 1 << 20
USER_AGENT = "rlu-release-downloader"


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
        with self._lock:
            self.entries[obj] = entry
            self._write()

    def drop(self, obj: str) -> None:
        with self._lock:
            if self.entries.pop(obj, None) is not None:
                self._write()

    def _write(self) -> None:
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        tmp = f"{self.path}.{os.getpid()}.{threading.get_ident()}.tmp"
        with open(tmp, "w") as f:
            json.dump(self.entries, f, indent=1, sort_keys=True)
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
        timeout: float = 60.0,
        progress: bool | None = None,
        verify_reuse: bool = True,
    ):
        self.root = release_dir(cache_dir)
        self.base_url = base_url or os.environ.get("RLU_RELEASE_BASE_URL") or None
        self.workers = max(1, workers)
        self.retries = retries
        self.backoff = backoff
        self.timeout = timeout
        self.progress = sys.stderr.isatty() if progress is None else progress
        self.verify_reuse = verify_reuse
        self.manifest = _Manifest(self.root)
        self.sleep: Callable[[float], None] = time.sleep

    def path_of(self, obj: str) -> str:
        return os.path.join(self.root, *obj.split("/"))

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
        if size != entry.get("size"):
            self.manifest.drop(obj)
            os.remove(path)
            return None
        if self.verify_reuse:
            digest = sha256_file(path)
            if digest != entry.get("sha256"):
                # Local damage since the download: fetch again.
                self.manifest.drop(obj)
                os.remove(path)
                return None
        return Fetched(obj, path, size, entry["sha256"], True)

    def _fetch_one(self, obj: str, bar: _Progress) -> Fetched:
        path = self.path_of(obj)
        got = self._reuse(obj, path)
        if got is not None:
            return got
        os.makedirs(os.path.dirname(path), exist_ok=True)
        url = object_url(obj, self.base_url)
        part = path + ".part"
        meta_path = part + ".json"
        last_error = ""
        for attempt in range(self.retries + 1):
            if attempt:
                self.sleep(self.backoff * (2 ** (attempt - 1)))
            try:
                ok, why = self._attempt(url, part, meta_path, bar)
            except (urllib.error.URLError, http.client.HTTPException, OSError, ValueError) as e:
                ok, why = False, f"{type(e).__name__}: {e}"
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
        """One request; True when ``part`` now holds the whole, verified object."""
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
            resp = urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as e:
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
                while True:
                    chunk = resp.read(CHUNK)
                    if not chunk:
                        break
                    f.write(chunk)
                    bar.add(len(chunk))
        size = os.path.getsize(part)
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
