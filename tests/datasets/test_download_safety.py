"""``mslam datasets download`` against a crafted registry and a misbehaving server: names that would leave their
folder, a ``.part`` of another version of the file, a changed file, two processes on one file.

Each test runs the command line (in process) against the local server of :mod:`dl_server` and checks the exit
code, the one error line, and what is on disk afterwards.
"""

from __future__ import annotations

import fcntl
import json
import os
import urllib.parse
import urllib.request
from pathlib import Path

import pytest
import yaml
from dl_server import (
    ICL,
    ICL_GT,
    TGZ,
    TUM_ROOT,
    Server,
    download,
    downloads,
    entries,
    leftovers,
    one_line_error,
    registry,
    serve_tum,
    sha,
    tgz,
    tree,
)

from mutualslam_cli.datasets.download.entry import downloadable_specs
from mutualslam_cli.datasets.registry import DEFAULT_REGISTRY
from mutualslam_cli.errors import DatasetError


def _outside(tmp_path: Path) -> list[Path]:
    """Files anywhere under ``tmp_path`` but outside the data root, the registry and the source sequence."""
    return [p for p in tmp_path.rglob("*") if p.is_file() and not p.is_relative_to(tmp_path / "data")
            and p.name != "datasets.yaml"]


# ----------------------------------------------------------------------------- names from outside


@pytest.mark.parametrize(("evil", "why"), [
    ("..%2F..%2Fevil.tgz", "is a path"),                # ../../evil.tgz: out of _downloads and the data root
    ("ABS", "is a path"),                               # an absolute path, percent-encoded (into tmp_path/outside)
    ("%2E%2E", "is a path"),                            # ".."
    (".hidden.tgz", "starts with '.'"),
    ("evil%00.tgz", "outside the safe set"),            # NUL: today a ValueError traceback from open()
    ("checksums.json", "mslam's own files"),            # would replace the checksum store
    ("a%5C..%5Cb.tgz", "is a path"),                    # backslashes
])
def test_unsafe_url_file_names_refused(tmp_path, server, tum_src, evil, why):
    if evil == "ABS":
        evil = urllib.parse.quote(str(tmp_path / "outside" / "evil.tgz"), safe="")
        (tmp_path / "outside").mkdir()
    server.files[f"x/{evil}"] = tgz([(f"top/{n}", b) for n, b in entries(tum_src)])
    reg, data = registry(tmp_path, server, tum_src, fr3_test={"archive": server.url(f"x/{evil}")})
    r = download(reg, data, "fr3_test")
    one_line_error(r, server.url(f"x/{evil}"), "file name", why, "refused, nothing written")
    assert server.requests == []  # refused before any request
    assert not (data / "_downloads").exists()
    assert not (data / "TUM").exists()
    assert _outside(tmp_path) == []


@pytest.mark.parametrize(("field", "value"), [("gt_name", "../../evil.freiburg"), ("gt_name", "ABS"),
                                          ("sequence", "../../seq-01")])
def test_unsafe_registry_names_refused(tmp_path, server, tum_src, field, value):
    name = "icl_test" if field == "gt_name" else "seven_test"
    if value == "ABS":  # an absolute path (inside tmp_path, so that today's code cannot harm the machine)
        value = str(tmp_path / "outside" / "evil.freiburg")
        (tmp_path / "outside").mkdir()
    server.files[ICL] = tgz([(f"top/{n}", b) for n, b in entries(tum_src)])
    server.files[f"VaFRIC/{ICL_GT}"] = b"1 0 0 0 0 0 0 1\n"
    server.files["kitchen.zip"] = b"PK\x05\x06" + bytes(18)  # an empty zip
    reg, data = registry(tmp_path, server, tum_src, **{name: {field: value}})
    r = download(reg, data, name)
    one_line_error(r, f"entry '{name}'", "gt" if field == "gt_name" else "sequence", "file name", repr(value),
                   "refused")
    assert server.requests == []
    assert not data.exists()
    assert _outside(tmp_path) == []


def test_repository_registry_urls_are_https_with_safe_names():
    reg = yaml.safe_load(DEFAULT_REGISTRY.read_text())["datasets"]
    urls = [u for e in reg.values() if "download" in e for k, u in e["download"].items() if k in ("archive", "gt")]
    assert urls, [u for u in urls if not u.startswith("https://")]
    assert all(u.startswith("https://") for u in urls), [u for u in urls if not u.startswith("https://")]
    names = [n for n, e in reg.items() if "download" in e]
    assert len(downloadable_specs(names)) == len(names)  # every URL's file name, gt: and sequence: pass the rule


def test_https_to_http_redirect_refused_and_http_redirect_followed(tmp_path, server, tum_src):
    # (imported here: the other tests run on any version)
    from mutualslam_cli.datasets.download.fetch import _NoDowngrade

    req = urllib.request.Request("https://example.org/data/x.tgz")
    with pytest.raises(DatasetError, match="not https; refused"):
        _NoDowngrade().redirect_request(req, None, 302, "Found", {}, "http://example.org/data/x.tgz")
    assert _NoDowngrade().redirect_request(req, None, 302, "Found", {}, "https://mirror.org/x.tgz") is not None
    archive = serve_tum(server, tum_src)  # a plain redirect (here http → http) is still followed
    server.redirects["moved/" + TGZ] = server.url(TGZ)
    reg, data = registry(tmp_path, server, tum_src, fr3_test={"archive": server.url("moved/" + TGZ)})
    assert download(reg, data, "fr3_test").exit_code == 0
    assert (data / "_downloads" / TGZ).read_bytes() == archive


# ----------------------------------------------------------------------------- resume only the same file


def _cut_download(tmp_path, server, tum_src):
    """A download of version A cut in the middle; returns ``(reg, data, A)``."""
    reg, data = registry(tmp_path, server, tum_src)
    a = serve_tum(server, tum_src)
    server.cut_after = len(a) // 2
    one_line_error(download(reg, data, "fr3_test"), "interrupted", "resume")
    return reg, data, a


def _version_b(server: Server, tum_src: Path) -> bytes:
    b = tgz([(f"rgbd_dataset_freiburg3_test/{n}", (d + b"\n" if n.endswith(".txt") else d))
             for n, d in entries(tum_src)])  # the publisher's next version: other bytes
    server.files[TGZ] = b
    return b


@pytest.mark.parametrize("server_honours_if_range", [True, False])
def test_part_of_another_version_starts_over(tmp_path, server, tum_src, server_honours_if_range):
    reg, data, _a = _cut_download(tmp_path, server, tum_src)
    etag_a = server.etag(TGZ)
    b = _version_b(server, tum_src)
    server.ignore_if_range = not server_honours_if_range  # then it sends 206 of B: the client must compare ETags
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert server.if_ranges[-2 if not server_honours_if_range else -1] == etag_a  # the resume carried If-Range
    assert "changed since it was partly downloaded" in r.output
    assert "resumed at" not in r.output
    assert (data / "_downloads" / TGZ).read_bytes() == b  # B whole, not A's head spliced onto B's tail
    assert downloads(data) == ["checksums.json", TGZ]
    assert leftovers(data / "TUM") == []


def test_part_without_a_record_is_not_resumed(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    (data / "_downloads" / f"{TGZ}.part").write_bytes(b"bytes another tool left behind " * 40)
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert server.ranges() == []
    assert "no record of which version" in r.output
    assert (data / "_downloads" / TGZ).read_bytes() == archive


def test_server_without_validators_is_not_resumed(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    archive = serve_tum(server, tum_src)
    server.validators, server.cut_after = False, len(archive) // 3
    one_line_error(download(reg, data, "fr3_test"), "interrupted", "cannot be resumed safely")
    r = download(reg, data, "fr3_test")
    assert r.exit_code == 0, r.output
    assert server.ranges() == []
    assert (data / "_downloads" / TGZ).read_bytes() == archive


def test_changed_file_is_named_as_such(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    a = serve_tum(server, tum_src)
    assert download(reg, data, "fr3_test").exit_code == 0
    rec = json.loads((data / "_downloads" / "checksums.json").read_text())[TGZ]
    assert (rec["sha256"], rec["bytes"], rec["url"], rec["etag"]) == (sha(a), len(a), server.url(TGZ),
                                                                     server.etag(TGZ))
    old = tree(data / TUM_ROOT)
    (data / "_downloads" / TGZ).unlink()
    b = _version_b(server, tum_src)
    r = download(reg, data, "fr3_test", extra=("--force",))
    one_line_error(r, TGZ, "does not match", sha(a), "the publisher's file changed", f"size {len(a)} → {len(b)}",
                   "ETag", "delete the entry")
    assert tree(data / TUM_ROOT) == old
    assert leftovers(data / "TUM") == []
    assert downloads(data) == ["checksums.json"]


# ----------------------------------------------------------------------------- one process per file


def test_second_process_on_the_same_file_refused(tmp_path, server, tum_src):
    reg, data = registry(tmp_path, server, tum_src)
    serve_tum(server, tum_src)
    (data / "_downloads").mkdir(parents=True)
    lock = data / "_downloads" / f"{TGZ}.lock"
    lock.write_text(json.dumps({"pid": 4242, "host": "lab-pc", "since": "2024-01-01T10:00:00+00:00"}))
    fd = os.open(lock, os.O_RDWR)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another open file: what a second process holds
        r = download(reg, data, "fr3_test")
        one_line_error(r, TGZ, "another mslam process", "pid 4242 on lab-pc", "nothing was touched")
        assert server.requests == []
        assert downloads(data) == []
        assert not (data / "TUM").exists()
    finally:
        os.close(fd)
    assert download(reg, data, "fr3_test").exit_code == 0  # released: the next command works


def test_checksum_records_of_two_processes_are_merged(tmp_path):
    from mutualslam_cli.datasets.download.checksums import ChecksumStore
    from mutualslam_cli.datasets.download.fetch import Entity

    path = tmp_path / "checksums.json"
    one, two = ChecksumStore(path), ChecksumStore(path)  # both loaded before either records
    one.put("a.tgz", "aa", 1, Entity("https://x/a.tgz", '"e1"'))
    two.put("b.tgz", "bb", 2, Entity("https://x/b.tgz"))
    data = json.loads(path.read_text())
    assert sorted(data) == ["a.tgz", "b.tgz"]
    assert data["a.tgz"]["etag"] == '"e1"'
