"""The journal's memory per keyframe (slow: run by hand or `make test-all`), the figure the README gives for
5,000 rendered frames (640 × 480, our VO): 42 kB of events per keyframe in memory, 467 kB per resumption
point, 90 kB per keyframe in the cache file. Measured here on 400 frames of the same room."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from mutualslam_cli.config import RunConfig, with_overrides
from mutualslam_cli.datasets.registry import load_sequence
from mutualslam_cli.datasets.synthetic import iter_render, write_tum
from mutualslam_cli.vo.journal_cache import cache_path
from mutualslam_cli.vo.source import FrontEndSource

#: README figures (5,000 frames: 10,185 events, 540 keyframes, 67 resumption points): bytes.
PER_KEYFRAME, PER_CHECKPOINT, FILE_PER_KEYFRAME = 22.81e6 / 540, 31.27e6 / 67, 48.59e6 / 540


def journal_bytes(events) -> int:
    """Bytes the events hold: objects, their dicts, arrays (data + 112 bytes of header), other values."""
    n = sys.getsizeof(events)
    for e in events:
        n += sys.getsizeof(e) + sys.getsizeof(e.data)
        n += sum(v.nbytes + 112 if isinstance(v, np.ndarray) else sys.getsizeof(v) for v in e.data.values())
    return n


@pytest.mark.slow
def test_journal_memory_per_keyframe_is_the_readmes(tmp_path: Path):
    root = write_tum(iter_render("room", 400, 640, 480, seed=0), tmp_path / "room400", scene="room", seed=0)
    seq = load_sequence(root)
    cfg = with_overrides(RunConfig(), threads=1)
    src = FrontEndSource(seq, cfg, tmp_path / "cache")
    src.run_all()
    nk = src.state.n_keyframes
    ev = journal_bytes(src.pure) / nk
    ck = sum(v.nbytes for c in src.pure_ckpts.values() for v in c.values() if isinstance(v, np.ndarray))
    ck /= max(1, len(src.pure_ckpts))
    src.close()
    file = cache_path(tmp_path / "cache", seq, cfg).stat().st_size / nk
    print(f"400 frames: {nk} keyframes, {len(src.pure)} events; {ev / 1e3:.1f} kB per keyframe, "
          f"{ck / 1e3:.0f} kB per resumption point, file {file / 1e3:.1f} kB per keyframe")
    assert nk > 20
    assert len(src.pure_ckpts) >= 2
    for got, readme in ((ev, PER_KEYFRAME), (ck, PER_CHECKPOINT), (file, FILE_PER_KEYFRAME)):
        assert readme / 1.5 <= got <= 1.5 * readme, (got, readme)
