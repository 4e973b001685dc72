"""``luo``: Luo et al.'s SLAM-based online adaptation strategy on our front end (a baseline).

Luo et al., "Real-time dense monocular SLAM with online adapted depth prediction network", IEEE
Trans. Multimedia 2019 (the paper's ``depthonlineadapt``). This scheme takes from it only what
the paper states in §IV-B "SLAM-based online adaptation":

- it fine-tunes on the most *recent* keyframes only: no replay, no regulariser;
- it trains on keyframe pairs with a dominant horizontal motion, used as simulated static
  stereo pairs.

Everything else is ours, as for every scheme: the front end, L_train (Eq. 7: the photometric
term of Eq. 3–5 with the per-pixel minimum over the sources, L_sparse, L_smooth), the Adam steps,
and Algorithm 1 (validation keyframes, early stopping, the global-BA trigger) unchanged.

**Pair rule** (:func:`stereo_measures`, :func:`is_stereo_pair`; constants in
:class:`~mutualslam_cli.config.AdaptConfig`): target keyframe i and keyframe j form a simulated
stereo pair when, with ``T = T_wc(i)⁻¹ · T_wc(j)`` (j's camera in i's camera frame; x along the
image rows), ``t = T[:3, 3]`` and ``R = T[:3, :3]``::

    ‖t‖ > 0,   |t_x| / ‖t‖ ≥ luo_min_horizontal_ratio (0.8),
    angle(R) = arccos((tr R − 1) / 2) ≤ luo_max_rotation_deg (5°).

**Batch.** The targets are those of ``recent`` (the two most recent training keyframes); the
photometric sources of each are its partners among the ``luo_window`` (3) most recent training
keyframes whose image is stored, nearest in arrival order first (the target is never its own
partner; validation keyframes never are partners, as they are never sources). A target without
a partner is left out: there is no fallback to its temporal neighbour (that would be ``recent``).
When neither target has a partner the keyframe trains nothing (``StepInfo.trained`` is false)
and Algorithm 1 goes on as for any keyframe that trains nothing. The arriving keyframe's
partners are ``StepInfo.sources`` (the ``sources`` column of ``keyframes.csv``), so a run shows
which keyframes found one.

Poses are the buffer's current ones, so after a global BA the pairs are judged on the refined
poses. With ``replay_capacity > 0`` the buffer only guarantees the two most recent training
images; a partner must be stored.
"""

from __future__ import annotations

import math

import numpy as np

from mutualslam_cli.adapt.buffer import KeyframeBuffer
from mutualslam_cli.adapt.schemes.recent import Recent
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.config.checks import check_config
from mutualslam_cli.types import check_shape


def stereo_measures(T_wc_target: np.ndarray, T_wc_other: np.ndarray) -> tuple[float, float]:
    """How stereo-like the pair (target, other) is.

    Args:
        T_wc_target: ``(4, 4)`` camera-to-world pose of the target keyframe.
        T_wc_other: ``(4, 4)`` camera-to-world pose of the other keyframe (same map units).

    Returns:
        ``(ratio, rot_deg)``: ``|t_x| / ‖t‖`` of the other camera's centre ``t`` in the target's
        camera frame (NaN for ``‖t‖ = 0``: no baseline, no stereo), and the relative rotation
        angle in degrees, in [0, 180].

    Raises:
        ShapeError: a pose is not 4×4.
    """
    Tt = np.asarray(T_wc_target, dtype=np.float64)
    To = np.asarray(T_wc_other, dtype=np.float64)
    check_shape(Tt, [4, 4], "stereo_measures: T_wc_target")
    check_shape(To, [4, 4], "stereo_measures: T_wc_other")
    R_t = Tt[:3, :3]
    t = R_t.T @ (To[:3, 3] - Tt[:3, 3])  # other's centre in the target camera frame
    R = R_t.T @ To[:3, :3]  # other's orientation in the target camera frame
    norm = float(np.linalg.norm(t))
    ratio = abs(float(t[0])) / norm if norm > 0 else math.nan
    cos = (float(np.trace(R)) - 1.0) / 2.0
    return ratio, math.degrees(math.acos(min(1.0, max(-1.0, cos))))


def is_stereo_pair(T_wc_target: np.ndarray, T_wc_other: np.ndarray, min_horizontal_ratio: float = 0.8,
                   max_rotation_deg: float = 5.0) -> bool:
    """The pair rule of the module docstring: dominant horizontal translation, little rotation.

    Args:
        T_wc_target, T_wc_other: ``(4, 4)`` camera-to-world poses.
        min_horizontal_ratio: least ``|t_x| / ‖t‖`` (``AdaptConfig.luo_min_horizontal_ratio``).
        max_rotation_deg: largest relative rotation, degrees (``AdaptConfig.luo_max_rotation_deg``).

    Returns:
        True when the pair qualifies; never for a zero baseline.
    """
    ratio, rot = stereo_measures(T_wc_target, T_wc_other)
    return ratio >= min_horizontal_ratio and rot <= max_rotation_deg  # False for a NaN ratio


class Luo(Recent):
    """``luo``: the ``recent`` targets, each with its simulated stereo partners as sources.

    Args:
        cfg: supplies ``luo_window``, ``luo_min_horizontal_ratio`` and ``luo_max_rotation_deg``
            (default: :class:`AdaptConfig`'s defaults).

    Raises:
        ConfigError: a setting of ``cfg`` out of its range (window < 2, ratio outside [0, 1], rotation outside
            [0, 180], ...).
    """

    name = "luo"
    regularizer = None

    def __init__(self, cfg: AdaptConfig | None = None) -> None:
        super().__init__(cfg)
        check_config(self.cfg, "adapt")  # luo_window ≥ 2, the ratio in [0, 1], the rotation in [0, 180]

    def select(self, buffer: KeyframeBuffer, newest: int, rng: np.random.Generator) -> list[int]:
        """The ``recent`` targets that have at least one stereo partner (newest first; may be empty)."""
        return [k for k in super().select(buffer, newest, rng) if self.sources(buffer, k)]

    def sources(self, buffer: KeyframeBuffer, target: int) -> list[int]:
        """Stored stereo partners of ``target`` among the ``luo_window`` most recent training keyframes.

        Nearest in arrival order first (ties: the newer first). Empty when ``target`` is not
        stored or no candidate qualifies.
        """
        if target not in buffer:
            return []
        c = self.cfg
        window = buffer.recent(c.luo_window)  # newest first
        if target not in window:
            return []
        pos = window.index(target)
        T = buffer.pose(target)
        seg = buffer.segment(target)  # a pose across a re-initialisation was not measured
        cands = sorted((k for k in window if k != target and k in buffer and buffer.segment(k) == seg),
                       key=lambda k: (abs(window.index(k) - pos), window.index(k)))
        return [k for k in cands
                if is_stereo_pair(T, buffer.pose(k), c.luo_min_horizontal_ratio, c.luo_max_rotation_deg)]
