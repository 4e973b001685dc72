"""Test helpers: tiny synthetic RGB-D sequences (in memory or in TUM layout on disk).

Other test files use these instead of real data::

    from synth import make_sequence, make_tum_dir
    root = make_tum_dir(tmp_path, scene="room", n=8)   # < 1 s at 64×48
"""

from __future__ import annotations

from pathlib import Path

from mutualslam_cli.datasets.synthetic import SyntheticSequence, render_sequence, write_tum


def make_sequence(scene: str = "room", n: int = 8, width: int = 64, height: int = 48, seed: int = 0,
                  domain: str = "target") -> SyntheticSequence:
    """A rendered synthetic sequence held in memory (exact depth and ``T_wc`` poses)."""
    return render_sequence(scene, n, width, height, seed, domain)  # type: ignore[arg-type]


def make_tum_dir(tmp_path: Path, scene: str = "room", n: int = 8, width: int = 64, height: int = 48,
                 seed: int = 0, domain: str = "target") -> Path:
    """Render a tiny sequence and write it in TUM layout under ``tmp_path``; returns the folder.

    The folder holds ``rgb/``, ``depth/``, ``rgb.txt``, ``depth.txt``, ``groundtruth.txt`` and
    ``intrinsics.txt`` (see :func:`mutualslam_cli.datasets.synthetic.write_tum`).
    """
    out = Path(tmp_path) / f"synth_{scene}_{domain}_s{seed}_{width}x{height}_n{n}"
    return write_tum(make_sequence(scene, n, width, height, seed, domain), out)


def plant_tracking_failures(root: Path, blackout: tuple[int, int] | None = None,
                            drop: tuple[int, int] | None = None) -> Path:
    """Make a TUM-layout folder hard to track, in place: frames ``blackout[0]..blackout[1]`` (inclusive)
    become black images (a covered lens, a failed exposure), and frames ``drop[0]..drop[1]`` disappear
    from ``rgb.txt`` and ``depth.txt`` (dropped frames: the camera jumps ahead, a whip). Returns ``root``."""
    import cv2
    import numpy as np

    def entries(name: str) -> tuple[list[str], list[str]]:
        lines = (root / name).read_text().splitlines()
        return [ln for ln in lines if ln.startswith("#")], [ln for ln in lines if ln and not ln.startswith("#")]

    if blackout is not None:
        _, rgb = entries("rgb.txt")
        for ln in rgb[blackout[0]:blackout[1] + 1]:
            path = root / ln.split()[1]
            img = cv2.imread(str(path))
            cv2.imwrite(str(path), np.zeros_like(img))
    if drop is not None:
        for name in ("rgb.txt", "depth.txt"):
            head, body = entries(name)
            keep = body[:drop[0]] + body[drop[1] + 1:]
            (root / name).write_text("\n".join(head + keep) + "\n")
    return root
