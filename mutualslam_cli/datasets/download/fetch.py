"""HTTP for ``mslam datasets download``: one URL into ``NAME.part``, resumed only when it is the same file.

- A fresh download records the entity it receives — URL, ``ETag``, ``Last-Modified``, size — in
  ``NAME.partinfo`` beside ``NAME.part`` before the first byte is written.
- A ``.part`` is resumed only when its ``.partinfo`` names the same URL and a validator (a strong
  ETag, else Last-Modified): the request carries ``Range: bytes=N-`` *and* ``If-Range: <validator>``,
  so a server whose file changed answers 200 with the new file instead of splicing its tail on.
  A ``.part`` without such a record (another tool's, an older mslam's, a server without validators)
  is downloaded anew.
- Answers to a resume: 206 starting at byte N, with the recorded size and (when it sends one) the
  recorded ETag → appended; 200 → the whole file anew (another entity, or a server without ranges);
  416 with size N → the ``.part`` is already complete; anything else → started over without ``Range``.
- A fresh request accepts only ``200``, or ``206`` starting at byte 0 (a server that answers a plain GET
  with another range would have those bytes kept as the start of the file); a resume accepts only the
  exact range it asked for (``N`` to the end of the recorded size), else it starts over.
- ``NAME.part`` is opened with ``O_NOFOLLOW`` and ``NAME.partinfo`` is read through its schema
  (:mod:`~mutualslam_cli.datasets.download.files`): a link is refused, a damaged record means starting over.
- Redirects from ``https`` to ``http`` are refused (a downgrade would drop the server's authentication).

Timeouts in seconds, sizes in bytes (MB = 10⁶ bytes in messages).
"""

from __future__ import annotations

import errno
import http.client
import json
import os
import re
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import asdict, dataclass
from email.message import Message
from pathlib import Path
from types import TracebackType
from typing import IO, Protocol

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.download.files import (
    OPTIONAL_COUNT,
    OPTIONAL_TEXT,
    TEXT,
    Schema,
    count_field,
    open_no_follow,
    read_record,
    refuse_link,
    text_field,
)
from mutualslam_cli.errors import DamagedRecord, DatasetError
from mutualslam_cli.types import Progress

TIMEOUT_S = 60.0
"""Seconds to wait for a connection or for the next bytes of a response."""

#: ``progress(stage, info)``: stage ``"download"`` with ``done``/``total`` bytes (``total`` None when the
#: server does not say), ``file`` and ``url``; stage ``"unpack"`` with ``done``/``total`` bytes of the archive
#: and ``file``.
DownloadProgress = Progress

_CHUNK = 1 << 20
_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")
_RANGE_TOTAL = re.compile(r"bytes\s+\*/(\d+)")
PARTINFO_SCHEMA: Schema = {"url": TEXT, "etag": OPTIONAL_TEXT, "last_modified": OPTIONAL_TEXT, "total": OPTIONAL_COUNT}
"""The fields of ``NAME.partinfo`` (an :class:`Entity`)."""


@dataclass(frozen=True)
class Entity:
    """The version of a file a server sent: its URL, validators and size in bytes (``None``: not said)."""

    url: str
    etag: str | None = None
    last_modified: str | None = None
    total: int | None = None

    @property
    def validator(self) -> str | None:
        """What ``If-Range`` may carry: the strong ETag, else Last-Modified (weak ETags never match)."""
        if self.etag and not self.etag.startswith("W/"):
            return self.etag
        return self.last_modified

    def changes(self, new: Entity) -> list[str]:
        """What differs between this entity and ``new`` (ETag, Last-Modified, size), where both say."""
        out = []
        for label, a, b in (("ETag", self.etag, new.etag), ("Last-Modified", self.last_modified, new.last_modified),
                            ("size", self.total, new.total)):
            if a is not None and b is not None and a != b:
                out.append(f"{label} {a} → {b}")
        return out


@dataclass
class Fetched:
    """One finished fetch: ``size`` bytes in the ``.part``, ``resumed_from`` bytes that were there, the
    ``entity`` they belong to, and a ``note`` when a ``.part`` was discarded (why)."""

    size: int
    resumed_from: int
    entity: Entity
    note: str | None = None


def _mb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e6:.{1 if n >= 1e6 else 3}f}"


class Response(Protocol):
    """An HTTP answer as urllib gives it: ``http.client.HTTPResponse``, or the ``HTTPError`` of a 416."""

    @property
    def headers(self) -> Message: ...

    def getcode(self) -> int | None: ...

    def read(self, amt: int, /) -> bytes: ...

    def close(self) -> None: ...

    def __enter__(self) -> Response: ...

    def __exit__(self, kind: type[BaseException] | None, value: BaseException | None,
                 traceback: TracebackType | None, /) -> None: ...


class _NoDowngrade(urllib.request.HTTPRedirectHandler):
    """Follows redirects, except from https to anything else."""

    def redirect_request(self, req: urllib.request.Request, fp: IO[bytes], code: int, msg: str,
                         headers: http.client.HTTPMessage, newurl: str) -> urllib.request.Request | None:
        if urllib.parse.urlsplit(req.full_url).scheme == "https" and urllib.parse.urlsplit(newurl).scheme != "https":
            raise DatasetError(f"{req.full_url}: the server redirects to {newurl}, which is not https; refused "
                               "(the file would arrive unauthenticated)")
        return super().redirect_request(req, fp, code, msg, headers, newurl)


_OPENER = urllib.request.build_opener(_NoDowngrade)
_OPENER_MAX_REDIRECTS = _NoDowngrade.max_redirections


def _open(url: str, timeout: float, start: int = 0, if_range: str | None = None) -> Response:
    """The response to GET ``url`` (``Range: bytes=start-`` and ``If-Range`` when resuming); a 416 answer to a
    resume is returned, not raised."""
    headers = {"User-Agent": "mslam-datasets-download"}
    if start:
        headers["Range"] = f"bytes={start}-"
        if if_range:
            headers["If-Range"] = if_range
    try:
        return _OPENER.open(urllib.request.Request(url, headers=headers), timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code == 416 and start:
            return e
        if 300 <= e.code < 400:
            raise DatasetError(f"{url}: the server redirects in a loop or more than {_OPENER_MAX_REDIRECTS} times "
                               f"(last answer HTTP {e.code}); expected the file (check the URL in datasets.yaml or "
                               "--base-url)") from None
        raise DatasetError(f"{url}: HTTP {e.code} {e.reason}; expected the file (check the URL in datasets.yaml "
                           "or --base-url)") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
        raise DatasetError(f"{url}: cannot connect ({getattr(e, 'reason', e)}); check the network, the URL or "
                           "--base-url") from None
    except ValueError:
        raise DatasetError(f"{url}: expected an http:// or https:// URL") from None


def _entity(url: str, resp: Response) -> Entity:
    h = resp.headers
    m = _CONTENT_RANGE.match(h.get("Content-Range", ""))
    length = h.get("Content-Length")
    total = (int(m.group(3)) if m.group(3) != "*" else None) if m else (int(length) if length and length.isdigit()
                                                                        else None)
    return Entity(url, h.get("ETag"), h.get("Last-Modified"), total)


def read_partinfo(path: Path) -> Entity | None:
    """The entity recorded in a ``.partinfo`` file, or ``None`` when there is none.

    Raises:
        DamagedRecord: a link, or a record of another shape than :data:`PARTINFO_SCHEMA`.
    """
    rec = read_record(path, PARTINFO_SCHEMA)
    if rec is None:
        return None
    return Entity(str(rec["url"]), text_field(rec, "etag"), text_field(rec, "last_modified"), count_field(rec, "total"))


def _fresh_range_ok(url: str, resp: Response) -> None:
    """Refuse an answer to a request without ``Range`` that is not the file from byte 0."""
    code = resp.getcode()
    m = _CONTENT_RANGE.match(resp.headers.get("Content-Range", ""))
    if code == 200 or (code == 206 and m and int(m.group(1)) == 0):
        return
    resp.close()
    what = f"HTTP {code}" + (f" with Content-Range {resp.headers.get('Content-Range')}" if code == 206 else "")
    raise DatasetError(f"{url}: the server answered a request for the whole file with {what}; expected 200, or "
                       "206 starting at byte 0; nothing was kept")


def _exact_range(m: re.Match[str] | None, have: int, rec: Entity) -> bool:
    """True when ``Content-Range`` match ``m`` is the range a resume asked for: ``have`` to the recorded end."""
    if m is None or m.group(3) == "*" or int(m.group(1)) != have:
        return False
    total = int(m.group(3))
    return int(m.group(2)) == total - 1 and rec.total in (None, total)


def _begin(url: str, part: Path, info: Path, timeout: float) -> tuple[Response | None, int, Entity, str | None]:
    """Open ``url`` for the rest of ``part``: ``(response or None, start byte, entity, note)``; ``None`` as the
    response: ``part`` is already complete. A fresh start records its entity in ``info`` first."""
    refuse_link(part)
    have = part.stat().st_size if part.is_file() else 0
    rec, note = None, None
    if have:
        try:
            rec = read_partinfo(info)
        except DamagedRecord as e:  # never trusted: the .part is downloaded anew
            note = f"{e}: damaged record, starting over"
    if have and note is None and (rec is None or rec.url != url or rec.validator is None):
        note = (f"{part.name}: {_mb(have)} MB with no record of which version of the file they belong to; "
                "downloading the file anew")
    elif have and rec is not None:
        resp = _open(url, timeout, have, rec.validator)
        got = _entity(url, resp)
        code = resp.getcode()
        if code == 416:
            m = _RANGE_TOTAL.match(resp.headers.get("Content-Range", ""))
            resp.close()
            if m and int(m.group(1)) == have and rec.total in (None, have):
                return None, have, rec, None
            note = f"{part.name}: the server's file is not the {_mb(have)} MB already here; downloading it anew"
        elif code == 206:
            m = _CONTENT_RANGE.match(resp.headers.get("Content-Range", ""))
            if _exact_range(m, have, rec) and not rec.changes(got):
                return resp, have, rec, None
            resp.close()
            note = (f"{part.name}: the server's file changed since it was partly downloaded "
                    f"({'; '.join(rec.changes(got)) or 'another byte range'}); downloading it anew")
        elif code != 200:
            resp.close()
            note = f"{part.name}: the server answered the resume with HTTP {code}; downloading the file anew"
        else:  # 200: the whole file — another version (If-Range did not match) or a server without ranges
            changed = rec.changes(got)
            note = (f"{part.name}: the server's file changed since it was partly downloaded ({'; '.join(changed)}); "
                    "downloading it anew" if changed else
                    f"{part.name}: the server sent the whole file instead of the rest; downloading it anew")
            atomic_write_text(info, json.dumps(asdict(got)) + "\n")
            return resp, 0, got, note
    resp = _open(url, timeout)
    _fresh_range_ok(url, resp)
    got = _entity(url, resp)
    atomic_write_text(info, json.dumps(asdict(got)) + "\n")
    return resp, 0, got, note


def fetch(url: str, dest: Path, progress: DownloadProgress | None = None, timeout: float = TIMEOUT_S) -> Fetched:
    """Download ``url`` into ``dest`` + ``.part``, resuming an existing ``.part`` of the same entity.

    The ``.part`` (and its ``.partinfo``) are left in place on any failure, and are complete (not renamed)
    on success.

    Raises:
        DatasetError: HTTP error, no connection, a downgrading redirect, an interrupted transfer (``.part``
            kept for resuming), more bytes than announced, or a full disk.
    """
    part = dest.with_name(dest.name + ".part")
    info = dest.with_name(dest.name + ".partinfo")
    resp, start, ent, note = _begin(url, part, info, timeout)
    if resp is None:
        return Fetched(start, start, ent, note)
    done, total = start, ent.total
    buf: bytes | None = b""  # None: the connection failed mid-transfer
    flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if start else os.O_TRUNC)
    with resp, os.fdopen(open_no_follow(part, flags), "ab" if start else "wb") as f:
        while True:
            try:
                buf = resp.read(_CHUNK)
            except (OSError, http.client.HTTPException):
                buf = None
            if not buf:
                break
            try:
                f.write(buf)
            except OSError as e:
                if e.errno == errno.ENOSPC:
                    raise DatasetError(f"no space left on device while downloading {url} to {part} "
                                       f"({_mb(done)} of {_mb(total)} MB written, kept for resuming); free some "
                                       "space and run the command again") from None
                raise DatasetError(f"{part}: cannot write ({e.strerror or e})") from None
            done += len(buf)
            if progress:
                progress("download", {"done": done, "total": total, "file": dest.name, "url": url})
    if total is not None and done > total:
        part.unlink(missing_ok=True)
        info.unlink(missing_ok=True)
        raise DatasetError(f"{url}: the server sent {done} bytes, it announced {total}; removed {part.name}, run "
                           "the command again")
    if (total is not None and done < total) or buf is None:
        again = ("run the command again to resume" if ent.validator else "run the command again to download it "
                 "anew (the server names no ETag or Last-Modified, so a cut download cannot be resumed safely)")
        raise DatasetError(f"download of {url} interrupted at {_mb(done)} of {_mb(total)} MB; {again}")
    return Fetched(done, start, ent, note)
