"""Resumable, checksum-recorded HTTPS download of release shards into a cache directory.

- Files land at ``CACHE/release/<object path>`` (bucket-shaped, so ``rlu convert --src`` finds
  them); bytes stream into ``<name>.part`` and are renamed only after every check passed, so a
  final name never holds a partial or unverified file.
- Errors that another try cannot mend end the whole command at once, with one line naming the
  URL and the fix: an unknown host (DNS), a refused connection, an unreachable network, a TLS
  failure, HTTP 4xx (403, 404, ...), a web page instead of a file, a body over its bound. Other
  workers stop too, so an offline machine fails in a second, not after backoff on every shard.
- Errors another try may mend (a timeout, a reset or cut connection, HTTP 5xx, 408 and 429, a
  corrupt transfer) are retried with exponential backoff, capped at ``MAX_BACKOFF`` seconds a
  wait; a cut connection resumes from the bytes already on disk with an HTTP ``Range`` request
  (a server that ignores Range makes the download start over). A file that fails every try ends
  the command too, the other files' progress kept for the next run.
- Checks, all before a file is recorded as complete: the size against ``Content-Length`` /
  ``Content-Range`` (a body longer than announced fails too, it is never cut to fit); a body
  without a length stops at its family's largest shard size (``Family.max_shard_bytes``), so an
  endless body fails at that bound instead of filling the disk; where the bucket sends them
  (Google Cloud Storage's ``x-goog-hash``), the object's MD5 and CRC-32C; and what the catalog
  knows of the object: its family's framing (a gzip stream, or a plain TFRecord, whose first
  record header carries a valid CRC), so an HTML page served with status 200 is refused. The
  sha256 and size of each file go into ``CACHE/release/manifest.json``; a reused file is verified
  again (size, sha256, framing) and fetched anew when it fails.
- The cache never writes or reads through a link it did not make: ``.part`` files, their
  ``.part.json`` resume notes, the manifest and its lock are opened with ``O_NOFOLLOW`` and
  refused when they are a symbolic link or have a second hard link; temporary files are made
  with ``O_EXCL``. (A linked *directory* is followed: a cache on another disk is a common set-up.)
- Redirects to another host are refused unless ``allow_redirects=True`` (``--allow-redirects``);
  every socket operation has a ``timeout`` (``--timeout``, default 30 s), so a stalled server fails
  in seconds, not minutes.
- One process per cache entry: fetching an object holds :class:`rlu.locks.OutputLock` on its
  file, so a second ``rlu download`` of the same object fails with "in use by PID N" instead of
  writing into the same ``.part``.
- Progress: one :class:`rlu.progress.Progress` over the bytes to fetch (a bar with rate and ETA
  on a terminal, a plain line every 10 s otherwise, nothing with ``progress=False`` /
  ``--quiet``); files done, failed and reused are counted apart.
- Cache directory: the ``cache_dir`` argument (``--cache-dir``), else ``$RLU_CACHE_DIR``, else
  ``~/.cache/rlu``. ``base_url`` (``--base-url``) points at a mirror. Proxies come from the usual
  ``HTTPS_PROXY`` / ``HTTP_PROXY`` / ``NO_PROXY`` variables (urllib's rules).

:meth:`Downloader.fetch_one` is the whole life of one shard (lock, reuse check, download with
retries, verification, manifest entry) with no shared state but the manifest file, so another
backend can run it per shard.
"""

from __future__ import annotations

import base64
import errno
import fcntl
import functools
import hashlib
import http.client
import json
import os
import socket
import ssl
import struct
import threading
import time
import urllib.error
import urllib.parse
import urllib.request
import zlib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import IO, Any, BinaryIO

from rlu.data.release.catalog import object_url, shard_limit
from rlu.files import move_into_place, open_private, write_atomic
from rlu.locks import OutputLock
from rlu.progress import Progress
from rlu.types import RluError

CHUNK = 1 << 20
USER_AGENT = "rlu-release-downloader"
DEFAULT_TIMEOUT = 30.0
MAX_BACKOFF = 10.0  # seconds: the longest wait between two tries of one file
_GRACE = 1.0  # seconds the other workers get to stop once the command fails
_MIRROR = "point --base-url at a mirror you can reach"
_PROXY = "set HTTPS_PROXY / HTTP_PROXY (and NO_PROXY) if you need a proxy"


class DownloadError(RluError):
    """A file could not be fetched intact: a permanent error, or a transient one every retry."""


class _Fail(Exception):
    """One try failed; ``permanent``: no other try can mend it (the command ends)."""

    def __init__(self, why: str, permanent: bool = False):
        super().__init__(why)
        self.why = why
        self.permanent = permanent


class _Stopped(Exception):
    """The command is ending (another file failed, or Ctrl-C): this file was left as it was."""


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


# --- files that refuse links ---------------------------------------------------------------


def _read_private(path: str) -> bytes | None:
    """The bytes of a cache file, None when missing; a link is refused (see open_private)."""
    try:
        fd = open_private(path, os.O_RDONLY, "cache file")
    except FileNotFoundError:
        return None
    with os.fdopen(fd, "rb") as f:
        return f.read()


def _read_json(path: str) -> dict:
    try:
        raw = _read_private(path)
        got = json.loads(raw) if raw is not None else {}
    except (OSError, ValueError):
        return {}
    return got if isinstance(got, dict) else {}


def _write_json_atomic(path: str, value: dict) -> None:
    """The manifest's bytes as before (sorted, indent 1), written by rlu.files.write_atomic (a
    temporary opened with ``O_EXCL | O_NOFOLLOW``, renamed over ``path``)."""
    write_atomic(path, json.dumps(value, indent=1, sort_keys=True))


class _Manifest:
    """``manifest.json``: object -> {size, sha256, url, md5?}; written atomically, thread-safe."""

    def __init__(self, root: str):
        self.path = os.path.join(root, "manifest.json")
        self._lock = threading.Lock()
        # a damaged manifest only costs re-verification by download; a linked one is refused
        self.entries: dict[str, dict] = self._load()

    def _load(self) -> dict[str, dict]:
        got = _read_json(self.path)
        return {k: v for k, v in got.items() if isinstance(k, str) and isinstance(v, dict)}

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
        with self._lock:
            fd = open_private(self.path + ".lock", os.O_RDWR | os.O_CREAT, "cache lock")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
                current = self._load()
                if entry is None:
                    if current.pop(obj, None) is None:
                        self.entries.pop(obj, None)
                        return
                else:
                    current[obj] = entry
                self.entries = current
                _write_json_atomic(self.path, current)
            finally:
                os.close(fd)


def read_manifest(root: str) -> dict[str, dict]:
    """The entries of ``root/manifest.json`` ({} when missing or damaged; a link is refused)."""
    return _Manifest(root).entries


def sha256_file(path: str) -> str:
    h = hashlib.sha256()
    with os.fdopen(open_private(path, os.O_RDONLY, "cache file"), "rb") as f:
        while chunk := f.read(CHUNK * 4):
            h.update(chunk)
    return h.hexdigest()


def _goog_hashes(headers: http.client.HTTPMessage) -> dict[str, str]:
    """``x-goog-hash: crc32c=..., md5=...`` (one header or several) -> {'md5': b64, ...}."""
    out = {}
    for value in headers.get_all("x-goog-hash") or []:
        for part in value.split(","):
            k, _, v = part.strip().partition("=")
            if k and v:
                out[k.lower()] = v.strip()
    return out


# --- what an error means -----------------------------------------------------------------


def _proxy_for(url: str) -> str | None:
    """The proxy urllib sends ``url`` through (from the environment), None when direct."""
    parts = urllib.parse.urlsplit(url)
    proxies = urllib.request.getproxies()
    proxy = proxies.get(parts.scheme)
    if not proxy or (parts.hostname and urllib.request.proxy_bypass(parts.hostname)):
        return None
    return proxy


def classify(exc: BaseException, url: str, timeout: float = DEFAULT_TIMEOUT) -> _Fail:
    """What a failed request means: why (one clause) and whether another try could mend it."""
    parts = urllib.parse.urlsplit(url)
    host = parts.hostname or url
    port = parts.port or (443 if parts.scheme == "https" else 80)
    proxy = _proxy_for(url)
    via = f" (through the proxy {proxy})" if proxy else ""
    if isinstance(exc, urllib.error.HTTPError):
        return _http_status(exc.code, str(exc.reason), url)
    reason: object = exc.reason if isinstance(exc, urllib.error.URLError) else exc
    if isinstance(reason, str):  # urllib's own words: a URL it cannot use
        return _Fail(f"{reason}; check --base-url", permanent=True)
    if isinstance(reason, socket.gaierror):
        where = f"the proxy's host in {proxy}" if proxy else f"the host {host}"
        return _Fail(
            f"{where} cannot be resolved (DNS: {reason.strerror or reason}); offline or "
            f"behind a firewall? {_MIRROR}, or {_PROXY}",
            permanent=True,
        )
    if isinstance(reason, ConnectionRefusedError):
        target = f"the proxy {proxy}" if proxy else f"{host}:{port}"
        return _Fail(
            f"connection refused by {target} (nothing listens there); {_MIRROR}, or {_PROXY}",
            permanent=True,
        )
    if isinstance(reason, (TimeoutError, socket.timeout)):
        return _Fail(f"no answer within --timeout {timeout:g} s{via} ({reason})")
    if isinstance(reason, ssl.SSLCertVerificationError):
        return _Fail(
            f"TLS certificate of {host} not trusted ({reason.verify_message or reason}){via}; a "
            "proxy that inspects HTTPS needs its CA in SSL_CERT_FILE, or " + _MIRROR,
            permanent=True,
        )
    if isinstance(reason, (ssl.SSLEOFError, ssl.SSLZeroReturnError)):
        return _Fail(f"the TLS connection was cut ({reason})")
    if isinstance(reason, ssl.SSLError):
        return _Fail(
            f"TLS failed with {host}:{port} ({reason.reason or reason}){via}; is it an HTTPS "
            f"server? Check --base-url's scheme and port, or {_PROXY}",
            permanent=True,
        )
    if isinstance(reason, OSError) and reason.errno in (
        errno.ENETUNREACH,
        errno.EHOSTUNREACH,
        errno.ENETDOWN,
        errno.EADDRNOTAVAIL,
    ):
        return _Fail(
            f"{host} cannot be reached ({reason.strerror}): offline? {_MIRROR}, or {_PROXY}",
            permanent=True,
        )
    if isinstance(reason, (ConnectionError, http.client.IncompleteRead)):
        return _Fail(f"the connection broke ({type(reason).__name__}: {reason})")
    if isinstance(reason, http.client.HTTPException):
        return _Fail(
            f"{host}:{port} does not answer in HTTP ({type(reason).__name__}: {reason}); "
            "check --base-url",
            permanent=True,
        )
    if isinstance(reason, ValueError):
        return _Fail(f"{reason}; check --base-url", permanent=True)
    return _Fail(f"{type(reason).__name__}: {reason}{via}")


def _http_status(code: int, reason: str, url: str) -> _Fail:
    if code >= 500 or code in (408, 425, 429):
        return _Fail(f"HTTP {code} {reason} (the server is busy or failing)")
    if code in (404, 410):
        fix = "check the task, --shards and --base-url (a mirror keeps the bucket's paths)"
        return _Fail(f"not found (HTTP {code}); {fix}", permanent=True)
    if code in (401, 403, 407):
        who = "a proxy" if code == 407 else "the server"
        return _Fail(
            f"access denied by {who} (HTTP {code} {reason}); the public bucket needs no login: "
            f"{_MIRROR}, or {_PROXY}",
            permanent=True,
        )
    return _Fail(f"HTTP {code} {reason}; check --base-url", permanent=True)


class _Tally:
    """Files done / failed / reused and the bytes fetched, shown by one Progress (thread-safe).

    The total is an estimate: the sizes announced so far plus their mean for each file that has
    not answered yet; reused files count for nothing (nothing to fetch).
    """

    def __init__(self, files: int, progress: bool):
        self.files = files
        self.done = self.failed = self.reused = 0
        self.sizes: dict[str, int] = {}  # object -> bytes it announced it still had to send
        self.bar = Progress(None, "download", "B", quiet=not progress)
        self._lock = threading.Lock()
        self._show()

    def announce(self, obj: str, remaining: int | None) -> None:
        with self._lock:
            if obj not in self.sizes or remaining is not None:
                self.sizes[obj] = remaining or 0
            self._estimate()

    def add(self, n: int) -> None:
        self.bar.update(n)

    def finished(self, f: Fetched) -> None:
        with self._lock:
            self.done += 1
            if f.reused:
                self.reused += 1
            self._estimate()
            self._show()

    def fail(self) -> None:
        with self._lock:
            self.failed += 1
            self._show()

    def _estimate(self) -> None:
        known = sum(self.sizes.values())
        waiting = self.files - len(self.sizes) - self.reused - self.failed
        mean = known / len(self.sizes) if self.sizes else 0
        self.bar.set_total(known + max(0, waiting) * mean or None)

    def _show(self) -> None:
        fields: dict[str, object] = {"files": f"{self.done}/{self.files}"}
        if self.failed:
            fields["failed"] = self.failed
        if self.reused:
            fields["reused"] = self.reused
        self.bar.set_postfix(**fields)

    def summary(self) -> str:
        return f"{self.done} of {self.files} files done, {self.failed} failed"

    def close(self, failed: bool) -> None:
        self.bar.close(failed)


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
        max_bytes: int | None = None,
        lock_wait: float = 0.0,
    ):
        """``progress``: show one (False: nothing; None or True: a bar on a terminal, plain
        lines elsewhere). ``max_bytes``: the bound of a body without a length (default: the
        object's family's largest shard, :func:`rlu.data.release.catalog.shard_limit`).
        ``lock_wait``: seconds to wait for a cache entry another process holds before failing
        with "in use" (0: at once; a cluster's retried shard waits for its lost first try)."""
        self.root = release_dir(cache_dir)
        self.base_url = base_url or os.environ.get("RLU_RELEASE_BASE_URL") or None
        self.workers = max(1, workers)
        self.retries = retries
        self.backoff = backoff
        self.timeout = timeout
        self.progress = progress is not False
        self.verify_reuse = verify_reuse
        self.allow_redirects = allow_redirects
        self.max_bytes = max_bytes
        self.lock_wait = lock_wait
        self.manifest = _Manifest(self.root)
        self.sleep: Callable[[float], object] | None = None  # None: wait, unless stopped
        self._opener = urllib.request.build_opener(_Redirects(allow_redirects))

    def path_of(self, obj: str) -> str:
        parts = obj.split("/")
        if not obj or obj.startswith("/") or any(p in ("", ".", "..") for p in parts):
            raise DownloadError(f"{obj!r} is not a release object name (bucket-relative path)")
        return os.path.join(self.root, *parts)

    def fetch(self, objects: Sequence[str]) -> list[Fetched]:
        """Download (or reuse) every object; returns them in order.

        The first file that fails ends the command: the other workers stop at their next chunk
        (given ``_GRACE`` seconds, then left to finish in the background, writing only their
        ``.part``) and its error is raised, with how many files were done.
        """
        objects = list(objects)
        stop = threading.Event()
        tally = _Tally(len(objects), self.progress)
        results: list[Fetched | None] = [None] * len(objects)
        errors: list[BaseException] = []
        todo = iter(range(len(objects)))
        lock = threading.Lock()

        def work() -> None:
            while not stop.is_set():
                with lock:
                    i = next(todo, None)
                if i is None:
                    return
                obj = objects[i]
                try:
                    results[i] = got = self.fetch_one(
                        obj, tally.add, functools.partial(tally.announce, obj), stop
                    )
                    tally.finished(got)
                except _Stopped:
                    return
                except (KeyboardInterrupt, SystemExit):
                    stop.set()
                    raise
                except BaseException as e:  # the first one ends the command
                    tally.fail()
                    with lock:
                        errors.append(e)
                    stop.set()
                    return

        ok = False
        try:
            if self.workers == 1 or len(objects) <= 1:
                work()
            else:
                # daemon threads: one stuck in a silent socket read cannot hold the command
                threads = [
                    threading.Thread(target=work, name=f"rlu-download-{k}", daemon=True)
                    for k in range(min(self.workers, len(objects)))
                ]
                for t in threads:
                    t.start()
                deadline = None
                while any(t.is_alive() for t in threads):
                    for t in threads:
                        t.join(0.05)
                    if stop.is_set():
                        deadline = deadline or time.monotonic() + _GRACE
                        if time.monotonic() > deadline:
                            break
            ok = not errors
        except BaseException:
            stop.set()  # Ctrl-C: the workers stop at their next chunk
            raise
        finally:
            tally.close(failed=not ok)
        if errors:
            first = errors[0]
            if isinstance(first, DownloadError) and len(objects) > 1:
                raise DownloadError(f"{first} ({tally.summary()})") from None
            raise first
        return [r for r in results if r is not None]

    # --- one file ---

    def fetch_one(
        self,
        obj: str,
        on_bytes: Callable[[int], object] | None = None,
        on_size: Callable[[int | None], object] | None = None,
        stop: threading.Event | None = None,
    ) -> Fetched:
        """Reuse (verified) or download one object under its cache-entry lock.

        ``on_bytes(n)``: n more bytes arrived; ``on_size(n)``: the server announced n bytes still
        to come for this file (None: no length; a later call replaces an earlier one). ``stop``:
        set by another thread to end the download at its next chunk (raises ``_Stopped``).
        Raises :class:`DownloadError` when the file cannot be had intact.
        """
        stop = stop or threading.Event()
        path = self.path_of(obj)
        os.makedirs(os.path.dirname(path), exist_ok=True)
        with OutputLock(path, "cache entry").acquire(self.lock_wait):
            got = self.verify_cached(obj, path)
            if got is not None:
                return got
            return self._download(obj, path, on_bytes or _ignore, on_size or _ignore, stop)

    def verify_cached(self, obj: str, path: str | None = None) -> Fetched | None:
        """The cached file of ``obj`` when the manifest records it and it still verifies (size,
        and with ``verify_reuse`` sha256 and framing); a damaged one is removed (None)."""
        path = path or self.path_of(obj)
        entry = self.manifest.get(obj)
        if os.path.islink(path):
            raise DownloadError(
                f"{path}: a symbolic link where rlu keeps a downloaded shard; rlu never reads its "
                "cache through a link: remove it (and find out who made it)"
            )
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

    def _download(
        self,
        obj: str,
        path: str,
        on_bytes: Callable[[int], object],
        on_size: Callable[[int | None], object],
        stop: threading.Event,
    ) -> Fetched:
        url = object_url(obj, self.base_url)
        part = path + ".part"
        meta_path = part + ".json"
        limit = self.max_bytes or shard_limit(obj)
        sleep = self.sleep or stop.wait
        last = ""
        for attempt in range(self.retries + 1):
            if attempt:
                sleep(min(self.backoff * 2 ** (attempt - 1), MAX_BACKOFF))
            if stop.is_set():
                raise _Stopped
            try:
                self._attempt(url, part, meta_path, limit, on_bytes, on_size, stop)
                why = release_framing(part, obj)
                if why:
                    _remove(part, meta_path)
                    raise _Fail(why)
            except (_Fail, urllib.error.URLError, http.client.HTTPException, OSError,
                    ValueError) as e:  # fmt: skip
                fail = e if isinstance(e, _Fail) else classify(e, url, self.timeout)
                if fail.permanent:
                    _remove_if_empty(part, meta_path)
                    raise DownloadError(f"cannot download {url}: {fail.why}") from None
                last = fail.why
                continue
            digest = sha256_file(part)
            size = os.path.getsize(part)
            move_into_place(part, path)
            meta = _read_json(meta_path)
            _remove(meta_path)
            entry = {"size": size, "sha256": digest, "url": url}
            if meta.get("md5"):
                entry["md5"] = meta["md5"]
            self.manifest.put(obj, entry)
            return Fetched(obj, path, size, digest, False)
        _remove_if_empty(part, meta_path)
        have = os.path.getsize(part) if os.path.isfile(part) else 0
        kept = (
            f"the {have:,} bytes so far are kept in {part}: run the command again to resume"
            if have
            else "run the command again later"
        )
        raise DownloadError(
            f"could not download {url} after {self.retries + 1} tries: {last}; {kept}, or {_MIRROR}"
        )

    def _attempt(
        self,
        url: str,
        part: str,
        meta_path: str,
        limit: int,
        on_bytes: Callable[[int], object],
        on_size: Callable[[int | None], object],
        stop: threading.Event,
    ) -> None:
        """One request; returns when ``part`` holds the whole object, checked against the
        headers (length, hashes) and ``limit``; raises :class:`_Fail` (or a network error for
        :func:`classify`) otherwise. The caller checks the framing."""
        have = os.path.getsize(part) if os.path.isfile(part) and not os.path.islink(part) else 0
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
                raise _Fail("HTTP 416 on resume; starting over") from None
            raise _http_status(e.code, str(e.reason), url) from None
        with resp:
            status = resp.status
            headers = resp.headers
            ctype = (headers.get("Content-Type") or "").split(";")[0].strip().lower()
            if ctype in ("text/html", "application/xhtml+xml"):
                raise _Fail(
                    f"the server answers with a web page ({ctype}), not a release file; check "
                    "--base-url (a login, error or captive-portal page?)",
                    permanent=True,
                )
            if status == 206 and have:
                total = _content_range_total(headers.get("Content-Range"))
                append = True
            else:
                have = 0
                total = _int(headers.get("Content-Length"))
                append = False
                meta = {"etag": headers.get("ETag"), "size": total, **_goog_hashes(headers)}
            if total is None:
                total = meta.get("size")
            if total is not None and total > limit:
                raise _Fail(
                    f"the server announces {total:,} bytes, more than any shard of this family "
                    f"({limit:,}): not a release file; check --base-url",
                    permanent=True,
                )
            on_size(None if total is None else total - have)
            flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
            fd = open_private(part, flags, "partial download")
            if not append:
                _write_private(meta_path, json.dumps(meta).encode())
            with os.fdopen(fd, "wb") as f:
                longer = _copy_body(resp, f, part, limit - have, on_bytes, stop)
        _check_body(part, meta_path, meta, total, limit, longer)


def _check_body(
    part: str, meta_path: str, meta: dict[str, Any], total: int | None, limit: int, longer: str
) -> None:
    """After a request's body: ``part`` is the whole object (its announced length and hashes)
    or :class:`_Fail` says why not, the part removed where resuming it cannot help;
    ``longer`` is what ``_copy_body`` found past the end."""
    size = os.path.getsize(part)
    if longer == "over":
        _remove(part, meta_path)
        raise _Fail(
            f"the body goes on past {limit:,} bytes without a length, more than any shard "
            "of this family: a broken or hostile server; check --base-url",
            permanent=True,
        )
    if longer:
        _remove(part, meta_path)
        raise _Fail("the server sent more bytes than its Content-Length announced")
    if total is not None and size < total:
        raise _Fail(f"connection closed after {size:,} of {total:,} bytes")
    if total is not None and size > total:
        _remove(part, meta_path)
        raise _Fail(f"received {size:,} bytes, more than the {total:,} announced")
    why = _check_hashes(part, meta)
    if why:
        _remove(part, meta_path)
        raise _Fail(why)


def _ignore(*_: object) -> None:
    pass


def _write_private(path: str, data: bytes) -> None:
    fd = open_private(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, "download note")
    with os.fdopen(fd, "wb") as f:
        f.write(data)


class _Redirects(urllib.request.HTTPRedirectHandler):
    """Follow redirects on the same host; to another host only when allowed (a mirror that
    redirects to a CDN: ``--allow-redirects``)."""

    def __init__(self, allow: bool):
        self.allow = allow

    def redirect_request(
        self,
        req: urllib.request.Request,
        fp: IO[bytes],
        code: int,
        msg: str,
        headers: http.client.HTTPMessage,
        newurl: str,
    ) -> urllib.request.Request | None:
        old = urllib.parse.urlsplit(req.full_url).hostname
        new = urllib.parse.urlsplit(urllib.parse.urljoin(req.full_url, newurl)).hostname
        if old != new and not self.allow:
            raise DownloadError(
                f"{req.full_url}: the server redirects (HTTP {code}) to another host, {new}; "
                "rlu follows redirects to other hosts only with --allow-redirects"
            )
        return super().redirect_request(req, fp, code, msg, headers, newurl)


def _copy_body(
    resp: http.client.HTTPResponse,
    f: BinaryIO,
    part: str,
    limit: int,
    on_bytes: Callable[[int], object],
    stop: threading.Event,
) -> str:
    """Copy the body to ``f``: '' when whole, 'longer' when the server sent more than its
    Content-Length, 'over' when a body without a length went past ``limit`` bytes.

    ``http.client`` stops reading at Content-Length and drops the rest silently, so with a length
    the body is read from the connection itself, then one more byte is asked for: the request
    said ``Connection: close``, so an honest server has closed it (EOF) by then. Without a length
    (chunked, or until close) at most ``limit + 1`` bytes are read.
    """
    declared = resp.length
    if resp.chunked or declared is None:
        left = limit + 1
        while left > 0 and (chunk := resp.read(min(CHUNK, left))):
            _write(f, chunk, part)
            on_bytes(len(chunk))
            left -= len(chunk)
            if stop.is_set():
                raise _Stopped
        return "over" if left <= 0 else ""
    fp = resp.fp
    left = declared
    while left > 0:
        chunk = fp.read(min(CHUNK, left))
        if not chunk:
            return ""  # cut: the size check names it
        _write(f, chunk, part)
        on_bytes(len(chunk))
        left -= len(chunk)
        if stop.is_set():
            raise _Stopped
    try:
        return "longer" if fp.read1(1) else ""
    except TimeoutError:
        return ""  # a server that keeps the connection open sent nothing more


def _write(f: BinaryIO, chunk: bytes, part: str) -> None:
    """A failed write (a full disk) is this machine's, not the server's: it ends the command."""
    try:
        f.write(chunk)
    except OSError as e:
        raise DownloadError(
            f"{part}: cannot write the download ({e.strerror or e}); free space or choose "
            "another --cache-dir"
        ) from None


def release_framing(path: str, obj: str) -> str:
    """Why ``path`` is not a release file of ``obj``'s family ('' when it looks like one).

    The catalog knows each object's family, so its framing: a gzip stream, or (RWRL) a plain
    TFRecord, whose first record header must carry a valid length CRC. An HTML page, a JSON
    error or a truncated first block fails here, before the file is recorded.
    """
    from rlu.data.release.families import FAMILIES
    from rlu.data.release.framing import GZIP_MAGIC, masked_crc32c

    fam = FAMILIES.get(obj.split("/", 1)[0])
    if fam is None:
        return ""  # not a catalog object: nothing is known to check
    with os.fdopen(open_private(path, os.O_RDONLY, "partial download"), "rb") as f:
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
    if struct.unpack("<I", head[8:12])[0] != masked_crc32c(head[:8]):
        return f"its first record header is not TFRecord framing: not a {fam.name} shard"
    if length > fam.max_record_bytes:
        return (
            f"its first record declares {length:,} bytes, over the {fam.max_record_bytes:,} a "
            f"{fam.name} record may have ({fam.record_note}): not a {fam.name} shard"
        )
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
    with os.fdopen(open_private(path, os.O_RDONLY, "partial download"), "rb") as f:
        while chunk := f.read(CHUNK * 4):
            h.update(chunk)
            if c is not None:
                c.update(chunk)
    if md5 and base64.b64encode(h.digest()).decode() != md5:
        return "MD5 mismatch against the bucket's x-goog-hash (corrupt transfer)"
    if c is not None and base64.b64encode(c.digest()).decode() != crc:
        return "CRC-32C mismatch against the bucket's x-goog-hash (corrupt transfer)"
    return ""


def _remove(*paths: str) -> None:
    for p in paths:
        if os.path.lexists(p) and not os.path.isdir(p):
            os.remove(p)  # a link is removed, never what it points to


def _remove_if_empty(part: str, meta_path: str) -> None:
    """Drop a ``.part`` that holds no byte (and its note): nothing to resume from."""
    if os.path.isfile(part) and not os.path.islink(part) and os.path.getsize(part) == 0:
        _remove(part, meta_path)


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
    **kw: Any,
) -> list[Fetched]:
    """Fetch ``objects`` (bucket-relative names) into the cache; returns where they are."""
    return Downloader(cache_dir=cache_dir, base_url=base_url, **kw).fetch(objects)
