"""``<data root>/_downloads/checksums.json``: what each downloaded file was when it first proved whole.

None of the publishers gives checksums, so the first complete download whose archive unpacked is
trusted and recorded — its SHA-256, size in bytes, URL, the server's ``ETag`` and ``Last-Modified``, and
the date — and every later download of the same file name is compared with it. A mismatch says which
it is: the publisher's file *changed* (another size, ETag or Last-Modified than recorded: delete the
entry to accept the new version) or the bytes are *corrupt* (same size and ETag: download again). A
checksum published in ``datasets.yaml`` (``checksums:``) wins over the record.

Several processes may record files at once (different entries, one data root): each update re-reads
the file under a short lock (:func:`~mutualslam_cli.datasets.download.lock.locked_update`) and
replaces it atomically, so no record is lost.

Each entry is read through its schema (:data:`CHECKSUM_SCHEMA`, :mod:`~mutualslam_cli.datasets.download.files`):
an entry of another shape is never trusted; the line names the entry and field and says to delete it.
The file itself and the files it checks are opened without following symbolic links.
"""

from __future__ import annotations

import hashlib
import json
import os
from datetime import date
from pathlib import Path

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.download.fetch import Entity
from mutualslam_cli.datasets.download.files import (
    COUNT,
    OPTIONAL_TEXT,
    SHA256,
    TEXT,
    Schema,
    check_record,
    count_field,
    open_no_follow,
    read_text_no_follow,
    text_field,
)
from mutualslam_cli.datasets.download.lock import locked_update
from mutualslam_cli.errors import DamagedRecord, DatasetError
from mutualslam_cli.types import JSONObject

CHECKSUMS_FILE = "checksums.json"
ALGORITHMS = ("sha256", "md5")
_CHUNK = 1 << 20
CHECKSUM_SCHEMA: Schema = {"sha256": SHA256, "bytes": COUNT, "url": TEXT, "etag": OPTIONAL_TEXT,
                           "last_modified": OPTIONAL_TEXT, "recorded": OPTIONAL_TEXT}
"""The fields of one entry of ``checksums.json``."""


class ChecksumStore:
    """``checksums.json``: file name → ``{"sha256", "bytes", "url", "etag", "last_modified", "recorded"}``."""

    def __init__(self, path: Path):
        self.path = path
        self.data: JSONObject = self._load()  # entries unchecked until read (get)

    def _load(self) -> JSONObject:
        text = read_text_no_follow(self.path, limit=64 << 20)
        if text is None:
            return {}
        try:
            data = json.loads(text)
            if not isinstance(data, dict):
                raise ValueError
        except ValueError:
            raise DatasetError(f"{self.path}: invalid JSON; expected file name → {{sha256, bytes, url}} "
                               "(delete it to record the checksums anew)") from None
        return data

    def get(self, name: str) -> JSONObject | None:
        """The record of file ``name``, if any.

        Raises:
            DamagedRecord: the entry is not of the shape mslam writes (:data:`CHECKSUM_SCHEMA`).
        """
        rec = self.data.get(name)
        if rec is None:
            return None
        try:
            return check_record(rec, CHECKSUM_SCHEMA, f"{self.path}: entry {name!r}")
        except DamagedRecord as e:
            raise DamagedRecord(f"{e}; the record is not trusted: delete the entry {name!r} (or the whole "
                                f"{self.path.name}) and run the command again to record the checksum anew") from None

    def put(self, name: str, sha256: str, size: int, entity: Entity) -> JSONObject:
        """Record file ``name`` (merged into the file as it is now on disk, saved atomically); returns the record."""
        record: JSONObject = {"sha256": sha256, "bytes": size, "url": entity.url, "etag": entity.etag,
                  "last_modified": entity.last_modified, "recorded": date.today().isoformat()}
        with locked_update(self.path):
            self.data = self._load()
            self.data[name] = record
            atomic_write_text(self.path, json.dumps(self.data, indent=2, sort_keys=True) + "\n")
        return record

    def drop(self, name: str) -> None:
        """Forget file ``name`` (saved at once)."""
        with locked_update(self.path):
            self.data = self._load()
            if self.data.pop(name, None) is not None:
                atomic_write_text(self.path, json.dumps(self.data, indent=2, sort_keys=True) + "\n")


def digests(path: Path, algos: set[str]) -> dict[str, str]:
    """Hex digests of the file ``path`` (algorithm name → hex)."""
    hs = {a: hashlib.new(a) for a in algos}
    with os.fdopen(open_no_follow(path, os.O_RDONLY), "rb") as f:
        while buf := f.read(_CHUNK):
            for h in hs.values():
                h.update(buf)
    return {a: h.hexdigest() for a, h in hs.items()}


def verify(path: Path, name: str, url: str, entity: Entity | None, published: tuple[str, str] | None,
           store: ChecksumStore) -> str:
    """SHA-256 of ``path`` (file ``name`` from ``url``) after checking it against the ``published``
    ``(algorithm, hex)`` or the recorded checksum; ``entity``: what the server said of it (``None`` for a
    file downloaded before).

    Raises:
        DatasetError: a mismatch; the file is removed and the line says whether the publisher's file
            changed (size, ETag, Last-Modified or URL differ from the record) or the bytes are corrupt.
    """
    got = digests(path, {"sha256"} | ({published[0]} if published else set()))
    size = path.stat().st_size
    problem, again = None, "run the command again to download it anew"
    if published and got[published[0]] != published[1]:
        label = {"sha256": "SHA-256", "md5": "MD5"}[published[0]]
        problem = f"{label} {got[published[0]]} does not match the published {published[1]} (datasets.yaml)"
    elif (rec := store.get(name)) is not None and rec.get("sha256") != got["sha256"]:
        before = Entity(str(rec.get("url")), text_field(rec, "etag"), text_field(rec, "last_modified"),
                        count_field(rec, "bytes"))
        now = entity or Entity(url, total=size)
        changed = before.changes(Entity(now.url, now.etag, now.last_modified, size))
        if before.url != now.url:
            changed.append(f"URL {before.url} → {now.url}")
        head = (f"SHA-256 {got['sha256']} does not match {rec.get('sha256')} recorded in {store.path} at its first "
                f"download ({rec.get('recorded', 'date not recorded')})")
        if changed:
            problem = (f"{head}: the publisher's file changed ({'; '.join(changed)}); if the new version is wanted, "
                       f"delete the entry {name!r} in {store.path.name}")
            again = "then run the command again"
        else:
            same = "size and ETag" if now.etag and before.etag else "size"
            problem = f"{head}, with the same {same}: the bytes are corrupt (in transit or on disk)"
    if problem:
        path.unlink(missing_ok=True)
        path.with_name(name + ".partinfo").unlink(missing_ok=True)
        raise DatasetError(f"{name} from {url}: {problem}; removed the file, {again}")
    return got["sha256"]
