"""``mslam datasets download``: fetch the public archive of a ``datasets.yaml`` entry, verify it, unpack it.

An entry that can be downloaded has a ``download:`` block (see the header of ``datasets.yaml``)::

    download:
      archive: URL            # .tgz / .tar.gz / .zip: the sequence's archive
      gt: URL                 # optional: a trajectory file published beside it (ICL-NUIM *.gt.freiburg),
                              # saved in the sequence folder under the entry's `gt:` name
      layout: 7scenes         # optional: a 7-Scenes scene zip, of which `sequence:` (e.g. seq-01) is
      sequence: seq-01        #   converted to the TUM layout (seven_scenes.convert_7scenes)
      checksums: {FILE: "sha256:HEX" | "md5:HEX"}   # optional, published checksums by file name

What comes from outside is checked before it touches the disk, in this order:

- **where**: the entry's ``root``, resolved (``..`` and symbolic links), must lie inside the data root
  (and not in ``_downloads/``); a root elsewhere can still be read, but not downloaded into. ``force``
  replaces only a folder that mslam unpacked (it holds :data:`~mutualslam_cli.datasets.download.unpack.MARKER`),
  never a folder of the user's;
- **names**: each URL's file name, the entry's ``gt:`` and ``sequence:`` must be safe single file
  names (:mod:`~mutualslam_cli.datasets.download.safe_names`), so nothing lands outside ``<data root>/_downloads/``
  or the sequence folder;
- **one process per file**: the files of the entry are locked (:mod:`~mutualslam_cli.datasets.download.lock`);
  a second command on the same file stops at once, naming the holder;
- **the bytes**: files arrive as ``FILE.part``; a ``.part`` is resumed only when it is the same version
  of the file (``If-Range`` with the recorded ETag / Last-Modified, :mod:`~mutualslam_cli.datasets.download.fetch`).
  A complete file is checked against its size, a published checksum when the block gives one, and
  otherwise against what ``_downloads/checksums.json`` recorded at its first complete download
  (:mod:`~mutualslam_cli.datasets.download.checksums`: SHA-256, size, URL, ETag; recorded once its archive has
  unpacked); a mismatching file is removed, and the message says whether the publisher changed it;
- **the archive**: unpacked within limits (:mod:`~mutualslam_cli.datasets.download.limits`) into a temporary
  folder beside the sequence folder, checked there with the sequence check
  (:func:`~mutualslam_cli.datasets.check.check_sequence`), and renamed into place only when it passes
  (:mod:`~mutualslam_cli.datasets.download.unpack`), so the sequence folder either does not exist or is whole and
  checked; ``force`` keeps the old folder (and the old checksum record) until the new one takes its
  place. Only then is the archive's SHA-256 recorded.

Sizes in messages are in MB (10⁶ bytes); timeouts in seconds.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from mutualslam_cli.datasets.check import CheckProgress, CheckReport, check_sequence
from mutualslam_cli.datasets.download.checksums import ALGORITHMS, CHECKSUMS_FILE, ChecksumStore, verify
from mutualslam_cli.datasets.download.fetch import TIMEOUT_S, DownloadProgress, Entity, fetch
from mutualslam_cli.datasets.download.limits import UnpackLimits
from mutualslam_cli.datasets.download.lock import download_lock
from mutualslam_cli.datasets.download.safe_names import check_name, path_inside, url_file_name
from mutualslam_cli.datasets.download.unpack import (
    install_archive,
    is_complete,
    is_unpacked_by_mslam,
    not_unpacked_by_mslam,
    recover_leftovers,
)
from mutualslam_cli.datasets.registry import DEFAULT_REGISTRY, list_datasets
from mutualslam_cli.errors import CorruptArchive, DatasetError
from mutualslam_cli.types import SequenceSpec

__all__ = [
    "BASE_URL_ENV",
    "CHECKSUMS_FILE",
    "DOWNLOAD_DIR",
    "TIMEOUT_S",
    "DownloadBlock",
    "DownloadProgress",
    "DownloadResult",
    "FetchedFile",
    "data_root_of",
    "download_block",
    "download_sequence",
    "downloadable_specs",
    "file_url",
    "get_file",
    "url_file_name",
]

DOWNLOAD_DIR = "_downloads"
"""Folder in the data root that holds the downloaded files and ``checksums.json``."""
BASE_URL_ENV = "MSLAM_DOWNLOAD_BASE_URL"
"""Environment variable that replaces everything before the file name of each URL (a mirror)."""


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
    entity: Entity | None = None  # what the server said of it (None: reused)
    note: str | None = None  # a discarded .part, and why


@dataclass
class DownloadResult:
    """What :func:`download_sequence` did for one entry."""

    name: str
    root: Path
    skipped: bool
    files: list[FetchedFile] = field(default_factory=list)
    report: CheckReport | None = None  # the sequence check of the new folder (None: skipped)


def _mb(n: int | None) -> str:
    return "?" if n is None else f"{n / 1e6:.{1 if n >= 1e6 else 3}f}"


def download_block(spec: SequenceSpec) -> DownloadBlock | None:
    """The entry's ``download:`` block, validated (URL file names, ``gt:`` and ``sequence:`` are safe file
    names), or ``None`` when it has none.

    Raises:
        DatasetError: a malformed block; :class:`~mutualslam_cli.errors.UnsafeName` for an unsafe name.
    """
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
        if algo.lower() not in ALGORITHMS or not re.fullmatch(r"[0-9a-fA-F]+", hexd):
            raise DatasetError(f"{where}: checksum of {fname} must be 'sha256:HEX' or 'md5:HEX', got {value!r}")
        checksums[str(fname)] = (algo.lower(), hexd.lower())
    gt = str(raw["gt"]) if raw.get("gt") else None
    block = DownloadBlock(raw["archive"], gt, layout, str(raw["sequence"]) if raw.get("sequence") else None,
                          checksums)
    for url in block.urls:
        url_file_name(url)
    if block.sequence is not None:
        check_name(block.sequence, f"{where}: sequence")
    if gt is not None and spec.gt_file:
        check_name(spec.gt_file, f"datasets.yaml entry '{spec.name}': gt")
    return block


def data_root_of(registry_path: str | os.PathLike | None = None, data_root: str | os.PathLike | None = None) -> Path:
    """The data root relative registry roots resolve against (``data_root``, ``$MSLAM_DATA``, the yaml's folder)."""
    registry = Path(registry_path) if registry_path is not None else DEFAULT_REGISTRY
    base = data_root if data_root is not None else os.environ.get("MSLAM_DATA") or registry.parent
    return Path(base).expanduser().resolve()


def downloadable_specs(names: list[str], registry_path: str | os.PathLike | None = None,
                       data_root: str | os.PathLike | None = None) -> list[SequenceSpec]:
    """The specs of ``names``; an unknown name or one without a ``download:`` block lists the downloadable ones."""
    specs = {s.name: s for s in list_datasets(registry_path, data_root)}
    ok = [n for n, s in specs.items() if s.extra.get("download") is not None]
    bad = [n for n in names if n not in ok]
    if bad or not names:
        registry = Path(registry_path) if registry_path is not None else DEFAULT_REGISTRY
        what = (f"cannot download {', '.join(bad)}: not in {registry} or no 'download:' block there" if bad
                else "name the sequences to download")
        raise DatasetError(f"{what}; downloadable: {', '.join(ok) or 'none'}")
    for n in names:
        download_block(specs[n])  # every entry's names checked before anything is fetched
    return [specs[n] for n in names]


def root_inside(spec: SequenceSpec, data_root: Path) -> Path:
    """The entry's sequence folder, resolved (``..``, symbolic links), checked to lie inside ``data_root`` and
    outside its ``_downloads`` folder: the only place a download may write.

    Raises:
        DatasetError: one line naming the entry's ``root`` field, where it resolves and the data root.
    """
    base = Path(os.path.realpath(data_root))
    root = Path(os.path.realpath(spec.root))
    if root == base or not root.is_relative_to(base) or root.is_relative_to(base / DOWNLOAD_DIR):
        via = f" (through {spec.root})" if Path(spec.root) != root else ""
        where = "is the data root itself" if root == base else (
            f"resolves to {root}{via}, inside {base / DOWNLOAD_DIR}" if root.is_relative_to(base) else
            f"resolves to {root}{via}, outside the data root {base}")
        raise DatasetError(f"datasets.yaml entry '{spec.name}': root {where}; a download writes only into a folder "
                           f"inside the data root {base} (give a root relative to it, or another --data-root); "
                           "nothing was touched")
    return root


def file_url(url: str, base_url: str | None = None) -> str:
    """``url``, or ``base_url/<its file name>`` when a mirror is given."""
    return url if not base_url else base_url.rstrip("/") + "/" + url_file_name(url)


def get_file(url: str, folder: Path, block: DownloadBlock, store: ChecksumStore,
             progress: DownloadProgress | None = None, timeout: float = TIMEOUT_S) -> FetchedFile:
    """``folder/<file name of url>``: reused when complete there, else downloaded; verified either way
    (its SHA-256 is recorded by :func:`download_sequence` once the archive has unpacked)."""
    name = url_file_name(url)
    dest = path_inside(folder, name, url)
    published = block.checksums.get(name)
    if dest.is_file():
        sha = verify(dest, name, url, None, published, store)
        return FetchedFile(dest, url, dest.stat().st_size, sha, reused=True)
    got = fetch(url, dest, progress, timeout)
    part = dest.with_name(name + ".part")
    sha = verify(part, name, url, got.entity, published, store)
    os.replace(part, dest)
    dest.with_name(name + ".partinfo").unlink(missing_ok=True)
    return FetchedFile(dest, url, got.size, sha, resumed_from=got.resumed_from, entity=got.entity, note=got.note)


# ----------------------------------------------------------------------------- the whole entry


def download_sequence(spec: SequenceSpec, download_dir: Path, base_url: str | None = None, force: bool = False,
                      progress: DownloadProgress | None = None, on_message: Callable[[str], None] | None = None,
                      timeout: float = TIMEOUT_S, limits: UnpackLimits | None = None, sample: int = 0,
                      check_progress: CheckProgress | None = None) -> DownloadResult:
    """Download, verify, unpack and check the registry entry ``spec`` into ``spec.root`` (see the module
    docstring).

    Args:
        spec: a registry entry with a ``download:`` block.
        download_dir: where the files go (``<data root>/_downloads``), with ``checksums.json``; its parent is
            the data root, inside which ``spec.root`` must lie.
        base_url: a mirror replacing everything before each file name (default ``$MSLAM_DOWNLOAD_BASE_URL``).
        force: unpack again and replace an existing sequence folder (the downloaded files are reused).
        progress: see :data:`~mutualslam_cli.datasets.download.fetch.DownloadProgress`.
        on_message: one-line notes (skipped, reused, resumed, restarted, checksum recorded).
        timeout: seconds for a connection or the next bytes.
        limits: unpacking limits (default :class:`~mutualslam_cli.datasets.download.limits.UnpackLimits`).
        sample: the sequence check of the unpacked folder decodes the images of this many frames (0: all).
        check_progress: see :data:`~mutualslam_cli.datasets.check.CheckProgress`.

    Raises:
        DatasetError: every failure, as one line naming the URL or file and what was expected.
    """
    say = on_message or (lambda _msg: None)
    block = download_block(spec)
    if block is None:
        raise DatasetError(f"datasets.yaml entry '{spec.name}' has no 'download:' block")
    root = root_inside(spec, download_dir.parent)
    spec = dataclasses.replace(spec, root=root)
    base = base_url if base_url is not None else os.environ.get(BASE_URL_ENV) or None
    urls = [file_url(url, base) for url in block.urls]
    download_dir.mkdir(parents=True, exist_ok=True)
    with download_lock(download_dir, [url_file_name(u) for u in urls]):
        for note in recover_leftovers(root):
            say(note)
        if is_complete(root) and not force:
            say(f"{spec.name}: {root} already exists; download skipped (--force unpacks it again)")
            return DownloadResult(spec.name, root, skipped=True)
        if force and root.exists() and (is_complete(root) or not root.is_dir()) and not is_unpacked_by_mslam(root):
            raise not_unpacked_by_mslam(root)
        checked: list[CheckReport] = []

        def check(folder: Path) -> None:
            report = check_sequence(dataclasses.replace(spec, root=folder), sample=sample, progress=check_progress)
            checked.append(dataclasses.replace(report, root=str(root),
                                               warnings=[w.replace(str(folder), str(root)) for w in report.warnings]))

        result = _fetch_and_install(spec, block, root, urls, download_dir, force, progress, say, timeout, limits,
                                    check)
        result.report = checked[0] if checked else None
        return result


def _fetch_and_install(spec: SequenceSpec, block: DownloadBlock, root: Path, urls: list[str], download_dir: Path,
                       force: bool, progress: DownloadProgress | None, say: Callable[[str], None], timeout: float,
                       limits: UnpackLimits | None, check: Callable[[Path], None]) -> DownloadResult:
    store = ChecksumStore(download_dir / CHECKSUMS_FILE)
    files = []
    for url in urls:
        got = get_file(url, download_dir, block, store, progress, timeout)
        if got.note:
            say(got.note)
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
                        progress=cb, limits=limits, check=check)
    except CorruptArchive as e:
        archive.unlink(missing_ok=True)
        store.drop(archive.name)
        raise DatasetError(f"{archive}: truncated or corrupt archive ({e}); removed it and the temporary folder, "
                           "run the command again to download it anew") from None
    for got in files:  # recorded once the archive has proved whole, so a bad first download is never the reference
        if store.get(got.path.name) is None:
            store.put(got.path.name, got.sha256, got.size, got.entity or Entity(got.url, total=got.size))
            got.recorded = True
            say(f"{got.path.name}: SHA-256 {got.sha256} recorded in {store.path} (first download: trusted on "
                "first use, later downloads are compared with it)")
    say(f"{spec.name}: unpacked {files[0].path.name} into {root}")
    return DownloadResult(spec.name, root, skipped=False, files=files)
