"""Relocalisation: a frame's pose in the existing map when frame-to-frame tracking has failed.

KLT follows features from one frame to the next with a motion prior; fast rotation, a dropped
frame and motion blur together (TUM fr1_desk: 5–10° between frames 64–68 ms apart, blurred)
break that chain. A keyframe does not need the previous frame: each keyframe keeps its grey
image, a thumbnail and its ORB features (:class:`RelocIndex`), and a lost frame is found against
them.

For a query frame:

1. **Candidates**: the newest keyframes of the map and the keyframes whose thumbnails correlate
   best with the frame's (zero-mean NCC), at most ``n_candidates``.
2. **Coarse warp**: ORB features of the frame matched to the candidate's (Hamming distance,
   Lowe's ratio test), a homography fitted to them by RANSAC: where the candidate's image content
   went, whatever the motion (ORB needs no motion prior).
3. **Matches**: the candidate's map points, predicted through that homography, refined by KLT from
   the candidate's image (forward–backward checked); PnP-RANSAC on them.
4. **Verification**, since a wrong relocalisation is worse than none: ``min_inliers`` inliers that are
   at least ``min_ratio`` of the matches; a pose from either random half of the *inliers* must place at
   least ``min_ratio`` of the other half within the threshold; and, because every match so far came from
   the candidate's own image (a look-alike place, or an image that does not belong to the points, fools
   all of the above consistently), *other* keyframes must confirm it: the keyframes of the candidate's
   segment whose points the pose puts most in view (at most ``neighbours``) must have ``min_verified``
   of them in view, and their own images must find at least ``min_ratio`` of those where the pose
   projects them (KLT, :func:`~mutualslam_cli.vo.reproject.reproject_points`). A pose no other keyframe
   can witness is refused.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from mutualslam_cli.geometry import to_normalized
from mutualslam_cli.map.store import Map
from mutualslam_cli.pixels import in_image
from mutualslam_cli.types import Intrinsics
from mutualslam_cli.vo.camera import distort_points, undistort_points
from mutualslam_cli.vo.features import orb_features, orb_matches
from mutualslam_cli.vo.keyframe_images import KeyframeImages
from mutualslam_cli.vo.reproject import reproject_points
from mutualslam_cli.vo.tracking import estimate_pose, klt_track, reprojection_errors

#: Thumbnail size (width, height) for the appearance ranking, pixels.
THUMB = (40, 30)
#: ORB features per image.
ORB_FEATURES = 1000
#: RANSAC threshold of the coarse homography, pixels (it only has to bring KLT near).
HOMOGRAPHY_PX = 8.0
#: Queries for an old place (a lost frame's second look, a loop, a merge) rank the best this many keyframes by thumbnail
#: again by their ORB matches with the frame (:attr:`RelocSettings.rerank`; ≈ 2 ms each). On RedKitchen's true
#: revisits the thumbnails alone ranked the right keyframes 9th to 12th where ORB ranked them first.
OLD_PLACE_RERANK = 16
#: KLT of the relocalisation: window, pyramid levels above the prediction, forward-backward bound (px).
KLT_WIN, KLT_LEVELS, KLT_FB_PX = 31, 2, 2.0


@dataclass(frozen=True)
class RelocSettings:
    """Thresholds of a relocalisation (module docstring)."""

    n_candidates: int = 4
    """Keyframes tried per query: the newest two, then the best thumbnail matches."""
    min_matches: int = 20
    """ORB matches, homography inliers and PnP inliers below which a candidate is dropped."""
    min_inliers: int = 40
    """Inliers needed to accept (ORB-SLAM asks 50 for its relocalisation)."""
    min_verified: int = 10
    """Points of other keyframes that must be in view under the pose (else it is not verifiable: refused)."""
    min_ratio: float = 0.5
    """Share of the matches that must be inliers, of each half of the inliers the other half's pose must
    place, and of the other keyframes' points in view that their images must find."""
    neighbours: int = 4
    """Other keyframes (same segment, most points in view under the pose) whose images verify it."""
    inlier_factor: float = 1.0
    """The PnP inlier threshold is the front end's RANSAC threshold times this. 1 for a frame just lost (the map
    it returns to was made seconds ago); a loop's old map has drifted since it was made, and its points miss a
    true revisit's own image by more (RedKitchen's true revisits: a median 2.1–2.9 px)."""
    witness_ratio: float | None = None
    """Share of the witnesses' points in view their images must find; ``None``: ``min_ratio``."""
    rerank: int = 0
    """The best ``rerank`` keyframes by thumbnail are ranked again by their ORB matches with the frame (0: the
    thumbnails' order). A 40×30 thumbnail ranks by overall brightness layout, which a viewpoint 15° away changes;
    ORB matches survive it (≈ 2 ms per keyframe)."""


@dataclass
class Relocalisation:
    """An accepted relocalisation.

    Attributes:
        T_cw: ``(4, 4)`` pose of the frame (world to camera, map units).
        pids: ``(M,)`` inlying map points; raw: ``(M, 2)`` float32 their raw pixels in the frame.
        keyframe: the candidate keyframe the pose came from.
        inliers: matches within the RANSAC threshold of the pose.
        candidates_tried: keyframes tried, this one included.
    """

    T_cw: np.ndarray
    pids: np.ndarray
    raw: np.ndarray
    keyframe: int
    inliers: int
    candidates_tried: int


#: What became of a candidate keyframe of a query (:attr:`RelocIndex.outcomes`; a record, no decision reads it).
PASSED, REFUTED, NO_MATCH = "passed", "refuted by verification", "no geometric match (ORB homography, KLT or PnP)"


def _thumb(gray: np.ndarray) -> np.ndarray:
    """Zero-mean, unit-norm thumbnail of a grey image (appearance vector)."""
    t = cv2.resize(gray, THUMB, interpolation=cv2.INTER_AREA).astype(np.float32).ravel()
    t -= t.mean()
    n = float(np.linalg.norm(t))
    return t / n if n > 0 else t


class HeldImages(Mapping[int, np.ndarray]):
    """Keyframe grey images by keyframe id, in the order added: held in memory, or — given ``load`` (keyframe id →
    its ``(H, W)`` uint8 grey image, decoded again from the sequence: the same pixels) — only their ids, each
    image decoded when asked through a small LRU (:class:`~mutualslam_cli.vo.local_map.KeyframeImages`), so a
    long sequence costs no memory per keyframe for them."""

    def __init__(self, load: Callable[[int], np.ndarray] | None = None) -> None:
        self._held: dict[int, np.ndarray | None] = {}
        self._lru = KeyframeImages(load) if load is not None else None

    def add(self, kf: int, gray: np.ndarray) -> None:
        self._held[kf] = gray if self._lru is None else None

    def __setitem__(self, kf: int, gray: np.ndarray) -> None:
        """Put another image under ``kf`` (held images only: a decoded one is the sequence's)."""
        if self._lru is not None:
            raise TypeError("keyframe images decoded from the sequence cannot be replaced")
        self._held[kf] = gray

    def __getitem__(self, kf: int) -> np.ndarray:
        if kf not in self._held:
            raise KeyError(kf)
        if self._lru is not None:
            return self._lru.get(kf)
        img = self._held[kf]
        assert img is not None  # without a loader every image is held
        return img

    def __iter__(self) -> Iterator[int]:
        return iter(self._held)

    def __len__(self) -> int:
        return len(self._held)

    def __contains__(self, kf: object) -> bool:
        return kf in self._held


class RelocIndex:
    """What relocalisation keeps per keyframe: the grey image (the source of KLT; with ``load``, decoded again when
    needed instead, :class:`HeldImages`), a thumbnail and ORB features (~0.35 MB per 640×480 keyframe with its
    image, ~0.03 MB without), and counters of its decisions."""

    def __init__(self, intr: Intrinsics, settings: RelocSettings | None = None,
                 load: Callable[[int], np.ndarray] | None = None) -> None:
        self.intr, self.K = intr, intr.K()
        self.settings = settings or RelocSettings()
        self.images = HeldImages(load)
        self.thumbs: dict[int, np.ndarray] = {}
        self.features: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # kf → (raw keypoints (N, 2), descriptors)
        self.rejected = 0  # candidate poses the verification refuted
        self.outcomes: dict[int, str] = {}  # the last query's candidates, in the order tried → PASSED | REFUTED …

    def add_keyframe(self, kf: int, gray: np.ndarray) -> None:
        """Record keyframe ``kf``'s grey image ``(H, W)`` uint8."""
        self.images.add(kf, gray)
        self.thumbs[kf] = _thumb(gray)
        self.features[kf] = orb_features(gray, ORB_FEATURES)

    def candidates(self, gray: np.ndarray, keyframes: list[int], newest: int = 2,
                   settings: RelocSettings | None = None,
                   feats: tuple[np.ndarray, np.ndarray] | None = None) -> list[int]:
        """The ``newest`` of ``keyframes`` (a lost frame is most likely near them), then the others by thumbnail
        similarity to ``gray`` (the best ``rerank`` of them by ORB matches with ``feats``, ``gray``'s features);
        at most ``n_candidates`` (of ``settings``, default the index's)."""
        s = settings or self.settings
        ks = [k for k in keyframes if k in self.thumbs]
        first = sorted(ks)[len(ks) - newest:][::-1] if newest else []
        t = _thumb(gray)
        rest = sorted((k for k in ks if k not in first), key=lambda k: -float(self.thumbs[k] @ t))
        if s.rerank:
            d = (feats if feats is not None else orb_features(gray, ORB_FEATURES))[1]
            n = {k: len(orb_matches(d, self.features[k][1])[0]) for k in rest[: s.rerank]}
            rest = sorted(n, key=lambda k: -n[k]) + rest[s.rerank:]  # stable: ties keep the thumbnails' order
        return (first + rest)[: s.n_candidates]

    def query(self, gray: np.ndarray, m: Map, thr: float, seed: int = 0,
              keyframes: list[int] | None = None, newest: int = 2,
              witnesses: list[int] | None = None, settings: RelocSettings | None = None) -> Relocalisation | None:
        """The pose of the grey frame ``gray`` in map ``m`` (``None``: no candidate passed).

        Args:
            thr: the front end's RANSAC threshold in normalised units (/ f); the inliers' is it ×
                ``settings.inlier_factor``.
            keyframes: keyframes that may serve (default: every keyframe of the index).
            newest: candidates taken by recency before the thumbnail ranking (0: by appearance only).
            witnesses: keyframes that may witness a candidate's pose (default: the candidate's segment). A loop gives
                the old side of the map: the keyframes made since the old visit carry the drift the loop corrects,
                so their points under a true loop pose are off by that drift and refute every true revisit.
            settings: thresholds of this query (default: the index's).
        """
        s = settings or self.settings
        feats = orb_features(gray, ORB_FEATURES)
        pool = sorted(self.images) if keyframes is None else keyframes
        thr = thr * s.inlier_factor
        self.outcomes = {}
        for tried, kf in enumerate(self.candidates(gray, pool, newest, s, feats), 1):
            rejected0 = self.rejected
            found = self._try(kf, m, gray, feats, thr, seed, s, witnesses)
            self.outcomes[kf] = PASSED if found is not None else REFUTED if self.rejected > rejected0 else NO_MATCH
            if found is not None:
                return dataclasses.replace(found, candidates_tried=tried)
        return None

    def _try(self, kf: int, m: Map, gray: np.ndarray, feats: tuple[np.ndarray, np.ndarray], thr: float,
             seed: int, s: RelocSettings, witnesses: list[int] | None = None) -> Relocalisation | None:
        H = self._homography(self.features[kf], feats, seed, s.min_matches)
        pids = np.array(sorted(m.kf_points[kf]), np.int64)
        if H is None or len(pids) < s.min_matches:
            return None
        src = distort_points(np.array([m.obs[p][kf] for p in pids]), self.intr).astype(np.float32)
        pred = cv2.perspectiveTransform(src[:, None, :], H)[:, 0, :].astype(np.float32)
        raw, ok = klt_track(self.images[kf], gray, src, KLT_WIN, KLT_LEVELS, KLT_FB_PX, pred=pred, retry=False)
        if ok.sum() < s.min_matches:
            return None
        pids, raw = pids[ok], raw[ok]
        xn = to_normalized(undistort_points(raw, self.intr), self.K)
        T, inl = estimate_pose(m.Xw[pids], xn, [m.T_cw(kf)], thr, seed=seed)
        if T is None or inl.sum() < s.min_matches:
            return None
        if not self._verified(T, kf, m, gray, pids, xn, thr, seed, s, witnesses):
            self.rejected += 1
            return None
        good = reprojection_errors(T, m.Xw[pids], xn) < thr
        return Relocalisation(T, pids[good], raw[good].astype(np.float32), kf, int(good.sum()), 0)

    def _verified(self, T: np.ndarray, kf: int, m: Map, gray: np.ndarray, pids: np.ndarray, xn: np.ndarray,
                  thr: float, seed: int, s: RelocSettings, witnesses: list[int] | None = None) -> bool:
        """The tests a relocalised pose ``T`` must pass (module docstring): enough inliers among the
        matches; a pose from either half of the inliers placing the other half; and other keyframes'
        images finding their points where ``T`` projects them — evidence the candidate's own image cannot
        give (every match came from it). Without such evidence the pose is refused."""
        Xw = m.Xw[pids]
        inl = reprojection_errors(T, Xw, xn) < thr
        if inl.sum() < s.min_inliers or inl.mean() < s.min_ratio:
            return False
        idx = np.random.default_rng(seed).permutation(np.flatnonzero(inl))
        halves = (idx[: len(idx) // 2], idx[len(idx) // 2:])
        for a, b in (halves, halves[::-1]):
            Ta = estimate_pose(Xw[a], xn[a], [m.T_cw(kf)], thr, seed=seed + 1)[0]
            if Ta is None or np.mean(reprojection_errors(Ta, Xw[b], xn[b]) < thr) < s.min_ratio:
                return False
        others = self._witnesses(T, kf, m, gray.shape, s, witnesses)
        if not others:
            return False
        cand = np.array(sorted(set().union(*(m.kf_points[k] for k in others))), np.int64)
        seen = self._in_view(T, m.Xw[cand], gray.shape).sum() if len(cand) else 0
        if seen < s.min_verified:
            return False
        found, _ = reproject_points(m, {k: self.images[k] for k in others}, gray, T, np.zeros(0, np.int64), others,
                                    self.intr, KLT_WIN, KLT_LEVELS, KLT_FB_PX, 2 * thr)
        return len(found) >= (s.min_ratio if s.witness_ratio is None else s.witness_ratio) * seen

    def _in_view(self, T: np.ndarray, Xw: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """``(N,)`` bool: world points ``Xw`` in front of ``T`` and inside the image, away from the border."""
        Xc = Xw @ T[:3, :3].T + T[:3, 3]
        px = Xc[:, :2] / np.maximum(Xc[:, 2:3], 1e-9) @ self.K[:2, :2].T + self.K[:2, 2]
        h, w = shape
        return (Xc[:, 2] > 0) & in_image(px, w, h, margin=KLT_WIN // 2)

    def _witnesses(self, T: np.ndarray, kf: int, m: Map, shape: tuple[int, int], s: RelocSettings,
                   pool: list[int] | None = None) -> list[int]:
        """Keyframes other than the candidate, with an image — of ``pool``, else of the candidate's segment — whose
        points ``T`` puts most in view: at most ``neighbours`` of them, each with ``min_verified`` points in view."""
        allowed = None if pool is None else set(pool)
        counts = []
        for k in self.images:
            if k == kf or not m.kf_points[k]:
                continue
            if (m.kf_segment[k] != m.kf_segment[kf]) if allowed is None else (k not in allowed):
                continue
            pts = np.fromiter(m.kf_points[k], np.int64, len(m.kf_points[k]))
            n = int(self._in_view(T, m.Xw[pts], shape).sum())
            if n >= s.min_verified:
                counts.append((-n, k))
        return [k for _, k in sorted(counts)[: s.neighbours]]

    def _homography(self, a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray],
                    seed: int, n: int) -> np.ndarray | None:
        """Raw-pixel homography from image ``a``'s ORB features to ``b``'s (``None``: fewer than ``n`` matches)."""
        (pa, da), (pb, db) = a, b
        if len(pa) < n or len(pb) < n:
            return None
        i, j = orb_matches(da, db)
        if len(i) < n:
            return None
        cv2.setRNGSeed(seed)  # OpenCV's RANSAC draws from its global RNG
        H, mask = cv2.findHomography(pa[i], pb[j], cv2.RANSAC, HOMOGRAPHY_PX, maxIters=500, confidence=0.995)
        return H if H is not None and int(mask.sum()) >= n else None
