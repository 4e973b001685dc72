"""Table 4's "bridged" credit: the front end on its own, joined by bridges computed on its own map.

A run's bridges are planned on the live map, which a global BA or a loop closure Algorithm 1 triggered
may already have refined; replayed onto the front end run alone they would credit the bridges with the
BA's work, and the live run's segments need not be the front end's alone. So the credit is computed
afresh (:func:`credit_bridges`): the front end alone is streamed from its journal and each of its new
segments is bridged at its first keyframe, on its own map as it stood then, by the network as adapted
up to that frame — the weights :class:`WeightsAt` kept while the loop ran.
"""

from __future__ import annotations

import copy
from pathlib import Path

import torch

from mutualslam_cli.adapt.inputs import keyframe_images
from mutualslam_cli.backend.bridges import Bridge, plan_bridge
from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.map.result import VOResult
from mutualslam_cli.map.state import MapState
from mutualslam_cli.online.labels import depth_predictor


def front_end_alone(seq: Sequence, cfg: RunConfig, cache_dir: Path | None) -> tuple[VOResult, set[int]]:
    """The front end on its own to the end (from the journal cache, which it fills) and the frames at which it
    created the first keyframe of each segment but the first (where its bridges are planned)."""
    from mutualslam_cli.vo.source import FrontEndSource

    source = FrontEndSource(seq, cfg, cache_dir)
    try:
        source.run_all()
        return source.result(), segment_starts(source.state)
    finally:
        source.close()


def segment_starts(state: MapState) -> set[int]:
    """Frames at which ``state``'s front end created the first keyframe of a segment, the first segment's aside."""
    seen: set[int] = set()
    out: set[int] = set()
    for k in range(state.n_keyframes):
        seg = state.segment(k)
        if seg not in seen:
            if seen:
                out.add(int(state.created_at[k]))
            seen.add(seg)
    return out


class WeightsAt:
    """The network's weights at chosen frames of the loop's clock (a copy on the CPU per frame).

    Args:
        frames: the frames to keep (:func:`segment_starts` of the front end alone).
    """

    def __init__(self, frames: set[int]) -> None:
        self.frames = frames
        self.kept: dict[int, dict[str, torch.Tensor]] = {}

    def at_frame(self, frame: int, net: torch.nn.Module) -> None:
        """The loop is at ``frame`` (before its keyframes' work): keep ``net``'s weights when asked for."""
        if frame in self.frames and frame not in self.kept:
            self.kept[frame] = {k: v.detach().to("cpu", copy=True) for k, v in net.state_dict().items()}


def credit_bridges(seq: Sequence, cfg: RunConfig, cache_dir: Path | None, net: torch.nn.Module, fast: bool,
                   weights: WeightsAt) -> tuple[VOResult, list[Bridge]]:
    """The front end alone (its journal in ``cache_dir``, or run again) with each new segment bridged at its
    first keyframe on its own map of then, by the weights of then; returns ``(joined map, bridge records)``
    (refused bridges among the records, their segments left apart)."""
    from mutualslam_cli.vo.source import FrontEndSource

    if not weights.frames:  # one segment, or no bridging: the front end alone
        return front_end_alone(seq, cfg, cache_dir)[0], []
    source = FrontEndSource(seq, cfg, cache_dir)
    twin = copy.deepcopy(net)
    load = keyframe_images(seq, lambda k: source.state.frame_of(k), cfg.net.width, cfg.net.height)
    records: list[Bridge] = []
    seen: set[int] = set()
    try:
        for frame, keyframes in source.timeline():
            for kf in keyframes:
                seg = source.state.segment(kf)
                first, known = not seen, seg in seen
                seen.add(seg)
                if first or known:
                    continue
                if frame not in weights.kept:
                    raise RuntimeError(f"credit bridges: no weights kept at frame {frame}, where the front end "
                                       "alone starts a segment (it differs from the run that chose the frames)")
                twin.load_state_dict(weights.kept[frame])
                snap = source.state.snapshot(seq.frames, covisibility=False)
                b = plan_bridge(snap, kf, depth_predictor(twin, load, fast), seq.load_gray, seq.intrinsics)
                if b is not None and not b.refused:
                    source.transform_segment(b.segment, b.sim3(), b.onto)
                if b is not None:
                    records.append(b)
        return source.result(), records
    finally:
        source.close()
