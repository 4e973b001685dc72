"""``mslam datasets download``: fetching, resuming, checksums and unpacking, against a local HTTP server.

The server (127.0.0.1, port 0) serves archives built in the publishers' layouts from a tiny rendered
sequence: a TUM ``.tgz`` with one top folder, an ICL-NUIM ``*_frei_png.tar.gz`` (files at the top
or in one folder) with its separate ``.gt.freiburg``, and a 7-Scenes scene zip with a nested
``seq-01.zip``. It honours ``Range`` requests and can cut the connection after N bytes.
"""

from __future__ import annotations

import errno
import hashlib
import io
import json
import re
import shutil
import tarfile
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest
import yaml
from synth import make_tum_dir
from typer.testing import CliRunner

from mutualslam_cli.cli import app
from mutualslam_cli.datasets import download as dl
from mutualslam_cli.datasets import load_sequence
from mutualslam_cli.datasets import unpack as up
from mutualslam_cli.geometry import pose_from_tq

runner = CliRunner()
TGZ = "rgbd_dataset_freiburg3_test.tgz"
ICL = "living_room_traj9_frei_png.tar.gz"
ICL_GT = "livingRoom9.gt.freiburg"


# ----------------------------------------------------------------------------- the server


class Server:
    """A file server on 127.0.0.1 with ``Range`` support; ``cut_after`` (one-shot) sends only that many
    body bytes and closes; ``ignore_range`` answers 200 with the whole file; ``requests`` logs
    ``(path, Range header)``."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.cut_after: int | None = None
        self.ignore_range = False
        self.requests: list[tuple[str, str | None]] = []
        srv = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - http.server's name
                rng = self.headers.get("Range")
                srv.requests.append((self.path, rng))
                data = srv.files.get(self.path.lstrip("/"))
                if data is None:
                    self.send_error(404)
                    return
                start = 0
                if rng and not srv.ignore_range:
                    start = int(re.fullmatch(r"bytes=(\d+)-", rng).group(1))  # type: ignore[union-attr]
                    if start >= len(data):
                        self.send_response(416)
                        self.send_header("Content-Range", f"bytes */{len(data)}")
                        self.send_header("Content-Length", "0")
                        self.end_headers()
                        return
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{len(data) - 1}/{len(data)}")
                else:
                    self.send_response(200)
                body = data[start:]
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                if srv.cut_after is not None:
                    body, srv.cut_after = body[:srv.cut_after], None
                self.wfile.write(body)

            def log_message(self, *args: Any) -> None:
                pass

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.thread = threading.Thread(target=self.httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/{path}"

    def ranges(self) -> list[str]:
        return [r for _, r in self.requests if r]


@pytest.fixture
def server():
    s = Server()
    yield s
    s.httpd.shutdown()
    s.httpd.server_close()


# ----------------------------------------------------------------------------- archives


@pytest.fixture(scope="module")
def tum_src(tmp_path_factory) -> Path:
    return make_tum_dir(tmp_path_factory.mktemp("src"), scene="room", n=6, width=64, height=48)


def _entries(folder: Path) -> list[tuple[str, bytes]]:
    return [(p.relative_to(folder).as_posix(), p.read_bytes()) for p in sorted(folder.rglob("*")) if p.is_file()]


def _tgz(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def _data_lines(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def _icl_members(src: Path) -> tuple[list[tuple[str, bytes]], bytes]:
    """ICL-NUIM layout: rgb/N.png, depth/N.png, associations.txt (depth first), and the GT file's bytes."""
    rgb, dep, gt = _data_lines(src / "rgb.txt"), _data_lines(src / "depth.txt"), _data_lines(src / "groundtruth.txt")
    members, assoc, gt_lines = [], [], []
    for k, (r, d, g) in enumerate(zip(rgb, dep, gt), start=1):
        members += [(f"rgb/{k}.png", (src / r[1]).read_bytes()), (f"depth/{k}.png", (src / d[1]).read_bytes())]
        assoc.append(f"{k} depth/{k}.png {k} rgb/{k}.png")
        gt_lines.append(" ".join([str(k), *g[1:]]))
    members.append(("associations.txt", ("\n".join(assoc) + "\n").encode()))
    return members, ("\n".join(gt_lines) + "\n").encode()


def _registry(tmp_path: Path, server: Server, src: Path, **download_overrides: dict) -> tuple[Path, Path]:
    """A registry with fr3_test (TUM .tgz), icl_test (ICL + GT), seven_test (7-Scenes) and no_download."""
    fx, fy, cx, cy = (float(v) for v in (src / "intrinsics.txt").read_text().split()[:4])
    entries: dict[str, dict] = {
        "fr3_test": {"root": "TUM/rgbd_dataset_freiburg3_test", "format": "tum", "depth_scale": 5000,
                     "gt": "groundtruth.txt", "download": {"archive": server.url(TGZ)}},
        "icl_test": {"root": "ICL-NUIM/living_room_traj9_frei_png", "format": "icl", "intrinsics": [fx, fy, cx, cy],
                     "depth_scale": 5000, "gt": ICL_GT, "fy_sign": 1,
                     "download": {"archive": server.url(ICL), "gt": server.url(f"VaFRIC/{ICL_GT}")}},
        "seven_test": {"root": "7-Scenes/kitchen_seq-01", "format": "tum", "intrinsics": [fx, fy, cx, cy],
                       "depth_scale": 1000, "gt": "groundtruth.txt",
                       "download": {"archive": server.url("kitchen.zip"), "layout": "7scenes", "sequence": "seq-01"}},
        "no_download": {"root": "elsewhere", "format": "tum"},
    }
    for name, over in download_overrides.items():
        entries[name]["download"].update(over)
    reg = tmp_path / "datasets.yaml"
    reg.write_text(yaml.safe_dump({"datasets": entries}, sort_keys=False))
    return reg, tmp_path / "data"


def _serve_tum(server: Server, src: Path) -> bytes:
    data = _tgz([(f"rgbd_dataset_freiburg3_test/{n}", b) for n, b in _entries(src)])
    server.files[TGZ] = data
    return data


def _download(reg: Path, data: Path, *names: str, extra: tuple[str, ...] = ()) -> Any:
    return runner.invoke(app, ["datasets", "download", *names, "--registry", str(reg), "--data-root", str(data),
                               "--sample", "3", *extra])


def _one_line_error(result: Any, *needles: str) -> str:
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]  # notes (e.g. "SHA-256 recorded") may precede
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1 and lines[-1] == errors[0], result.output
    for n in needles:
        assert n in errors[0], (n, result.output)
    return errors[0]


def _leftovers(parent: Path) -> list[str]:
    return [p.name for p in parent.glob(".*")] if parent.is_dir() else []


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


# ----------------------------------------------------------------------------- complete downloads


def test_tum_archive_complete(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    r = _download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert "GT coverage" in r.output and "100.0 %" in r.output and "recorded" in r.output
    seq = load_sequence("fr3_test", data_root=data, registry_path=reg)
    assert len(seq) == 6 and all(f.pose is not None for f in seq.frames)
    assert (data / "_downloads" / TGZ).read_bytes() == archive
    sums = json.loads((data / "_downloads" / "checksums.json").read_text())
    assert sums[TGZ]["sha256"] == _sha(archive) and sums[TGZ]["bytes"] == len(archive)
    assert _leftovers(data / "TUM") == [] and not list((data / "_downloads").glob("*.part"))
    n = len(server.requests)
    r = _download(reg, data, "fr3_test")  # a complete folder is skipped, and still checked
    assert r.exit_code == 0 and "already exists" in r.output and "GT coverage" in r.output, r.output
    assert len(server.requests) == n


@pytest.mark.parametrize("top", ["", "living_room_traj9_frei_png/"])
def test_icl_archive_and_gt_file(tmp_path, server, tum_src, top):
    reg, data = _registry(tmp_path, server, tum_src)
    members, gt = _icl_members(tum_src)
    server.files[ICL] = _tgz([(top + n, b) for n, b in members])
    server.files[f"VaFRIC/{ICL_GT}"] = gt
    r = _download(reg, data, "icl_test")
    assert r.exit_code == 0, r.output
    root = data / "ICL-NUIM" / "living_room_traj9_frei_png"
    assert (root / ICL_GT).read_bytes() == gt and (root / "associations.txt").is_file()
    assert root.stat().st_mode & 0o777 != 0o700  # the usual permissions, not those of a private temporary folder
    seq = load_sequence("icl_test", data_root=data, registry_path=reg)
    assert len(seq) == 6 and all(f.pose is not None for f in seq.frames)
    sums = json.loads((data / "_downloads" / "checksums.json").read_text())
    assert sums[ICL]["sha256"] == _sha(server.files[ICL]) and sums[ICL_GT]["sha256"] == _sha(gt)
    assert _leftovers(root.parent) == []


def test_7scenes_scene_zip_converted_to_tum(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    rgb, dep, gt = (_data_lines(tum_src / f) for f in ("rgb.txt", "depth.txt", "groundtruth.txt"))
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
    r = _download(reg, data, "seven_test")
    assert r.exit_code == 0, r.output
    seq = load_sequence("seven_test", data_root=data, registry_path=reg)
    assert len(seq) == 6 and seq.frames[1].timestamp == pytest.approx(1 / 30, abs=1e-6)
    np.testing.assert_allclose(seq.frames[2].pose, poses[2], atol=1e-6)
    d0 = seq.load_depth(0)
    assert np.all(d0[0, :5] == 0) and 0.5 < np.median(d0[d0 > 0]) < 20


# ----------------------------------------------------------------------------- failures


def test_resume_after_cut_connection(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    half = len(archive) // 2
    server.cut_after = half
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, "download of", TGZ, "interrupted at", "run the command again to resume")
    part = data / "_downloads" / f"{TGZ}.part"
    assert part.stat().st_size == half and not (data / "TUM").exists()
    r = _download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert f"bytes={half}-" in server.ranges() and "resumed at" in r.output
    assert (data / "_downloads" / TGZ).read_bytes() == archive and not part.exists()
    assert len(load_sequence("fr3_test", data_root=data, registry_path=reg)) == 6


def test_complete_part_and_force(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    (data / "_downloads" / f"{TGZ}.part").write_bytes(archive)  # whole, but never renamed: the server says 416
    assert _download(reg, data, "fr3_test").exit_code == 0
    assert server.ranges() == [f"bytes={len(archive)}-"]
    root = data / "TUM" / "rgbd_dataset_freiburg3_test"
    (root / "stray.txt").write_text("x")
    r = _download(reg, data, "fr3_test", extra=("--force",))
    assert r.exit_code == 0 and "using the file downloaded before" in r.output, r.output
    assert not (root / "stray.txt").exists() and (root / "rgb.txt").is_file() and _leftovers(root.parent) == []


def test_server_ignoring_range_starts_over(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    (data / "_downloads" / f"{TGZ}.part").write_bytes(b"stale bytes of another file")
    server.ignore_range = True  # answers 200: the .part must be rewritten, not appended to
    r = _download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert server.ranges() and (data / "_downloads" / TGZ).read_bytes() == archive


def test_corrupted_against_recorded_checksum(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    assert _download(reg, data, "fr3_test").exit_code == 0
    shutil.rmtree(data / "TUM" / "rgbd_dataset_freiburg3_test")  # start again, but keep checksums.json
    (data / "_downloads" / TGZ).unlink()
    bad = bytearray(archive)
    bad[len(bad) // 2] ^= 0xFF
    server.files[TGZ] = bytes(bad)
    r = _download(reg, data, "fr3_test")
    line = _one_line_error(r, TGZ, "does not match", _sha(archive), "recorded", "removed the file")
    assert _sha(bytes(bad)) in line
    assert not list((data / "_downloads").glob(f"{TGZ}*")) and list((data / "TUM").iterdir()) == []


def test_corrupted_against_published_checksum(tmp_path, server, tum_src):
    published = "0" * 64
    reg, data = _registry(tmp_path, server, tum_src, fr3_test={"checksums": {TGZ: f"sha256:{published}"}})
    _serve_tum(server, tum_src)
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, TGZ, "does not match the published", published, "removed the file")
    assert not list((data / "_downloads").glob(f"{TGZ}*")) and not (data / "TUM").exists()
    sums = data / "_downloads" / "checksums.json"
    assert not sums.exists() or TGZ not in json.loads(sums.read_text())


def test_truncated_archive(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    archive = _serve_tum(server, tum_src)
    server.files[TGZ] = archive[: int(len(archive) * 0.6)]  # served whole, with a matching Content-Length
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, str(data / "_downloads" / TGZ), "truncated or corrupt archive", "removed it")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists() and _leftovers(data / "TUM") == []
    assert not (data / "_downloads" / TGZ).exists() and not (data / "_downloads" / "checksums.json").exists()
    server.files[TGZ] = archive  # the publisher's good file downloads fine afterwards
    assert _download(reg, data, "fr3_test").exit_code == 0


@pytest.mark.parametrize("evil", ["../evil.txt", "/tmp/mslam_evil.txt", "rgb/../../../evil.txt"])
def test_path_traversal_member_rejected(tmp_path, server, tum_src, evil):
    reg, data = _registry(tmp_path, server, tum_src)
    members = [(f"rgbd_dataset_freiburg3_test/{n}", b) for n, b in _entries(tum_src)]
    server.files[TGZ] = _tgz(members[:3] + [(evil, b"gotcha")] + members[3:])
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, TGZ, repr(evil), "absolute path or '..'", "refused")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists() and _leftovers(data / "TUM") == []
    assert not list(tmp_path.rglob("evil.txt")) and not Path("/tmp/mslam_evil.txt").exists()


def test_disk_full_while_unpacking(tmp_path, server, tum_src, monkeypatch):
    reg, data = _registry(tmp_path, server, tum_src)
    _serve_tum(server, tum_src)
    calls = []

    def full_disk(src, dst):
        calls.append(1)
        if len(calls) > 3:
            dst.write(src.read(10))
            raise OSError(errno.ENOSPC, "No space left on device")
        dst.write(src.read())

    monkeypatch.setattr(up, "_copy", full_disk)
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, "no space left on device while unpacking", TGZ, "removed the temporary folder")
    assert not (data / "TUM" / "rgbd_dataset_freiburg3_test").exists() and _leftovers(data / "TUM") == []
    assert (data / "_downloads" / TGZ).is_file()  # the archive is fine: kept for the next try
    monkeypatch.undo()
    r = _download(reg, data, "fr3_test")
    assert r.exit_code == 0 and "using the file downloaded before" in r.output, r.output


def test_unknown_or_undownloadable_names(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    line = _one_line_error(_download(reg, data, "nope", "no_download"), "cannot download nope, no_download",
                           "downloadable: fr3_test, icl_test, seven_test")
    assert line.count("no_download") == 1
    _one_line_error(_download(reg, data), "name the sequences to download", "downloadable: fr3_test")


def test_http_404_and_base_url(tmp_path, server, tum_src, monkeypatch):
    reg, data = _registry(tmp_path, server, tum_src)
    r = _download(reg, data, "fr3_test")
    _one_line_error(r, server.url(TGZ), "HTTP 404")
    server.files[f"mirror/{TGZ}"] = _tgz([(f"top/{n}", b) for n, b in _entries(tum_src)])
    r = _download(reg, data, "fr3_test", extra=("--base-url", server.url("mirror/")))
    assert r.exit_code == 0, r.output
    assert (f"/mirror/{TGZ}", None) in server.requests
    shutil.rmtree(data)
    monkeypatch.setenv(dl.BASE_URL_ENV, server.url("mirror"))
    n = len(server.requests)
    assert _download(reg, data, "fr3_test").exit_code == 0
    assert server.requests[n:] == [(f"/mirror/{TGZ}", None)]
    assert dl.file_url("https://x.org/p/q/f.tgz", None) == "https://x.org/p/q/f.tgz"
    assert dl.file_url("https://x.org/p/q/f.tgz", "http://m/") == "http://m/f.tgz"


def test_listing_and_check_unchanged(tmp_path, server, tum_src):
    reg, data = _registry(tmp_path, server, tum_src)
    r = runner.invoke(app, ["datasets", "--registry", str(reg), "--data-root", str(data)])
    assert r.exit_code == 0 and "fr3_test" in r.output, r.output
    r = runner.invoke(app, ["datasets", "--check", str(tum_src), "--sample", "2"])
    assert r.exit_code == 0 and "GT coverage" in r.output, r.output
    _one_line_error(runner.invoke(app, ["datasets", "a", "b"]), "expected one NAME or PATH")


def test_safe_relpath():
    assert str(up.safe_relpath("./a/b.png")) == "a/b.png"
    for bad in ("/etc/passwd", "a/../../b", "..", "C:/x", "a\\..\\..\\b"):
        with pytest.raises(up.UnsafeMember):
            up.safe_relpath(bad)
