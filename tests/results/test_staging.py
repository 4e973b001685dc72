"""A run folder changes only when the run completes (staging folder + one rename), and what cannot be written is
one line naming the path (issue 48, kind 3): the parts on their own."""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
from pathlib import Path

import pytest

from mutualslam_cli.errors import OutputError
from mutualslam_cli.results import staging, writable
from mutualslam_cli.results.staging import staged


def digest(folder: Path) -> dict[str, str]:
    """Every file under ``folder`` (hidden ones too) → its SHA-256."""
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def old_run(tmp_path: Path) -> Path:
    folder = tmp_path / "seq" / "none" / "seed0"
    (folder / "depth").mkdir(parents=True)
    (folder / "config.yaml").write_text("old config\n")
    (folder / "summary.json").write_text("{}\n")
    (folder / "depth" / "a.npy").write_bytes(b"\x00" * 64)
    return folder


def test_a_completed_block_replaces_the_folder_whole(old_run: Path):
    with staged(old_run) as tmp:
        assert tmp.parent == old_run.parent
        assert tmp.name.startswith(".seed0.staging-")
        assert not any(tmp.iterdir())
        (tmp / "config.yaml").write_text("new config\n")
        assert (old_run / "config.yaml").read_text() == "old config\n"  # nothing changes before the end
    assert digest(old_run) == {"config.yaml": hashlib.sha256(b"new config\n").hexdigest()}
    assert sorted(p.name for p in old_run.parent.iterdir()) == ["seed0"]  # no staging or old folder left
    assert oct(old_run.stat().st_mode & 0o777) == oct(0o777 & ~staging._UMASK)


def test_a_failed_block_leaves_the_folder_byte_identical(old_run: Path):
    before = digest(old_run)
    with pytest.raises(RuntimeError, match="a stage failed"), staged(old_run) as tmp:  # noqa: PT012
        (tmp / "config.yaml").write_text("new config\n")
        (tmp / "summary.json").write_text('{"new": 1}\n')
        raise RuntimeError("a stage failed")
    assert digest(old_run) == before
    assert sorted(p.name for p in old_run.parent.iterdir()) == ["seed0"]


def test_a_first_run_makes_the_folder_only_when_it_completes(tmp_path: Path):
    folder = tmp_path / "seq" / "none" / "seed0"
    with pytest.raises(KeyboardInterrupt), staged(folder):
        raise KeyboardInterrupt
    assert not folder.exists()
    assert list(folder.parent.iterdir()) == []
    with staged(folder) as tmp:
        (tmp / "summary.json").write_text("{}\n")
        assert not folder.exists()
    assert digest(folder) == {"summary.json": hashlib.sha256(b"{}\n").hexdigest()}


def test_what_a_killed_process_left_is_removed_by_the_next_run(old_run: Path):
    dead = old_run.parent / ".seed0.staging-dead"
    (dead / "depth").mkdir(parents=True)
    (dead / "summary.json").write_text("{}\n")  # killed between its summary and the rename
    (old_run.parent / ".seed0.old-dead").mkdir()
    other = old_run.parent / ".seed1.staging-alive"  # another run folder's: not ours to remove
    other.mkdir()
    with staged(old_run):
        assert not dead.exists()
        assert not (old_run.parent / ".seed0.old-dead").exists()
        assert other.exists()
    assert digest(old_run) == {}
    assert other.exists()


def test_from_current_adds_to_the_run_and_a_failure_keeps_it(old_run: Path):
    before = digest(old_run)
    with pytest.raises(ValueError, match="a stage failed"), staged(old_run, from_current=True) as tmp:  # noqa: PT012
        assert digest(tmp) == before
        (tmp / "summary.json").write_text('{"dense": 1}\n')  # written in place: the original is a copy's source
        (tmp / "depth" / "a.npy").unlink()
        raise ValueError("a stage failed")
    assert digest(old_run) == before
    with staged(old_run, from_current=True) as tmp:
        (tmp / "mesh.ply").write_text("ply\n")
    assert set(digest(old_run)) == set(before) | {"mesh.ply"}


def test_without_an_atomic_exchange_two_renames_replace_the_folder(old_run: Path, monkeypatch):
    monkeypatch.setattr(staging, "_exchange", lambda a, b: False)
    with staged(old_run) as tmp:
        (tmp / "summary.json").write_text('{"new": 1}\n')
    assert (old_run / "summary.json").read_text() == '{"new": 1}\n'
    assert not (old_run / "config.yaml").exists()
    assert sorted(p.name for p in old_run.parent.iterdir()) == ["seed0"]


# ----------------------------------------------------------------------------- what cannot be written


def test_an_out_that_is_a_file_is_refused_and_kept(tmp_path: Path):
    f = tmp_path / "results"
    f.write_text("mine\n")
    with pytest.raises(OutputError, match=rf"^{f}: is a file, not a folder for the results; choose another --out"):
        writable.check_output_folder(f)
    with pytest.raises(OutputError, match=rf"^{f}: is a file, not a folder for the results; {f}/sub cannot be made"):
        writable.check_output_folder(f / "sub")
    assert f.read_text() == "mine\n"


def test_a_missing_out_is_checked_without_creating_it(tmp_path: Path):
    assert writable.check_output_folder(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    assert list(tmp_path.iterdir()) == []


def test_an_out_that_cannot_be_written_is_refused(tmp_path: Path, monkeypatch):
    ro = tmp_path / "ro"
    ro.mkdir()
    if os.geteuid() == 0:  # root writes through mode bits: the refusal the kernel gives is simulated
        def denied(*a, **k):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES))
        monkeypatch.setattr(writable.tempfile, "mkstemp", denied)
        monkeypatch.setattr(writable.os, "access", lambda *a, **k: False)
    else:
        ro.chmod(0o555)
    try:
        with pytest.raises(OutputError, match=rf"^{ro}: cannot write the results there: Permission denied; make it"):
            writable.check_output_folder(ro)
        with pytest.raises(OutputError, match=rf"^{ro}: cannot write the results there: Permission denied"):
            writable.check_output_folder(ro / "new")
    finally:
        ro.chmod(0o755)
    assert list(ro.iterdir()) == []


def test_write_errors_name_the_path_and_what_to_do(tmp_path: Path, monkeypatch):
    root = tmp_path / "res"
    with pytest.raises(OutputError) as e, writable.write_errors(root, "nothing of this run was kept"):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # a write(2) on a full disk: no file name
    assert str(e.value) == (f"{root}: cannot write: No space left on device; free space there (or choose another "
                            "--out) and run again; nothing of this run was kept")
    with pytest.raises(OutputError, match=r"seed0/x.csv: cannot write: Permission denied; make it writable"), \
            writable.write_errors(root):
        raise PermissionError(errno.EACCES, "Permission denied", str(root / "seq" / "seed0" / "x.csv"))
    # a file outside the results (a dataset): not a write error of ours
    with pytest.raises(PermissionError), writable.write_errors(root):
        raise PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "data" / "rgb.txt"))
    with pytest.raises(RuntimeError, match="a bug"), writable.write_errors(root):  # not a write error: disk has room
        raise RuntimeError("a bug")
    monkeypatch.setattr(shutil, "disk_usage", lambda p: shutil._ntuple_diskusage(10 << 20, 10 << 20, 4096))
    with pytest.raises(OutputError, match=r"cannot write: the disk is full: 307200 requested and 24544 written"), \
            writable.write_errors(root):
        raise OSError("307200 requested and 24544 written")  # numpy's short write: no errno, no path
