"""Every exception class of mslam, in one place.

Two families, told apart by what the CLI does with them:

- :class:`MslamError` and its subclasses: errors a user (or the data) can cause. The CLI turns
  one into one red line and exit code 1; :mod:`~mutualslam_cli.ablate` records it as a failed
  job.

  - :class:`DatasetError`: a sequence on disk is missing, malformed or inconsistent.
    :class:`CameraFileError` (inside a camera file) and :class:`ArchiveError` (:class:`CorruptArchive`,
    :class:`UnsafeMember`, :class:`ArchiveTooLarge`: a downloaded archive) are the datasets' own, caught
    where they are raised. :class:`UnsafeName` (a file name from a URL or a registry field that would
    not be one file in its folder) and :class:`DownloadLocked` (another process downloads the same file)
    reach the user as they are. :class:`DamagedRecord`: a record beside the downloads, or a results book's job
    record, of the wrong shape (or edited by hand).
  - :class:`ConfigError`: a setting (config file, ``--set``, a constructor argument that comes
    from one) is invalid.
  - :class:`GeometryError`: an alignment is degenerate (too few pairs, collinear positions).
  - :class:`KeyframeError`: the keyframe buffer cannot serve a keyframe id (unknown, evicted,
    or not increasing).
  - :class:`ResultsLocked`: another live process works in the same result folder
    (:func:`~mutualslam_cli.results.lock.hold_lock`).
  - :class:`OutputError`: a results or report folder cannot be written (read-only, the disk full, a file
    where a folder should be; :mod:`~mutualslam_cli.results.writable`).
  - :class:`SchemaError`: a ``summary.json`` is not of a schema version mslam reads, or holds a key or value
    its version does not (:mod:`~mutualslam_cli.results.schema`); a stage writing such a key raises it too.

- Programming errors, deliberately *not* ``MslamError`` so that they keep their traceback:

  - :class:`ShapeError` (a ``ValueError``): an array or tensor does not have the documented
    shape (:func:`~mutualslam_cli.types.check_shape`).
  - :class:`TransitionError` (a ``RuntimeError``): an event that Algorithm 1 does not allow in
    the current state (:mod:`~mutualslam_cli.adapt.state`).
  - :class:`CacheMismatch` (a ``RuntimeError``): a cached front-end journal disagrees with the front end
    run again from a checkpoint (:mod:`~mutualslam_cli.vo.source`): the code changed under the
    cache key, or the front end is not deterministic.
"""

from __future__ import annotations


class MslamError(Exception):
    """Base class of all errors caused by input or configuration."""


class DatasetError(MslamError):
    """A sequence on disk is missing, malformed or inconsistent.

    The message names the file, the line (when there is one) and the expected format.
    """


class CameraFileError(DatasetError):
    """What is wrong inside a camera file (:mod:`~mutualslam_cli.datasets.recordings.camera_file`); the reader turns it
    into one :class:`DatasetError` line naming the file and the formats it accepts."""


class ArchiveError(DatasetError):
    """A downloaded archive cannot be unpacked (:mod:`~mutualslam_cli.datasets.download.unpack`); the download removes
    what it unpacked and reports one line."""


class CorruptArchive(ArchiveError):
    """The archive is truncated or corrupt (its reader failed); the message is the reader's reason."""


class UnsafeMember(ArchiveError):
    """An archive member that is not a plain file or folder inside the target folder: an absolute path, ``..``,
    a path too deep or too long, a link or special file, an unsupported zip compression
    (:mod:`~mutualslam_cli.datasets.download.members`)."""


class ArchiveTooLarge(ArchiveError):
    """Unpacking the archive would pass a limit (:mod:`~mutualslam_cli.datasets.download.limits`): total bytes, free
    disk, member count or a member's compression ratio; the message names the limit and how to change it."""


class UnsafeName(DatasetError):
    """A name from outside (a URL's last segment, a registry field) is not a safe single file name
    (:mod:`~mutualslam_cli.datasets.download.safe_names`)."""


class DownloadLocked(DatasetError):
    """Another live process downloads or unpacks the same file (:mod:`~mutualslam_cli.datasets.download.lock`);
    the message names the file and the holder."""


class DamagedRecord(DatasetError):
    """A record mslam keeps beside its downloads (``checksums.json``, ``NAME.partinfo``, ``NAME.lock``) is not of
    the shape mslam writes, or is a symbolic link (:mod:`~mutualslam_cli.datasets.download.files`); or a results
    book's job record (:mod:`~mutualslam_cli.book.records`) is damaged or was not written by mslam (its digest does
    not match). The reader names the file and the field and either starts over or says how to fix it, and never
    trusts it."""


class NotRefreshable(MslamError):
    """The network's converted OpenVINO graph has weights that cannot be matched to its tensors one to one
    (:mod:`mutualslam_cli.adapt.ov_refresh`)."""


class ConfigError(MslamError):
    """A configuration file, ``--set`` override or setting-valued argument is invalid."""


class GeometryError(MslamError):
    """An alignment is degenerate (too few pairs, all positions identical or collinear)."""


class KeyframeError(MslamError):
    """The keyframe buffer cannot serve a keyframe id.

    Raised by :class:`~mutualslam_cli.adapt.buffer.KeyframeBuffer` for an id that is not stored
    (unknown or evicted) and for an id that does not increase.
    """


class ResultsLocked(MslamError):
    """A result folder (a run's, or a grid's results root) is locked by another live process.

    Raised by :func:`~mutualslam_cli.results.lock.hold_lock`; the one-line message names the folder, the
    holder (pid, host, since when, doing what) and what to do. A plain message-only class, so it
    crosses process pools intact.
    """


class OutputError(MslamError):
    """A results or report folder cannot be written: read-only, the disk full (or a quota reached), a file in
    the way of a folder. The one-line message names the path, the reason and what to do, and what became of
    the run (nothing of it kept; a previous run in the folder as it was)."""


class SchemaError(MslamError):
    """A ``summary.json`` (read, or being written) does not fit its schema version: an unknown version, a key
    the schema does not have, a value of the wrong kind (:mod:`~mutualslam_cli.results.schema`). The message
    names the file (or the writer), the key and the version."""


class ShapeError(ValueError):
    """An array or tensor does not have the documented shape.

    A programming error, not an :class:`MslamError`: the CLI lets it through with its traceback.
    """


class TransitionError(RuntimeError):
    """An event that Algorithm 1 does not allow in the current state (a caller bug)."""


class CacheMismatch(RuntimeError):
    """The cached journal disagrees with the front end run again from a resumption point."""
