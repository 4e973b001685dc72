"""``mslam datasets download``: fetch the public archive of a ``datasets.yaml`` entry, verify it, unpack it.

An entry that can be downloaded has a ``download:`` block (see the header of ``datasets.yaml``)::

    download:
      archive: URL            # .tgz / .tar.gz / .zip: the sequence's archive
      gt: URL                 # optional: a trajectory file published beside it (ICL-NUIM *.gt.freiburg),
                              # saved in the sequence folder under the entry's `gt:` name
      layout: 7scenes         # optional: a 7-Scenes scene zip, of which `sequence:` (e.g. seq-01) is
      sequence: seq-01        #   converted to the TUM layout (unpack.convert_7scenes)
      checksums: {FILE: "sha256:HEX" | "md5:HEX"}   # optional, published checksums by file name

Files go to ``<data root>/_downloads/`` as ``FILE.part`` while they arrive; an existing ``.part`` is
resumed with an HTTP ``Range`` request (a server that answers 200 instead of 206 restarts it). A
complete file is checked against its size, a published checksum when the block gives one, and
otherwise against the SHA-256 recorded in ``_downloads/checksums.json`` at its first complete
download (recorded once its archive has unpacked); a mismatching file is removed. The archive is
unpacked into a temporary folder beside the sequence folder (same file system) and renamed into
place only when complete, so the sequence folder either does not exist or is whole. Sizes in
messages are in MB (10⁶ bytes); timeouts in seconds.
"""

from __future__ import annotations

import errno
import hashlib
import http.client
import json
import os
import re
import urllib.error
import urllib.parse
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, Callable

from mutualslam_cli.atomic import atomic_write_text
from mutualslam_cli.datasets.registry import DEFAULT_REGISTRY, list_datasets
from mutualslam_cli.datasets.unpack import install_archive, is_complete
from mutualslam_cli.errors import CorruptArchive, DatasetError
from mutualslam_cli.types import SequenceSpec

DOWNLOAD_DIR = "_downloads"
"""Folder in the data root that holds the downloaded files and ``checksums.json``."""
CHECKSUMS_FILE = "checksums.json"
BASE_URL_ENV = "MSLAM_DOWNLOAD_BASE_URL"
"""Environment variable that replaces everything before the file name of each URL (a mirror)."""
TIMEOUT_S = 60.0
"""Seconds to wait for a connection or for the next bytes of a response."""

#: ``progress(stage, info)``: stage ``"download"`` with ``done``/``total`` bytes (``total`` None when the
#: server does not say), ``file`` and ``url``; stage ``"unpack"`` with ``done``/``total`` bytes of the archive
#: and ``file``.
DownloadProgress = Callable[[str, dict[str, Any]], None]

_CHUNK = 1 << 20
_CONTENT_RANGE = re.compile(r"bytes\s+(\d+)-(\d+)/(\d+|\*)")
_RANGE_TOTAL = re.compile(r"bytes\s+\*/(\d+)")
_ALGOS = ("sha256", "md5")


@dataclass(frozen=True)
class DownloadBlock:
    """The validated ``download:`` block of a registry entry."""

    archive: str
    gt: str | None = None
    layout: str = "archive"  # "archive" (tar/zip of the sequence) or "7scenes"
    sequence: str | None = None
    checksums: dict[str, tuple[str, str]] = field(default_factory=dict)  # file name → (algorithm, hex)

    @property
    def urls(self) -> list[str]:
        """The archive URL, then the GT file's, if any."""
        return [self.archive] + ([self.gt] if self.gt else [])


@dataclass
class FetchedFile:
    """One downloaded (or reused) file. ``size`` in bytes; ``resumed_from``: bytes already there (0 = fresh)."""

    path: Path
    url: str
    size: int
    sha256: str
    resumed_from: int = 0
    reused: bool = False
    recorded: bool = False  # its SHA-256 was recorded now (first complete download that unpacked)


@dataclass
class DownloadResult:
    """What :func:`download_sequence` did for one entry."""

    name: str
    root: Path
    skipped: bool
    files: list[FetchedFile] = field(default_factory=list)


def _mb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e6:.{1 if n >= 1e6 else 3}f}"


def download_block(spec: SequenceSpec) -> DownloadBlock | None:
    """The entry's ``download:`` block, validated, or ``None`` when it has none."""
    raw = spec.extra.get("download")
    if raw is None:
        return None
    where = f"datasets.yaml entry '{spec.name}': download"
    if not isinstance(raw, dict) or not isinstance(raw.get("archive"), str):
        raise DatasetError(f"{where}: expected a mapping with 'archive: URL' (+ optional gt, layout, sequence, "
                           f"checksums), got {raw!r}")
    layout = str(raw.get("layout", "archive"))
    if layout not in ("archive", "7scenes"):
        raise DatasetError(f"{where}: layout '{layout}' unknown; expected archive or 7scenes")
    if layout == "7scenes" and not raw.get("sequence"):
        raise DatasetError(f"{where}: layout 7scenes needs 'sequence: seq-NN'")
    checksums: dict[str, tuple[str, str]] = {}
    for fname, value in (raw.get("checksums") or {}).items():
        algo, _, hexd = str(value).partition(":")
        if algo.lower() not in _ALGOS or not re.fullmatch(r"[0-9a-fA-F]+", hexd):
            raise DatasetError(f"{where}: checksum of {fname} must be 'sha256:HEX' or 'md5:HEX', got {value!r}")
        checksums[str(fname)] = (algo.lower(), hexd.lower())
    gt = raw.get("gt")
    return DownloadBlock(raw["archive"], str(gt) if gt else None, layout,
                         str(raw["sequence"]) if raw.get("sequence") else None, checksums)


def data_root_of(registry_path: str | os.PathLike | None = None, data_root: str | os.PathLike | None = None) -> Path:
    """The data root relative registry roots resolve against (``data_root``, ``$MSLAM_DATA``, the yaml's folder)."""
    registry = Path(registry_path) if registry_path is not None else DEFAULT_REGISTRY
    base = data_root if data_root is not None else os.environ.get("MSLAM_DATA") or registry.parent
    return Path(base).expanduser().resolve()


def downloadable_specs(names: list[str], registry_path: str | os.PathLike | None = None,
                       data_root: str | os.PathLike | None = None) -> list[SequenceSpec]:
    """The specs of ``names``; an unknown name or one without a ``download:`` block lists the downloadable ones."""
    specs = {s.name: s for s in list_datasets(registry_path, data_root)}
    ok = [n for n, s in specs.items() if download_block(s) is not None]
    bad = [n for n in names if n not in ok]
    if bad or not names:
        registry = Path(registry_path) if registry_path is not None else DEFAULT_REGISTRY
        what = (f"cannot download {', '.join(bad)}: not in {registry} or no 'download:' block there" if bad
                else "name the sequences to download")
        raise DatasetError(f"{what}; downloadable: {', '.join(ok) or 'none'}")
    return [specs[n] for n in names]


def file_url(url: str, base_url: str | None = None) -> str:
    """``url``, or ``base_url/<its file name>`` when a mirror is given."""
    return url if not base_url else base_url.rstrip("/") + "/" + url_file_name(url)


def url_file_name(url: str) -> str:
    """The file name at the end of ``url``'s path."""
    name = urllib.parse.unquote(PurePosixPath(urllib.parse.urlsplit(url).path).name)
    if not name or name in (".", ".."):
        raise DatasetError(f"{url}: expected a URL ending in a file name")
    return name


# ----------------------------------------------------------------------------- checksums


class ChecksumStore:
    """``checksums.json``: file name → ``{"sha256", "bytes", "url"}`` of its first complete download."""

    def __init__(self, path: Path):
        self.path = path
        self.data: dict[str, dict[str, Any]] = {}
        if path.is_file():
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
                if not isinstance(data, dict):
                    raise ValueError
            except ValueError:
                raise DatasetError(f"{path}: invalid JSON; expected file name → {{sha256, bytes, url}} "
                                   "(delete it to record the checksums anew)") from None
            self.data = data

    def get(self, name: str) -> dict[str, Any] | None:
        """The record of file ``name``, if any."""
        return self.data.get(name)

    def put(self, name: str, record: dict[str, Any]) -> None:
        """Record file ``name`` and save the file atomically."""
        self.data[name] = record
        self._save()

    def drop(self, name: str) -> None:
        """Forget file ``name`` (saved at once)."""
        if self.data.pop(name, None) is not None:
            self._save()

    def _save(self) -> None:
        atomic_write_text(self.path, json.dumps(self.data, indent=2, sort_keys=True) + "\n")


def _digests(path: Path, algos: set[str]) -> dict[str, str]:
    hs = {a: hashlib.new(a) for a in algos}
    with open(path, "rb") as f:
        while buf := f.read(_CHUNK):
            for h in hs.values():
                h.update(buf)
    return {a: h.hexdigest() for a, h in hs.items()}


def _verify(path: Path, name: str, url: str, block: DownloadBlock, store: ChecksumStore) -> str:
    """SHA-256 of ``path`` after checking it against the published or the recorded checksum (a mismatch
    removes the file and raises :class:`DatasetError`)."""
    published = block.checksums.get(name)
    got = _digests(path, {"sha256"} | ({published[0]} if published else set()))
    problem = None
    if published and got[published[0]] != published[1]:
        label = {"sha256": "SHA-256", "md5": "MD5"}[published[0]]
        problem = f"{label} {got[published[0]]} does not match the published {published[1]} (datasets.yaml)"
    elif (rec := store.get(name)) is not None and rec.get("sha256") != got["sha256"]:
        problem = (f"SHA-256 {got['sha256']} does not match {rec.get('sha256')} recorded in {store.path} at its "
                   "first download (delete that entry if the publisher changed the file)")
    if problem:
        path.unlink(missing_ok=True)
        raise DatasetError(f"{name} from {url}: {problem}; removed the file, run the command again to download "
                           "it anew")
    return got["sha256"]


# ----------------------------------------------------------------------------- HTTP


def _open(url: str, start: int, timeout: float) -> Any:
    """The response to GET ``url`` (``Range: bytes=start-`` when ``start``); a 416 answer is returned, not raised."""
    headers = {"User-Agent": "mslam-datasets-download"}
    if start:
        headers["Range"] = f"bytes={start}-"
    try:
        return urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code == 416 and start:
            return e
        raise DatasetError(f"{url}: HTTP {e.code} {e.reason}; expected the file (check the URL in datasets.yaml "
                           "or --base-url)") from None
    except (urllib.error.URLError, OSError, http.client.HTTPException) as e:
        raise DatasetError(f"{url}: cannot connect ({getattr(e, 'reason', e)}); check the network, the URL or "
                           "--base-url") from None
    except ValueError:
        raise DatasetError(f"{url}: expected an http:// or https:// URL") from None


def _start(url: str, part: Path, timeout: float) -> tuple[Any, int, int | None]:
    """Open ``url`` for the rest of ``part``: ``(response or None, start byte, total bytes or None)``.

    ``None`` as the response: ``part`` is already complete (the server answered 416 with its size)."""
    have = part.stat().st_size if part.is_file() else 0
    resp = _open(url, have, timeout)
    if have and resp.getcode() == 416:
        m = _RANGE_TOTAL.match(resp.headers.get("Content-Range", ""))
        resp.close()
        if m and int(m.group(1)) == have:
            return None, have, have
        resp, have = _open(url, 0, timeout), 0
    if have and resp.getcode() == 206:
        m = _CONTENT_RANGE.match(resp.headers.get("Content-Range", ""))
        if m and int(m.group(1)) == have:
            return resp, have, None if m.group(3) == "*" else int(m.group(3))
        resp.close()
        resp = _open(url, 0, timeout)
    length = resp.headers.get("Content-Length")
    return resp, 0, int(length) if length and length.isdigit() else None


def fetch(url: str, dest: Path, progress: DownloadProgress | None = None,
          timeout: float = TIMEOUT_S) -> tuple[int, int]:
    """Download ``url`` into ``dest`` + ``.part``, resuming an existing ``.part``; returns ``(bytes, resumed_from)``.

    The ``.part`` file is left in place on any failure, and is complete (not renamed) on success.

    Raises:
        DatasetError: HTTP error, no connection, an interrupted transfer (``.part`` kept for resuming),
            more bytes than announced, or a full disk.
    """
    part = dest.with_name(dest.name + ".part")
    resp, start, total = _start(url, part, timeout)
    if resp is None:
        return start, start
    done = start
    with resp, open(part, "ab" if start else "wb") as f:
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
        raise DatasetError(f"{url}: the server sent {done} bytes, it announced {total}; removed {part.name}, run "
                           "the command again")
    if (total is not None and done < total) or buf is None:
        raise DatasetError(f"download of {url} interrupted at {_mb(done)} of {_mb(total)} MB; run the command "
                           "again to resume")
    return done, start


def get_file(url: str, folder: Path, block: DownloadBlock, store: ChecksumStore,
             progress: DownloadProgress | None = None, timeout: float = TIMEOUT_S) -> FetchedFile:
    """``folder/<file name of url>``: reused when complete there, else downloaded; verified either way
    (its SHA-256 is recorded by :func:`download_sequence` once the archive has unpacked)."""
    name = url_file_name(url)
    dest = folder / name
    if dest.is_file():
        sha = _verify(dest, name, url, block, store)
        got = FetchedFile(dest, url, dest.stat().st_size, sha, reused=True)
    else:
        size, start = fetch(url, dest, progress, timeout)
        part = dest.with_name(name + ".part")
        sha = _verify(part, name, url, block, store)
        os.replace(part, dest)
        got = FetchedFile(dest, url, size, sha, resumed_from=start)
    return got


# ----------------------------------------------------------------------------- the whole entry


def download_sequence(spec: SequenceSpec, download_dir: Path, base_url: str | None = None, force: bool = False,
                      progress: DownloadProgress | None = None, on_message: Callable[[str], None] | None = None,
                      timeout: float = TIMEOUT_S) -> DownloadResult:
    """Download, verify and unpack the registry entry ``spec`` into ``spec.root`` (see the module docstring).

    Args:
        spec: a registry entry with a ``download:`` block.
        download_dir: where the files go (``<data root>/_downloads``), with ``checksums.json``.
        base_url: a mirror replacing everything before each file name (default ``$MSLAM_DOWNLOAD_BASE_URL``).
        force: unpack again and replace an existing sequence folder (the downloaded files are reused).
        progress: see :data:`DownloadProgress`.
        on_message: one-line notes (skipped, reused, resumed, checksum recorded).
        timeout: seconds for a connection or the next bytes.

    Raises:
        DatasetError: every failure, as one line naming the URL or file and what was expected.
    """
    say = on_message or (lambda _msg: None)
    block = download_block(spec)
    if block is None:
        raise DatasetError(f"datasets.yaml entry '{spec.name}' has no 'download:' block")
    root = Path(spec.root)
    if is_complete(root) and not force:
        say(f"{spec.name}: {root} already exists; download skipped (--force unpacks it again)")
        return DownloadResult(spec.name, root, skipped=True)
    base = base_url if base_url is not None else os.environ.get(BASE_URL_ENV) or None
    download_dir.mkdir(parents=True, exist_ok=True)
    store = ChecksumStore(download_dir / CHECKSUMS_FILE)
    files = []
    for url in block.urls:
        got = get_file(file_url(url, base), download_dir, block, store, progress, timeout)
        if got.reused:
            say(f"{got.path.name}: using the file downloaded before ({_mb(got.size)} MB)")
        elif got.resumed_from:
            say(f"{got.path.name}: resumed at {_mb(got.resumed_from)} MB")
        files.append(got)
    archive = files[0].path
    extra = {spec.gt_file or f.path.name: f.path for f in files[1:]}

    def cb(done: int, total: int) -> None:
        if progress:
            progress("unpack", {"done": done, "total": total, "file": archive.name})

    try:
        install_archive(archive, root, layout=block.layout, sequence=block.sequence, extra=extra, force=force,
                        progress=cb)
    except CorruptArchive as e:
        archive.unlink(missing_ok=True)
        store.drop(archive.name)
        raise DatasetError(f"{archive}: truncated or corrupt archive ({e}); removed it and the temporary folder, "
                           "run the command again to download it anew") from None
    for got in files:  # recorded once the archive has proved whole, so a bad first download is never the reference
        if store.get(got.path.name) is None:
            store.put(got.path.name, {"sha256": got.sha256, "bytes": got.size, "url": got.url})
            got.recorded = True
            say(f"{got.path.name}: SHA-256 {got.sha256} recorded in {store.path}")
    say(f"{spec.name}: unpacked {files[0].path.name} into {root}")
    return DownloadResult(spec.name, root, skipped=False, files=files)
