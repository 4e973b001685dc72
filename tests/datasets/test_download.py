"""``mslam datasets download``: fetching, resuming, checksums and unpacking, against a local HTTP server.

The server (:mod:`dl_server`, 127.0.0.1, port 0) serves archives built in the publishers' layouts from a
tiny rendered sequence: a TUM ``.tgz`` with one top folder, an ICL-NUIM ``*_frei_png.tar.gz`` (files at
the top or in one folder) with its separate ``.gt.freiburg``, and a 7-Scenes scene zip with a nested
``seq-01.zip``. It honours ``Range`` / ``If-Range`` requests and can cut the connection after N bytes.
Attacks and careless inputs (unsafe names, other entities, bombs, links, locks) are in
``test_download_safety.py`` and ``test_unpack_limits.py``.
"""

from __future__ import annotations

import errno
import io
import json
import shutil
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest
from dl_server import (
    ICL,
    ICL_GT,
    TGZ,
    data_lines,
    download,
    downloads,
    entries,
    leftovers,
    one_line_error,
    registry,
    runner,
    serve_tum,
    sha,
    tgz,
)

from mutualslam_cli.cli import app
from mutualslam_cli.datasets import load_sequence
from mutualslam_cli.datasets.download import entry as dl
from mutualslam_cli.datasets.download import unpack as up
from mutualslam_cli.datasets.download.limits import Budget
from mutualslam_cli.geometry import pose_from_tq


def _icl_members(src: Path) -> tuple[list[tuple[str, bytes]], bytes]:
    """ICL-NUIM layout: rgb/N.png, depth/N.png, associations.txt (depth first), and the GT file's bytes."""
    rgb, dep, gt = data_lines(src / "rgb.txt"), data_lines(src / "depth.txt"), data_lines(src / "groundtruth.txt")
    members, assoc, gt_lines = [], [], []
    for k, (r, d, g) in enumerate(zip(rgb, dep, gt), start=1):
        members += [(f"rgb/{k}.png", (src / r[1]).read_bytes()), (f"depth/{k}.png", (src / d[1]).read_bytes())]
        assoc.append(f"{k} depth/{k}.png {k} rgb/{k}.png")
        gt_lines.append(" ".join([str(k), *g[1:]]))
    members.append(("associations.txt", ("\n".join(assoc) + "\n").encode()))
    return members, ("\n".join(gt_lines) + "\n").encode()


# ----------------------------------------------------------------------------- complete downloads


def test_tum_archive_complete(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert "GT coverage" in r.output
    assert "100.0 %" in r.output
    assert "recorded" in r.output
    seq = load_sequence("fr3_test", data_root=data, registry_path=reg)
    assert len(seq) == 6
    assert all(f.pose is not None for f in seq.frames)
    assert (data / "_downloads" / TGZ).read_bytes() == archive
    sums = json.loads((data / "_downloads" / "checksums.json").read_text())
    assert sums[TGZ]["sha256"] == sha(archive)
    assert sums[TGZ]["bytes"] == len(archive)
    assert leftovers(data / "TUM") == []
    assert not list((data / "_downloads").glob("*.part"))
    n = len(server.requests)
    r = download(reg, data, "fr3_test")  # a complete folder is skipped, and still checked
    assert r.exit_code == 0, r.output
    assert "already exists" in r.output, r.output
    assert "GT coverage" in r.output, r.output
    assert len(server.requests) == n


@pytest.mark.parametrize("top", ["", "living_room_traj9_frei_png/"])
def test_icl_archive_and_gt_file(tmp_path, server, tum_src, top):
    reg, data = registry(tmp_path, server, tum_src)
    members, gt = _icl_members(tum_src)
    server.files[ICL] = tgz([(top + n, b) for n, b in members])
    server.files[f"VaFRIC/{ICL_GT}"] = gt
    r = download(reg, data, "icl_test")
    assert r.exit_code == 0, r.output
    root = data / "ICL-NUIM" / "living_room_traj9_frei_png"
    assert (root / ICL_GT).read_bytes() == gt
    assert (root / "associations.txt").is_file()
    assert root.stat().st_mode & 0o777 != 0o700  # the usual permissions, not those of a private temporary folder
    seq = load_sequence("icl_test", data_root=data, registry_path=reg)
    assert len(seq) == 6
    assert all(f.pose is not None for f in seq.frames)
    sums = json.loads((data / "_downloads" / "checksums.json").read_text())
    assert sums[ICL]["sha256"] == sha(server.files[ICL])
    assert sums[ICL_GT]["sha256"] == sha(gt)
    assert leftovers(root.parent) == []


def test_7scenes_scene_zip_converted_to_tum(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    rgb, dep, gt = (data_lines(tum_src / f) for f in ("rgb.txt", "depth.txt", "groundtruth.txt"))
    inner, poses = io.BytesIO(), []
    with zipfile.ZipFile(inner, "w") as z:
        for i, (r, d, g) in enumerate(zip(rgb, dep, gt)):
            depth_mm = (cv2.imread(str(tum_src / d[1]), cv2.IMREAD_UNCHANGED).astype(np.float64) / 5).astype(np.uint16)
            depth_mm[0, :5] = 65535  # 7-Scenes' "no measurement"
            T = pose_from_tq(np.array(g[1:4], float), np.array(g[4:8], float))
            poses.append(T)
            z.writestr(f"seq-01/frame-{i:06d}.color.png", (tum_src / r[1]).read_bytes())
            z.writestr(f"seq-01/frame-{i:06d}.depth.png", cv2.imencode(".png", depth_mm)[1].tobytes())
            z.writestr(f"seq-01/frame-{i:06d}.pose.txt", "\n".join(" ".join(f"{v:.9e}" for v in row) for row in T))
    outer = io.BytesIO()
    with zipfile.ZipFile(outer, "w") as z:
        z.writestr("kitchen/TestSplit.txt", "sequence1\n")
        z.writestr("kitchen/seq-01.zip", inner.getvalue())
    server.files["kitchen.zip"] = outer.getvalue()
    r = download(reg, data, "seven_test")
    assert r.exit_code == 0, r.output
    seq = load_sequence("seven_test", data_root=data, registry_path=reg)
    assert len(seq) == 6
    assert seq.frames[1].timestamp == pytest.approx(1 / 30, abs=1e-6)
    np.testing.assert_allclose(seq.frames[2].pose, poses[2], atol=1e-6)
    d0 = seq.load_depth(0)
    assert np.all(d0[0, :5] == 0)
    assert 0.5 < np.median(d0[d0 > 0]) < 20


# ----------------------------------------------------------------------------- failures


def test_resume_after_cut_connection(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    half = len(archive) // 2
    server.cut_after = half
    r = download(reg, data, "fr3_test")
    one_line_error(r, "download of", TGZ, "interrupted at", "run the command again to resume")
    part = data / "_downloads" / f"{TGZ}.part"
    assert part.stat().st_size == half
    assert not (data / "TUM").exists()
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert f"bytes={half}-" in server.ranges()
    assert "resumed at" in r.output
    assert (data / "_downloads" / TGZ).read_bytes() == archive
    assert not part.exists()
    assert len(load_sequence("fr3_test", data_root=data, registry_path=reg)) == 6


def test_complete_part_and_force(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    (data / "_downloads" / f"{TGZ}.part").write_bytes(archive)  # whole, but never renamed: the server says 416
    (data / "_downloads" / f"{TGZ}.partinfo").write_text(json.dumps(  # as the first request recorded it
        {"url": server.url(TGZ), "etag": server.etag(TGZ), "last_modified": None, "total": len(archive)}))
    assert download(reg, data, "fr3_test").exit_code == 0
    assert server.ranges() == [f"bytes={len(archive)}-"]
    assert server.if_ranges == [server.etag(TGZ)]
    root = data / "TUM" / "rgbd_dataset_freiburg3_test"
    (root / "stray.txt").write_text("x")
    r = download(reg, data, "fr3_test", extra=("--force",))
    assert r.exit_code == 0, r.output
    assert "using the file downloaded before" in r.output, r.output
    assert not (root / "stray.txt").exists()
    assert (root / "rgb.txt").is_file()
    assert leftovers(root.parent) == []


def test_server_ignoring_range_starts_over(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    (data / "_downloads" / f"{TGZ}.part").write_bytes(b"stale bytes of another file")
    (data / "_downloads" / f"{TGZ}.partinfo").write_text(json.dumps(
        {"url": server.url(TGZ), "etag": server.etag(TGZ), "last_modified": None, "total": len(archive)}))
    server.ignore_range = True  # answers 200: the .part must be rewritten, not appended to
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert server.ranges()
    assert (data / "_downloads" / TGZ).read_bytes() == archive


def test_corrupted_against_recorded_checksum(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    assert download(reg, data, "fr3_test").exit_code == 0
    shutil.rmtree(data / "TUM" / "rgbd_dataset_freiburg3_test")  # start again, but keep checksums.json
    (data / "_downloads" / TGZ).unlink()
    bad = bytearray(archive)
    bad[len(bad) // 2] ^= 0xFF
    server.files[TGZ] = bytes(bad)
    r = download(reg, data, "fr3_test")
    line = one_line_error(r, TGZ, "does not match", sha(archive), "recorded", "removed the file")
    assert sha(bytes(bad)) in line
    assert downloads(data) == ["checksums.json"]
    assert list((data / "TUM").iterdir()) == []


def test_corrupted_against_published_checksum(tmp_path, server, tum_src):
    published = "0" * 64
    reg, data = registry(tmp_path, server, tum_src, fr3_test={"checksums": {TGZ: f"sha256:{published}"}})
    serve_tum(server, tum_src)
    r = download(reg, data, "fr3_test")
    one_line_error(r, TGZ, "does not match the published", published, "removed the file")
    assert [n for n in downloads(data) if n.startswith(TGZ)] == []
    assert not (data / "TUM").exists()
    sums = data / "_downloads" / "checksums.json"
    assert not sums.exists() or TGZ not in json.loads(sums.read_text())


def test_truncated_archive(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    server.files[TGZ] = archive[: int(len(archive) * 0.6)]  # served whole, with a matching Content-Length
    r = download(reg, data, "fr3_test")
    one_line_error(r, str(data / "_downloads" / TGZ), "truncated or corrupt archive", "removed it")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists()
    assert leftovers(data / "TUM") == []
    assert not (data / "_downloads" / TGZ).exists()
    assert not (data / "_downloads" / "checksums.json").exists()
    server.files[TGZ] = archive  # the publisher's good file downloads fine afterwards
    assert download(reg, data, "fr3_test").exit_code == 0


@pytest.mark.parametrize("evil", ["../evil.txt", "/tmp/mslam_evil.txt", "rgb/../../../evil.txt"])
def test_path_traversal_member_rejected(tmp_path, server, tum_src, evil):
    reg, data = registry(tmp_path, server, tum_src)
    members = [(f"rgbd_dataset_freiburg3_test/{n}", b) for n, b in entries(tum_src)]
    server.files[TGZ] = tgz(members[:3] + [(evil, b"gotcha")] + members[3:])
    r = download(reg, data, "fr3_test")
    one_line_error(r, TGZ, repr(evil), "absolute path or '..'", "refused")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists()
    assert leftovers(data / "TUM") == []
    assert not list(tmp_path.rglob("evil.txt"))
    assert not Path("/tmp/mslam_evil.txt").exists()


def test_disk_full_while_unpacking(tmp_path, server, tum_src, monkeypatch):
    reg, data = registry(tmp_path, server, tum_src)
    serve_tum(server, tum_src)
    calls = []

    def full_disk(self, src, dst, name, consumed=None):
        calls.append(1)
        if len(calls) > 3:
            dst.write(src.read(10))
            raise OSError(errno.ENOSPC, "No space left on device")
        dst.write(src.read())

    monkeypatch.setattr(Budget, "copy", full_disk)
    r = download(reg, data, "fr3_test")
    one_line_error(r, "no space left on device while unpacking", TGZ, "removed the temporary folder")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists()
    assert leftovers(data / "TUM") == []
    assert (data / "_downloads" / TGZ).is_file()  # the archive is fine: kept for the next try
    monkeypatch.undo()
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert "using the file downloaded before" in r.output, r.output


def test_unknown_or_undownloadable_names(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    line = one_line_error(download(reg, data, "nope", "no_download"), "cannot download nope, no_download",
                           "downloadable: fr3_test, icl_test, seven_test")
    assert line.count("no_download") == 1
    one_line_error(download(reg, data), "name the sequences to download", "downloadable: fr3_test")


def test_http_404_and_base_url(tmp_path, server, tum_src, monkeypatch):
    reg, data = registry(tmp_path, server, tum_src)
    r = download(reg, data, "fr3_test")
    one_line_error(r, server.url(TGZ), "HTTP 404")
    server.files[f"mirror/{TGZ}"] = tgz([(f"top/{n}", b) for n, b in entries(tum_src)])
    r = download(reg, data, "fr3_test", extra=("--base-url", server.url("mirror/")))
    assert r.exit_code == 0, r.output
    assert (f"/mirror/{TGZ}", None) in server.requests
    shutil.rmtree(data)
    monkeypatch.setenv(dl.BASE_URL_ENV, server.url("mirror"))
    n = len(server.requests)
    assert download(reg, data, "fr3_test").exit_code == 0
    assert server.requests[n:] == [(f"/mirror/{TGZ}", None)]
    assert dl.file_url("https://x.org/p/q/f.tgz", None) == "https://x.org/p/q/f.tgz"
    assert dl.file_url("https://x.org/p/q/f.tgz", "http://m/") == "http://m/f.tgz"


def test_listing_and_check_unchanged(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    for words in (["datasets"], ["datasets", "list"]):  # `mslam datasets` alone still lists
        r = runner.invoke(app, [*words, "--registry", str(reg), "--data-root", str(data)])
        assert r.exit_code == 0, r.output
        assert "fr3_test" in r.output, r.output
    r = runner.invoke(app, ["datasets", "--registry", str(reg), "--data-root", str(data), "list"])
    assert r.exit_code == 0, r.output  # options before the sub-command apply to it
    assert "fr3_test" in r.output, r.output
    r = runner.invoke(app, ["datasets", "check", str(tum_src), str(tum_src), "--sample", "2"])
    assert r.exit_code == 0, r.output
    assert r.output.count("GT coverage") == 2, r.output
    one_line_error(runner.invoke(app, ["datasets", "check", str(tmp_path / "nope")]), "nope")
    r = runner.invoke(app, ["datasets", "a", "b"])
    assert r.exit_code == 2, r.output
    assert "No such command 'a'" in r.output, r.output


def test_safe_relpath():
    assert str(up.safe_relpath("./a/b.png")) == "a/b.png"
    for bad in ("/etc/passwd", "a/../../b", "..", "C:/x", "a\\..\\..\\b"):
        with pytest.raises(up.UnsafeMember):
            up.safe_relpath(bad)
