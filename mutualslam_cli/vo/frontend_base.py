"""The front end's state as its mixins see it, declared once for the type checker.

:class:`~mutualslam_cli.vo.frontend.FrontEnd` is put together from mixins (bootstrap, recovery, feedback, local
map, network) that read and write the state ``FrontEnd.__init__`` sets up and call each other's methods.
:class:`FrontEndBase`, the base of every mixin, declares those attributes and methods so that each mixin is
checked on its own. It holds annotations only: no attribute, no method and no behaviour at run time.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from mutualslam_cli.config import VOConfig
    from mutualslam_cli.datasets.sequence import Sequence
    from mutualslam_cli.map.journal import Journal
    from mutualslam_cli.map.state import MapState
    from mutualslam_cli.types import Intrinsics
    from mutualslam_cli.vo.keyframe_images import KeyframeImages
    from mutualslam_cli.vo.mapper import Mapper
    from mutualslam_cli.vo.relocalise import RelocIndex
    from mutualslam_cli.vo.scale_check import KeyframeRatio, ScaleCheck
    from mutualslam_cli.vo.state import TrackerState


class FrontEndBase:
    """What the front end's mixins rely on: the attributes set in ``FrontEnd.__init__`` and the methods one part
    calls in another (bodies in :class:`~mutualslam_cli.vo.frontend.FrontEnd` or the mixins)."""

    seq: Sequence
    cfg: VOConfig
    seed: int
    intr: Intrinsics
    K: np.ndarray
    f: float
    thr: float
    px_err_angle: float
    journal: Journal
    state_map: MapState
    mapper: Mapper
    reloc: RelocIndex | None
    st: TrackerState
    old_images: KeyframeImages
    scale: ScaleCheck | None

    if TYPE_CHECKING:  # declarations only: at run time the implementations are found on the mixins / FrontEnd
        def _undist(self, raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

        def _record(self, i: int) -> None: ...

        def _collect_ba(self) -> None: ...

        def _keyframe(self, i: int, gray: np.ndarray) -> None: ...

        def _new_seeds(self, kf: int, gray: np.ndarray, ratio: KeyframeRatio | None = None) -> None: ...

        def _start_ref(self, i: int, gray: np.ndarray) -> None: ...

        def _relocalise(self, i: int, gray: np.ndarray) -> bool: ...
