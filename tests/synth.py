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
