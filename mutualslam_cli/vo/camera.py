"""Camera model of the front end: pinhole K plus optional radial-tangential distortion.

The front end tracks in the raw (possibly distorted) image and immediately maps every
tracked pixel to undistorted pixels of the pinhole camera with the same ``fx, fy, cx, cy``
(OpenCV's ``k1 k2 p1 p2 k3`` model, as TUM fr1 publishes it). Everything downstream —
poses, map points, ``VOResult`` pixels — refers to that pinhole camera. ``fy`` may be
negative (ICL-NUIM); all maths goes through ``K`` and its inverse, never assumes ``fy > 0``.
"""

from __future__ import annotations

import cv2
import numpy as np

from mutualslam_cli.types import Intrinsics


def undistort_points(pix: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Raw pixels ``(N, 2)`` → undistorted pinhole pixels ``(N, 2)`` (same K).

    A no-op copy when ``intr.dist`` is ``None``.
    """
    pix = np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    if intr.dist is None or len(pix) == 0:
        return pix.copy()
    K = intr.K()
    out = cv2.undistortPoints(pix.reshape(-1, 1, 2), K, np.asarray(intr.dist, np.float64), P=K)
    return out.reshape(-1, 2)


def distort_points(pix: np.ndarray, intr: Intrinsics) -> np.ndarray:
    """Undistorted pinhole pixels ``(N, 2)`` → raw (distorted) pixels ``(N, 2)``.

    Forward OpenCV radial-tangential model on normalised coordinates (Brown–Conrady):
    ``x' = x·(1 + k1 r² + k2 r⁴ + k3 r⁶) + 2 p1 x y + p2 (r² + 2x²)``, likewise for ``y``.
    Used to look GT depth up in the distorted depth images of TUM fr1.
    """
    pix = np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    if intr.dist is None or len(pix) == 0:
        return pix.copy()
    k1, k2, p1, p2, k3 = (list(intr.dist) + [0.0] * 5)[:5]
    x = (pix[:, 0] - intr.cx) / intr.fx
    y = (pix[:, 1] - intr.cy) / intr.fy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2 + k3 * r2 ** 3
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return np.stack([xd * intr.fx + intr.cx, yd * intr.fy + intr.cy], axis=1)


def focal_px(intr: Intrinsics) -> float:
    """Mean absolute focal length in pixels (converts pixel thresholds to normalised units)."""
    return 0.5 * (abs(intr.fx) + abs(intr.fy))


class Undistorter:
    """Resamples raw frames of a distorted camera into its pinhole camera (:func:`pinhole`, same K).

    Training keyframes, evaluation frames and their GT depth all go through one of these, so the
    network is trained and scored in one image geometry (TUM fr1's radial distortion is strong).
    Colour is resampled bilinearly (as ``cv2.undistort``); depth by the nearest raw pixel, so no
    depth is invented across an edge. Pixels with no raw source are 0 (= missing depth).
    Without distortion both methods return their input unchanged.

    Args:
        intr: the raw camera (``dist`` may be ``None``).
    """

    def __init__(self, intr: Intrinsics) -> None:
        self.intr = intr
        self.active = intr.dist is not None
        self._maps: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}

    def _map(self, h: int, w: int, kind: int) -> tuple[np.ndarray, np.ndarray]:
        """Remap tables for an image of ``h × w`` (the camera scaled to it when it differs)."""
        key = (h, w, kind)
        if key not in self._maps:
            intr = self.intr if (w, h) == (self.intr.width, self.intr.height) else self.intr.scaled(w, h)
            K = intr.K()
            self._maps[key] = cv2.initUndistortRectifyMap(K, np.asarray(self.intr.dist, np.float64), None, K,
                                                          (w, h), kind)
        return self._maps[key]

    def image(self, rgb: np.ndarray) -> np.ndarray:
        """``(H, W, 3)`` uint8 raw → ``(H, W, 3)`` uint8 pinhole (bilinear)."""
        if not self.active:
            return rgb
        h, w = rgb.shape[:2]
        maps = self._map(h, w, cv2.CV_16SC2)  # the tables cv2.undistort uses
        return cv2.remap(rgb, *maps, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """``(H, W)`` float depth (m, 0 = missing) raw → pinhole (nearest raw pixel)."""
        if not self.active:
            return depth
        h, w = depth.shape[:2]
        maps = self._map(h, w, cv2.CV_32FC1)  # float tables: the exact nearest pixel
        return cv2.remap(depth, *maps, interpolation=cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT)
