"""HTTP with retries, endpoint failover and an on-disk cache (private helper).

One function, :func:`fetch`, in the spirit of osmnx's downloader:

* tries each endpoint URL in order; on one endpoint it makes ``1 + retries`` attempts with
  exponential backoff (``backoff_base_s * 2**k`` plus up to 25 % jitter, every wait capped
  at ``max_wait_s``); a ``Retry-After`` header on 429/503 is honoured, also capped;
* retries on HTTP 408/429/5xx, timeouts, broken connections and answers that the caller's
  ``validate(body)`` rejects ("garbage"); moves on to the next endpoint at once on
  connection refused / unknown host (when another endpoint is left) and on other 4xx
  answers (the same request would get the same answer);
* caches the validated body in ``cache_dir/<namespace>/<sha256(key)><suffix>``; the key
  is built by the caller from the request alone (never the endpoint URL), so an answer is
  reused whichever server gave it. Writes are atomic (temp file in the same folder, fsync,
  ``os.replace``), so a build killed mid-write never leaves a partial entry under the final
  name; a cached file that fails ``validate`` is ignored and fetched again;
* when everything failed it raises :class:`ServiceError` with one line naming the service,
  what happened last and the URLs tried; failing to write the cache (full disk, read-only
  folder) raises :class:`BuildError`.
"""
from __future__ import annotations

import email.utils
import errno
import hashlib
import logging
import os
import random
import re
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import requests

from .errors import BuildError, ServiceError

log = logging.getLogger("netgen.http")

USER_AGENT = "cosim/0.1 (netgen; +https://www.openstreetmap.org/copyright)"
DEFAULT_BACKOFF_BASE_S = 1.0
DEFAULT_MAX_WAIT_S = 30.0
_STALE_TMP_S = 6 * 3600.0   # temp files older than this in a cache folder are leftovers of a killed run


class Garbage(ValueError):
    """Raised by a ``validate`` callback: the answer is not what the service should send."""


@dataclass
class Fetched:
    body: bytes
    path: Path | None        # the cache file (None when caching is off)
    from_cache: bool
    url: str | None          # the endpoint that answered (None from the cache)
    attempts: int            # HTTP attempts made (0 from the cache)


class _Failure(Exception):
    """One failed attempt; ``what`` is a short user-facing description."""

    def __init__(self, what: str, *, retry: bool = True, next_endpoint: bool = False,
                 retry_after: float | None = None):
        super().__init__(what)
        self.what = what
        self.retry = retry                  # worth trying this endpoint again
        self.next_endpoint = next_endpoint  # go to the next endpoint now, if there is one
        self.retry_after = retry_after


def cache_file(cache_dir: str | os.PathLike, namespace: str, key: str | bytes, suffix: str = "") -> Path:
    """Where the answer to the request ``key`` is cached."""
    if isinstance(key, str):
        key = key.encode("utf-8")
    return Path(cache_dir) / namespace / (hashlib.sha256(key).hexdigest() + suffix)


def _fmt_s(s: float) -> str:
    return f"{s:g}"


def _short(text: str, n: int = 120) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= n else text[: n - 3] + "..."


def _parse_retry_after(value: str | None) -> float | None:
    if not value:
        return None
    value = value.strip()
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError, IndexError):
        return None
    if when is None:
        return None
    return max(0.0, when.timestamp() - time.time())


def _describe_connection_error(exc: Exception, timeout_s: float) -> _Failure:
    text = str(exc)
    low = text.lower()
    if "timed out" in low or "timeout" in low:
        return _Failure(f"timed out after {_fmt_s(timeout_s)} s")
    if "refused" in low:
        return _Failure("connection refused", next_endpoint=True)
    if ("name or service not known" in low or "nodename nor servname" in low
            or "temporary failure in name resolution" in low or "getaddrinfo failed" in low
            or "no address associated" in low):
        return _Failure("host not found", next_endpoint=True)
    if ("incompleteread" in low or "connection broken" in low or "remotedisconnected" in low
            or "connection aborted" in low or "reset by peer" in low or "protocolerror" in low):
        return _Failure("connection broken before the answer was complete")
    m = re.search(r"\[Errno -?\d+\] ([^'\")]+)", text)
    return _Failure(f"connection failed: {_short(m.group(1) if m else text, 80)}")


def _attempt(session: requests.Session, method: str, url: str, timeout_s: float, *,
             data=None, json_body=None, params=None, headers=None,
             validate: Callable[[bytes], None] | None) -> bytes:
    try:
        r = session.request(method, url, data=data, json=json_body, params=params,
                            headers=headers, timeout=(timeout_s, timeout_s))
        body = r.content
    except requests.Timeout:
        raise _Failure(f"timed out after {_fmt_s(timeout_s)} s")
    except requests.RequestException as e:  # ConnectionError, ChunkedEncodingError, ...
        raise _describe_connection_error(e, timeout_s)
    if r.status_code != 200:
        what = f"HTTP {r.status_code} {r.reason or ''}".strip()
        if r.status_code in (429, 503):
            raise _Failure(what, retry_after=_parse_retry_after(r.headers.get("Retry-After")))
        if r.status_code in (408, 425) or r.status_code >= 500:
            raise _Failure(what)
        # another 4xx: this server will give the same answer to the same request
        snippet = _short(re.sub(rb"<[^>]*>", b" ", body[:2000]).decode("utf-8", "replace"), 100)
        raise _Failure(what + (f": {snippet}" if snippet else ""), retry=False)
    if validate is not None:
        try:
            validate(body)
        except Exception as e:  # the validator's job is to raise on garbage, whatever it is
            raise _Failure(f"answered garbage: {_short(str(e) or type(e).__name__)}")
    return body


def _write_atomic(path: Path, body: bytes) -> None:
    """Write ``body`` to ``path`` so that ``path`` is either absent, old, or complete."""
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".tmp-")
        with os.fdopen(fd, "wb") as f:
            f.write(body)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
        tmp = None
        try:  # make the rename itself durable; not possible everywhere, and not essential
            dfd = os.open(path.parent, os.O_RDONLY)
            try:
                os.fsync(dfd)
            finally:
                os.close(dfd)
        except OSError:
            pass
    except OSError as e:
        reason = os.strerror(e.errno) if e.errno else str(e)
        hint = " (free some disk space or choose another --cache-dir)" if e.errno in (
            errno.ENOSPC, errno.EDQUOT, errno.EFBIG) else ""
        raise BuildError(f"cannot write cache file {path}: {reason}{hint}") from None
    finally:
        if tmp is not None:
            try:
                os.unlink(tmp)
            except OSError:
                pass


def _clean_stale_tmp(folder: Path) -> None:
    try:
        now = time.time()
        for p in folder.glob("*.tmp-*"):
            try:
                if now - p.stat().st_mtime > _STALE_TMP_S:
                    p.unlink()
            except OSError:
                pass
    except OSError:
        pass


def read_cached(path: Path, validate: Callable[[bytes], None] | None) -> bytes | None:
    """The cached body at ``path`` if it exists and passes ``validate``; else None."""
    try:
        body = path.read_bytes()
    except OSError:
        return None
    if validate is not None:
        try:
            validate(body)
        except Exception as e:
            log.warning("ignoring invalid cache file %s (%s); fetching again", path, _short(str(e), 80))
            return None
    return body


def fetch(service: str, urls: Sequence[str], *, key: str | bytes | None = None,
          cache_dir: str | os.PathLike | None = None, namespace: str = "http", suffix: str = "",
          method: str = "POST", data=None, json_body=None, params=None, headers: dict | None = None,
          validate: Callable[[bytes], None] | None = None,
          timeout_s: float = 60.0, retries: int = 3,
          backoff_base_s: float = DEFAULT_BACKOFF_BASE_S, max_wait_s: float = DEFAULT_MAX_WAIT_S,
          session: requests.Session | None = None) -> Fetched:
    """Fetch one request from the first endpoint that gives a valid answer (see module doc).

    ``key`` identifies the request for the cache (no caching when it or ``cache_dir`` is
    None); it must not contain the endpoint URL. ``validate(body)`` raises on garbage.
    """
    urls = [u for u in (urls or []) if u]
    if not urls:
        raise ServiceError(f"{service}: no server URL configured")
    retries = max(0, int(retries))
    timeout_s = float(timeout_s)

    path = None
    if key is not None and cache_dir is not None:
        path = cache_file(cache_dir, namespace, key, suffix)
        body = read_cached(path, validate)
        if body is not None:
            log.debug("%s: cache hit %s", service, path)
            return Fetched(body, path, True, None, 0)

    hdrs = {"User-Agent": USER_AGENT}
    hdrs.update(headers or {})
    own_session = session is None
    session = session or requests.Session()
    attempts = 0
    tried: list[str] = []
    last: dict[str, str] = {}
    last_what, last_url = "no attempt made", urls[0]
    try:
        for ui, url in enumerate(urls):
            tried.append(url)
            more_endpoints = ui + 1 < len(urls)
            for k in range(retries + 1):
                attempts += 1
                try:
                    body = _attempt(session, method, url, timeout_s, data=data, json_body=json_body,
                                    params=params, headers=hdrs, validate=validate)
                except _Failure as f:
                    last_what, last_url, last[url] = f.what, url, f.what
                    if not f.retry or (f.next_endpoint and more_endpoints) or k == retries:
                        if more_endpoints:
                            log.warning("%s: %s from %s; trying %s", service, f.what, url, urls[ui + 1])
                        break
                    wait = backoff_base_s * (2 ** k)
                    wait += random.uniform(0, 0.25 * wait)
                    if f.retry_after is not None:
                        wait = max(wait, f.retry_after)
                    wait = max(0.0, min(wait, max_wait_s))
                    log.warning("%s: %s from %s; retry %d/%d in %.1f s",
                                service, f.what, url, k + 1, retries, wait)
                    time.sleep(wait)
                    continue
                if path is not None:
                    _write_atomic(path, body)
                    _clean_stale_tmp(path.parent)
                return Fetched(body, path, False, url, attempts)
    finally:
        if own_session:
            session.close()
    head = f"{service} failed after {attempts} attempt{'s' if attempts != 1 else ''}"
    if len(tried) == 1:
        raise ServiceError(f"{head}: {last_what} (tried {tried[0]})")
    tried_txt = ", ".join(f"{u} ({last[u]})" for u in tried)
    raise ServiceError(f"{head}: last {last_what} from {last_url}; tried {tried_txt}")
