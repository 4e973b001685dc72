"""Crafted archives through ``mslam datasets download``: zip and tar bombs, a pax-header bomb, links, special
files, deep paths, too many members, a full disk, and a ``--force`` that fails or was killed half way.

Each checks the exit code, the one error line, that no sequence folder (or the old one, intact) and no
hidden temporary folder is left, and that nothing was written outside the data root.
"""

from __future__ import annotations

import io
import os
import tarfile
import zipfile
from pathlib import Path

import pytest
from dl_server import (
    TGZ,
    TUM_ROOT,
    download,
    downloads,
    leftovers,
    one_line_error,
    registry,
    serve_tum,
    tree,
    tum_members,
)

ZEROS = 20_000_000  # bytes of a bomb's member: deflate makes ~20 kB of them


def _tar(members: list[tarfile.TarInfo | tuple[str, bytes]], pax: dict[str, str] | None = None) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", format=tarfile.PAX_FORMAT, pax_headers=pax or {}) as tf:
        for m in members:
            if isinstance(m, tarfile.TarInfo):
                tf.addfile(m)
            else:
                info = tarfile.TarInfo(m[0])
                info.size = len(m[1])
                tf.addfile(info, io.BytesIO(m[1]))
    return buf.getvalue()


def _link(name: str, target: str, kind: bytes) -> tarfile.TarInfo:
    info = tarfile.TarInfo(name)
    info.type, info.linkname = kind, target
    return info


def _serve(server, tum_src, tmp_path, data: bytes, name: str = TGZ):
    server.files[name] = data
    return registry(tmp_path, server, tum_src, fr3_test={"archive": server.url(name)})


def _nothing_unpacked(tmp_path: Path, data: Path) -> None:
    assert not (data / TUM_ROOT).exists()
    assert leftovers(data / "TUM") == []
    outside = [p for p in tmp_path.rglob("*") if not p.is_relative_to(tmp_path / "data") and p.name != "datasets.yaml"]
    assert outside == []
    assert not Path("/tmp/mslam_evil").exists()


# ----------------------------------------------------------------------------- bombs


def test_zip_bomb_refused_before_writing(tmp_path, server, tum_src):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as z:
        for n, b in tum_members(tum_src):
            z.writestr(n, b)
        z.writestr("rgbd_dataset_freiburg3_test/bomb.bin", bytes(ZEROS))
    reg, data = _serve(server, tum_src, tmp_path, buf.getvalue(), "bomb.zip")
    r = download(reg, data, "fr3_test")
    one_line_error(r, "refused to unpack", "bomb.zip", "past", "10× the archive's", "--max-unpack-gb",
                   "removed the temporary folder")
    _nothing_unpacked(tmp_path, data)
    assert downloads(data) == ["bomb.zip"]  # kept: a larger --max-unpack-gb may be meant
    r = download(reg, data, "fr3_test", extra=("--max-unpack-gb", "5"))  # the limit raised: the ratio stops it
    one_line_error(r, "member 'rgbd_dataset_freiburg3_test/bomb.bin' expands", "limit is 100×", "zip bomb")
    _nothing_unpacked(tmp_path, data)


@pytest.mark.parametrize(("max_gb", "needles"), [(None, ("past", "10× the archive's")),
                                             ("5", ("expands", "limit is 100×"))])
def test_tar_bomb_refused(tmp_path, server, tum_src, max_gb, needles):
    reg, data = _serve(server, tum_src, tmp_path, _tar(tum_members(tum_src)
                                                       + [("rgbd_dataset_freiburg3_test/bomb.bin", bytes(ZEROS))]))
    r = download(reg, data, "fr3_test", extra=("--max-unpack-gb", max_gb) if max_gb else ())
    one_line_error(r, "refused to unpack", TGZ, "bomb.bin", *needles)
    _nothing_unpacked(tmp_path, data)


def test_pax_header_bomb_refused(tmp_path, server, tum_src):
    reg, data = _serve(server, tum_src, tmp_path, _tar(tum_members(tum_src), pax={"comment": "x" * ZEROS}))
    one_line_error(download(reg, data, "fr3_test"), "refused to unpack", "tar header asks for")
    _nothing_unpacked(tmp_path, data)


def test_total_limit_and_free_disk(tmp_path, server, tum_src, monkeypatch):
    from mutualslam_cli.datasets.download import limits

    reg, data = registry(tmp_path, server, tum_src)
    serve_tum(server, tum_src)
    one_line_error(download(reg, data, "fr3_test", extra=("--max-unpack-gb", "0.00002")),  # 20 kB
                   "refused to unpack", "past 2e-05 GB (the --max-unpack-gb limit)")
    _nothing_unpacked(tmp_path, data)
    monkeypatch.setattr(limits, "disk_free", lambda folder: limits.MIN_FREE_BYTES + 10_000)
    one_line_error(download(reg, data, "fr3_test"), "refused to unpack", "free on the disk of", "free some space")
    _nothing_unpacked(tmp_path, data)
    monkeypatch.undo()
    assert download(reg, data, "fr3_test").exit_code == 0


def test_too_many_members(tmp_path, server, tum_src, monkeypatch):
    from mutualslam_cli.datasets.download import limits

    monkeypatch.setattr(limits, "MAX_MEMBERS", 40)
    extra = [(f"rgbd_dataset_freiburg3_test/empty/{k}.txt", b"") for k in range(40)]
    reg, data = _serve(server, tum_src, tmp_path, _tar(tum_members(tum_src) + extra))
    one_line_error(download(reg, data, "fr3_test"), "refused to unpack", "more than 40 members")
    _nothing_unpacked(tmp_path, data)


# ----------------------------------------------------------------------------- members that are not files


TOP = "rgbd_dataset_freiburg3_test/"


@pytest.mark.parametrize(("member", "needles"), [
    (_link(TOP + "rgb", "/tmp/mslam_evil", tarfile.SYMTYPE), ("symbolic link", "/tmp/mslam_evil")),
    (_link(TOP + "passwd", "/etc/passwd", tarfile.LNKTYPE), ("hard link", "/etc/passwd")),
    (_link(TOP + "fifo", "", tarfile.FIFOTYPE), ("special file",)),
    ((TOP + "deep/" * 40 + "x.txt", b"x"), ("42 path components", "limits 32")),
    ((TOP + "d" * 200 + "/" + "e" * 200 + "/" * 5 + "f" * 1500, b"x"), ("1934 characters", "1024")),
])
def test_tar_members_that_are_not_plain_files_refused(tmp_path, server, tum_src, member, needles):
    members = tum_members(tum_src)
    # the link first, then a file "through" it: the classic escape when links are extracted
    evil = [member] + ([(TOP + "rgb/evil.png", b"gotcha")] if "symbolic" in needles[0] else [])
    reg, data = _serve(server, tum_src, tmp_path, _tar(members[:2] + evil + members[2:]))
    one_line_error(download(reg, data, "fr3_test"), TGZ, "refused to unpack", *needles)
    _nothing_unpacked(tmp_path, data)


@pytest.mark.parametrize("kind", ["symlink", "bzip2"])
def test_zip_members_that_cannot_be_unpacked_safely(tmp_path, server, tum_src, kind):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as z:
        for n, b in tum_members(tum_src):
            z.writestr(n, b)
        if kind == "symlink":
            info = zipfile.ZipInfo("rgbd_dataset_freiburg3_test/link")
            info.external_attr = 0o120777 << 16
            z.writestr(info, "/etc")
        else:
            z.writestr("rgbd_dataset_freiburg3_test/notes.txt", b"a" * 1000, compress_type=zipfile.ZIP_BZIP2)
    reg, data = _serve(server, tum_src, tmp_path, buf.getvalue(), "seq.zip")
    needles = ("symbolic link",) if kind == "symlink" else ("compression method 12", "stored or deflate")
    one_line_error(download(reg, data, "fr3_test"), "seq.zip", "refused to unpack", *needles)
    _nothing_unpacked(tmp_path, data)


# ----------------------------------------------------------------------------- --force


def test_failed_force_restores_the_old_folder(tmp_path, server, tum_src, monkeypatch):
    reg, data = registry(tmp_path, server, tum_src)
    serve_tum(server, tum_src)
    assert download(reg, data, "fr3_test").exit_code == 0
    root = data / TUM_ROOT
    (root / "my_notes.txt").write_text("mine")
    before = tree(root)
    rename = os.rename

    def failing(src, dst, *a, **k):  # the new folder cannot take the old one's place
        if ".unpack-" in str(src) and Path(dst) == root:
            raise PermissionError(13, "Permission denied")
        return rename(src, dst, *a, **k)

    monkeypatch.setattr(os, "rename", failing)
    r = download(reg, data, "fr3_test", extra=("--force",))
    assert tree(root) == before
    assert leftovers(root.parent) == []
    one_line_error(r, "cannot unpack", "Permission denied", "is unchanged")


def test_killed_force_is_finished_by_the_next_command(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    serve_tum(server, tum_src)
    assert download(reg, data, "fr3_test").exit_code == 0
    root = data / TUM_ROOT
    (root / "my_notes.txt").write_text("mine")
    before = tree(root)
    old = root.parent / f".{root.name}.old-4242-abcd"  # killed after moving the old folder aside ...
    old.mkdir()
    os.rename(root, old / root.name)
    (root.parent / f".{root.name}.unpack-4242-abcd" / "rgb").mkdir(parents=True)  # ... with a half-unpacked new one
    n = len(server.requests)
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert "restored the folder an interrupted --force had moved" in r.output, r.output
    assert "download skipped" in r.output
    assert len(server.requests) == n
    assert tree(root) == before
    assert leftovers(root.parent) == []
