"""What the download tests share: a local HTTP file server, archives in the publishers' layouts, a registry
pointing at them, and the checks of one error line and of leftovers.

The server (127.0.0.1, port 0) honours ``Range`` and ``If-Range`` and sends an ``ETag`` (from the file's
bytes) and a ``Last-Modified``, like the publishers' servers; switches make it misbehave: ``cut_after``
(one-shot: send only that many body bytes and close), ``ignore_range`` (always 200 with the whole file),
``ignore_if_range`` (resume even when the validator does not match: the splice a client must catch
itself), ``validators`` (False: no ETag / Last-Modified), ``redirects`` (path → Location, a 302), ``custom`` (path →
``(status, reason, headers, body)``: that answer to every request), ``resume_range`` (one-shot: answer the
next ``Range`` request with 206 and this ``(first, last)`` byte range instead).
"""

from __future__ import annotations

import hashlib
import io
import re
import tarfile
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any

import yaml
from typer.testing import CliRunner

from mutualslam_cli.cli import app

runner = CliRunner()
TGZ = "rgbd_dataset_freiburg3_test.tgz"
ICL = "living_room_traj9_frei_png.tar.gz"
ICL_GT = "livingRoom9.gt.freiburg"
TUM_ROOT = "TUM/rgbd_dataset_freiburg3_test"


class Server:
    """A file server on 127.0.0.1 (see the module docstring); ``requests`` logs ``(path, Range)`` and
    ``if_ranges`` the ``If-Range`` header of each request."""

    def __init__(self) -> None:
        self.files: dict[str, bytes] = {}
        self.cut_after: int | None = None
        self.ignore_range = False
        self.ignore_if_range = False
        self.validators = True
        self.redirects: dict[str, str] = {}
        self.custom: dict[str, tuple[int, str, dict[str, str], bytes]] = {}
        self.resume_range: tuple[int, int] | None = None
        self.requests: list[tuple[str, str | None]] = []
        self.if_ranges: list[str | None] = []
        srv = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # http.server's name
                rng, if_range = self.headers.get("Range"), self.headers.get("If-Range")
                srv.requests.append((self.path, rng))
                srv.if_ranges.append(if_range)
                path = self.path.lstrip("/")
                if path in srv.redirects:
                    self.send_response(302)
                    self.send_header("Location", srv.redirects[path])
                    self.send_header("Content-Length", "0")
                    self.end_headers()
                    return
                if path in srv.custom:
                    code, reason, headers, body = srv.custom[path]
                    self.send_response(code, reason)
                    for k, v in {"Content-Length": str(len(body)), **headers}.items():
                        self.send_header(k, v)
                    self.end_headers()
                    self.wfile.write(body)
                    return
                data = srv.files.get(path)
                if data is None:
                    self.send_error(404)
                    return
                etag, modified = srv.etag(path), "Mon, 01 Jan 2024 00:00:00 GMT"
                if if_range is not None and if_range not in (etag, modified) and not srv.ignore_if_range:
                    rng = None  # RFC 9110 13.1.5: the validator does not match — send the whole, current file
                start = 0
                if rng and not srv.ignore_range:
                    start = int(re.fullmatch(r"bytes=(\d+)-", rng).group(1))  # type: ignore[union-attr]
                    if start >= len(data):
                        self.send_response(416)
                        self.send_header("Content-Range", f"bytes */{len(data)}")
                        self.send_header("Content-Length", "0")
                        self.end_headers()
                        return
                    end = len(data) - 1
                    if srv.resume_range is not None:
                        (start, end), srv.resume_range = srv.resume_range, None
                    self.send_response(206)
                    self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
                else:
                    self.send_response(200)
                if srv.validators:
                    self.send_header("ETag", etag)
                    self.send_header("Last-Modified", modified)
                body = data[start:end + 1] if rng and not srv.ignore_range else data
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

    def etag(self, path: str) -> str:
        """The ETag the server sends for ``path`` (from its current bytes)."""
        return '"' + hashlib.sha256(self.files[path]).hexdigest()[:16] + '"'

    def url(self, path: str) -> str:
        return f"http://127.0.0.1:{self.httpd.server_address[1]}/{path}"

    def ranges(self) -> list[str]:
        return [r for _, r in self.requests if r]

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


# ----------------------------------------------------------------------------- archives and registries


def entries(folder: Path) -> list[tuple[str, bytes]]:
    """``(relative path, bytes)`` of every file under ``folder``."""
    return [(p.relative_to(folder).as_posix(), p.read_bytes()) for p in sorted(folder.rglob("*")) if p.is_file()]


def tgz(members: list[tuple[str, bytes]]) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz") as tf:
        for name, data in members:
            info = tarfile.TarInfo(name)
            info.size = len(data)
            tf.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def tum_members(src: Path) -> list[tuple[str, bytes]]:
    return [(f"rgbd_dataset_freiburg3_test/{n}", b) for n, b in entries(src)]


def serve_tum(server: Server, src: Path) -> bytes:
    data = tgz(tum_members(src))
    server.files[TGZ] = data
    return data


def data_lines(path: Path) -> list[list[str]]:
    return [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def registry(tmp_path: Path, server: Server, src: Path, **download_overrides: dict) -> tuple[Path, Path]:
    """A registry with fr3_test (TUM .tgz), icl_test (ICL + GT), seven_test (7-Scenes) and no_download."""
    fx, fy, cx, cy = (float(v) for v in (src / "intrinsics.txt").read_text().split()[:4])
    ents: dict[str, dict] = {
        "fr3_test": {"root": TUM_ROOT, "format": "tum", "depth_scale": 5000,
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
        top = {k: over.pop(k) for k in list(over) if k in ("gt_name", "root")}
        ents[name]["download"].update(over)
        if "gt_name" in top:
            ents[name]["gt"] = top["gt_name"]
        if "root" in top:
            ents[name]["root"] = top["root"]
    reg = tmp_path / "datasets.yaml"
    reg.write_text(yaml.safe_dump({"datasets": ents}, sort_keys=False))
    return reg, tmp_path / "data"


def download(reg: Path, data: Path, *names: str, extra: tuple[str, ...] = ()) -> Any:
    return runner.invoke(app, ["datasets", "download", *names, "--registry", str(reg), "--data-root", str(data),
                               "--sample", "3", *extra])


def one_line_error(result: Any, *needles: str) -> str:
    """The one ``error:`` line of a failed command (exit code 1, no traceback, the last line), checked to hold
    each of ``needles``."""
    assert result.exit_code == 1, result.output
    assert "Traceback" not in result.output
    lines = [ln for ln in result.output.splitlines() if ln.strip()]  # notes (e.g. "SHA-256 recorded") may precede
    errors = [ln for ln in lines if ln.startswith("error:")]
    assert len(errors) == 1, result.output
    assert lines[-1] == errors[0], result.output
    for n in needles:
        assert n in errors[0], (n, result.output)
    return errors[0]


def leftovers(parent: Path) -> list[str]:
    """Hidden entries in ``parent`` (temporary or moved-aside folders of an unpacking)."""
    return [p.name for p in parent.glob(".*")] if parent.is_dir() else []


def downloads(data: Path) -> list[str]:
    """Names in ``<data>/_downloads`` apart from the lock files (which stay, as notes for the next holder)."""
    folder = data / "_downloads"
    return sorted(p.name for p in folder.iterdir() if not p.name.endswith(".lock")) if folder.is_dir() else []


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def tree(root: Path) -> dict[str, bytes]:
    """Every file under ``root`` (relative path → bytes), to show a folder unchanged."""
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}
