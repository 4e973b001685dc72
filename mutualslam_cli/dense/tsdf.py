"""Dense reconstruction: TSDF fusion of depth maps, surface extraction, surface scores, rendering.

The library half of the dense stage (:mod:`~mutualslam_cli.stages.dense` is the run
integration). Everything here takes plain arrays in metres and returns plain arrays:

- :class:`TSDFVolume` fuses ``(H, W)`` depth maps (+ RGB) seen from ``T_wc`` poses into open3d's
  CPU voxel-block grid (``open3d.t.geometry.VoxelBlockGrid``; projective truncated signed
  distance, Curless & Levoy 1996, as KinectFusion, Newcombe et al. 2011) and extracts a
  triangle mesh by marching cubes. The legacy ``ScalableTSDFVolume`` is not used (broken in
  open3d 0.19+). The grid's hash map is allocated once with ``block_count`` blocks and never
  grows: a frame that would need more blocks is fused only into the blocks that exist, or
  skipped when even those do not fit (:attr:`TSDFVolume.frames` counts each case).
- :func:`score_surfaces`: accuracy, completeness, precision, recall and F-score between two
  surfaces (Knapitsch et al., "Tanks and Temples", SIGGRAPH 2017, §4: precision and recall at a
  distance threshold, F = harmonic mean), on voxel-downsampled mesh vertices.
- :func:`render_mesh`: a headless ray-cast picture of a mesh (``open3d.t.geometry.RaycastingScene``),
  Lambertian shading from the triangle normals.

Meshes are canonical (vertices sorted by position, triangles by their vertices), so the same inputs give the
same files and scores whatever open3d's threads do. open3d is imported inside the functions (~1 s).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mutualslam_cli.atomic import atomic_write_text, atomic_write_with
from mutualslam_cli.errors import DatasetError, GeometryError
from mutualslam_cli.metrics.alignment import align_positions
from mutualslam_cli.metrics.trajectory import associate_indices
from mutualslam_cli.types import Trajectory, check_shape

#: Distance (m) under which a point counts as right in precision / recall (the ``fscore_5cm`` keys).
FSCORE_THRESHOLD_M = 0.05
#: Bytes per voxel: tsdf, weight and RGB, all float32 (the dtypes open3d's TSDF kernels take with colour).
VOXEL_BYTES = 4 + 4 + 3 * 4
#: Albedo of the shaded meshes (and of frames fused without colour) and the background, RGB in [0, 1].
MESH_ALBEDO = (0.78, 0.80, 0.84)
BACKGROUND = (1.0, 1.0, 1.0)


def _open3d() -> Any:
    """``open3d``, imported on first use, untyped (why: :func:`mutualslam_cli.results.map_ply.open3d`)."""
    import open3d as o3d
    return o3d


def block_memory_bytes(block_resolution: int, block_count: int) -> int:
    """Bytes the voxel values of a grid of ``block_count`` blocks of ``block_resolution³`` voxels take
    (:data:`VOXEL_BYTES` per voxel; the hash map's keys and buckets add < 0.1 %)."""
    return int(block_count) * int(block_resolution) ** 3 * VOXEL_BYTES


@dataclass
class Mesh:
    """A triangle mesh in plain arrays.

    Attributes:
        vertices: ``(V, 3)`` float64 positions, metres.
        triangles: ``(F, 3)`` int64 vertex indices.
        colours: ``(V, 3)`` float64 RGB in [0, 1].
    """

    vertices: np.ndarray
    triangles: np.ndarray
    colours: np.ndarray

    @staticmethod
    def empty() -> Mesh:
        return Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros((0, 3)))

    def canonical(self) -> Mesh:
        """The same mesh with vertices sorted by (x, y, z) and triangles by their (rotated) indices."""
        if len(self.vertices) == 0:
            return self
        order = np.lexsort((self.vertices[:, 2], self.vertices[:, 1], self.vertices[:, 0]))
        new_index = np.empty(len(order), np.int64)
        new_index[order] = np.arange(len(order))
        tri = new_index[self.triangles]
        shift = np.argmin(tri, axis=1)  # rotate each triangle to start at its lowest index: orientation kept
        tri = np.take_along_axis(tri, (shift[:, None] + np.arange(3)[None]) % 3, axis=1)
        tri = tri[np.lexsort((tri[:, 2], tri[:, 1], tri[:, 0]))]
        return Mesh(self.vertices[order], tri, self.colours[order])


def _flip_to_positive_focal(depth: np.ndarray, rgb: np.ndarray | None,
                            K: np.ndarray) -> tuple[np.ndarray, np.ndarray | None, np.ndarray]:
    """Mirror the image so that ``fx, fy > 0`` (ICL-NUIM has ``fy < 0``): row ``v`` → ``H−1−v`` with
    ``fy' = −fy``, ``cy' = H−1−cy`` projects every 3-D point to the mirrored pixel (same for columns)."""
    K = K.copy()
    h, w = depth.shape
    if K[1, 1] < 0:
        depth, rgb = depth[::-1], None if rgb is None else rgb[::-1]
        K[1, 1], K[1, 2] = -K[1, 1], h - 1 - K[1, 2]
    if K[0, 0] < 0:
        depth, rgb = depth[:, ::-1], None if rgb is None else rgb[:, ::-1]
        K[0, 0], K[0, 2] = -K[0, 0], w - 1 - K[0, 2]
    return depth, rgb, K


class TSDFVolume:
    """A truncated signed distance volume on open3d's CPU voxel-block grid, of bounded size.

    Args:
        voxel_size: voxel edge, metres.
        trunc_voxels: truncation distance in voxels (``trunc_voxels · voxel_size`` metres).
        depth_min, depth_max: depth outside ``[depth_min, depth_max]`` (m) is not fused.
        block_resolution: voxels per block edge.
        block_count: blocks the hash map holds; allocated (and zeroed) at once, never exceeded
            (memory: :func:`block_memory_bytes`).

    Colour is always fused (open3d 0.20 cannot extract a mesh from a grid without it); frames
    given without RGB are fused in :data:`MESH_ALBEDO` grey.
    """

    def __init__(self, voxel_size: float, trunc_voxels: float, depth_min: float, depth_max: float,
                 block_resolution: int, block_count: int) -> None:
        o3d = _open3d()

        c = o3d.core
        self._o3d = o3d
        self.grid = o3d.t.geometry.VoxelBlockGrid(["tsdf", "weight", "color"], [c.float32, c.float32, c.float32],
                                                  [[1], [1], [3]], float(voxel_size), int(block_resolution),
                                                  int(block_count), c.Device("CPU:0"))
        self.voxel_size, self.trunc_voxels = float(voxel_size), float(trunc_voxels)
        self.depth_min, self.depth_max = float(depth_min), float(depth_max)
        self.capacity = int(block_count)
        #: frames fused into every block they touch, into existing blocks only (cap reached), or skipped.
        self.frames = {"full": 0, "existing_only": 0, "skipped": 0}

    @property
    def blocks(self) -> int:
        """Blocks allocated so far (≤ the ``block_count`` it was made with)."""
        return int(self.grid.hashmap().size())

    def integrate(self, depth: np.ndarray, K: np.ndarray, T_wc: np.ndarray, rgb: np.ndarray | None = None) -> str:
        """Fuse one depth map.

        Args:
            depth: ``(H, W)`` depth in metres (0, NaN or outside the depth range: not fused).
            K: ``(3, 3)`` pinhole intrinsics of ``depth`` (``fy`` may be negative).
            T_wc: ``(4, 4)`` camera-to-world pose, metres.
            rgb: ``(H, W, 3)`` uint8 colour registered with ``depth`` (None: grey).

        Returns:
            ``full``, ``existing_only`` (block cap reached: only blocks that exist were updated) or
            ``skipped`` (not even those fit, or no valid depth).
        """
        o3d, c = self._o3d, self._o3d.core
        depth = np.asarray(depth, np.float32)
        check_shape(depth, ["H", "W"], "TSDFVolume.integrate depth")
        check_shape(np.asarray(K), [3, 3], "TSDFVolume.integrate K")
        check_shape(np.asarray(T_wc), [4, 4], "TSDFVolume.integrate T_wc")
        if rgb is None:
            rgb = np.broadcast_to(np.round(np.asarray(MESH_ALBEDO) * 255).astype(np.uint8), (*depth.shape, 3))
        check_shape(rgb, [depth.shape[0], depth.shape[1], 3], "TSDFVolume.integrate rgb")
        depth = np.where(np.isfinite(depth) & (depth >= self.depth_min) & (depth <= self.depth_max), depth, 0.0)
        depth, rgb, K = _flip_to_positive_focal(depth.astype(np.float32), rgb, np.asarray(K, np.float64))
        if not np.any(depth > 0):
            self.frames["skipped"] += 1
            return "skipped"
        d_img = o3d.t.geometry.Image(c.Tensor(np.ascontiguousarray(depth)))
        K_t = c.Tensor(np.ascontiguousarray(K))
        E_t = c.Tensor(np.ascontiguousarray(np.linalg.inv(np.asarray(T_wc, np.float64))))  # world → camera
        coords = self.grid.compute_unique_block_coordinates(d_img, K_t, E_t, 1.0, self.depth_max, self.trunc_voxels)
        hm, kind = self.grid.hashmap(), "full"
        # open3d grows (rehashes) the map when size + len(coords) > capacity, even for coords it holds
        if hm.size() + coords.shape[0] > self.capacity:
            _, found = hm.find(coords)
            coords = c.Tensor(coords.numpy()[found.numpy().astype(bool)])
            kind = "existing_only"
            if coords.shape[0] == 0 or hm.size() + coords.shape[0] > self.capacity:
                self.frames["skipped"] += 1
                return "skipped"
        c_img = o3d.t.geometry.Image(c.Tensor(np.ascontiguousarray(rgb, dtype=np.float32) / np.float32(255.0)))
        self.grid.integrate(coords, d_img, c_img, K_t, K_t, E_t, 1.0, self.depth_max, self.trunc_voxels)
        self.frames[kind] += 1
        return kind

    def mesh(self, weight_threshold: float = 1.0) -> Mesh:
        """Marching-cubes mesh of the zero level set where every voxel has weight ≥ ``weight_threshold``
        (canonical order, :meth:`Mesh.canonical`; empty when nothing was fused)."""
        if self.blocks == 0:
            return Mesh.empty()
        # open3d keeps weight > threshold; every frame adds 1 to a voxel's weight, so ≥ w is > w − ½
        m = self.grid.extract_triangle_mesh(float(weight_threshold) - 0.5, -1)
        if "positions" not in m.vertex or len(m.vertex.positions) == 0:
            return Mesh.empty()
        v = m.vertex.positions.numpy().astype(np.float64)
        tri = m.triangle.indices.numpy().astype(np.int64) if "indices" in m.triangle else np.zeros((0, 3), np.int64)
        col = (np.clip(m.vertex.colors.numpy().astype(np.float64), 0, 1) if "colors" in m.vertex
               else np.full((len(v), 3), 0.7))
        return Mesh(v, tri, col).canonical()


# ----------------------------------------------------------------------------- poses in metres


def sim3_per_segment(gt: Trajectory, est: Trajectory, segments: np.ndarray,
                     max_dt: float) -> dict[int, tuple[np.ndarray, np.ndarray, float]]:
    """``{segment: (R (3, 3), t (3,), s)}`` aligning each segment's positions to GT (Umeyama, Sim(3));
    pairs associated by timestamp as the ATE does. Segments with < 3 pairs or degenerate positions, and poses of
    segment −1, are left out."""
    i_ref, i_est = associate_indices(gt.timestamps, est.timestamps, max_dt)
    out = {}
    for sid in np.unique(segments[i_est]) if len(i_est) else []:
        k = np.flatnonzero(segments[i_est] == sid)
        if sid < 0 or len(k) < 3:  # −1: not tracked
            continue
        try:
            _, T, R, s = align_positions(gt.positions[i_ref[k]], est.positions[i_est[k]], "sim3")
        except GeometryError:
            continue
        out[int(sid)] = (R, T[:3, 3].copy(), float(s))
    return out


def apply_sim3(T_wc: np.ndarray, R: np.ndarray, t: np.ndarray, s: float) -> np.ndarray:
    """``(4, 4)`` pose after the similarity ``x ↦ s·R·x + t``: rotation ``R·R_wc``, centre ``s·R·c + t``."""
    out = np.eye(4)
    out[:3, :3] = R @ T_wc[:3, :3]
    out[:3, 3] = s * R @ T_wc[:3, 3] + t
    return out


# ----------------------------------------------------------------------------- files


def write_mesh(path: Path, mesh: Mesh) -> None:
    """Binary PLY of ``mesh`` with vertex colours, written with open3d to a temporary name and renamed.
    An empty mesh is written as a header-only ASCII PLY (open3d refuses to write it)."""
    o3d = _open3d()

    path = Path(path)
    if len(mesh.vertices) == 0:
        atomic_write_text(path, "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
                          "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
        return
    m = o3d.t.geometry.TriangleMesh()
    m.vertex.positions = o3d.core.Tensor(mesh.vertices.astype(np.float32))
    m.vertex.colors = o3d.core.Tensor(mesh.colours.astype(np.float32))
    m.triangle.indices = o3d.core.Tensor(mesh.triangles.astype(np.int32))
    atomic_write_with(path, lambda name: o3d.t.io.write_triangle_mesh(name, m, write_ascii=False), "mesh (open3d)")


def read_mesh(path: Path) -> Mesh:
    """A mesh PLY (:func:`write_mesh`'s, or any open3d reads).

    Raises:
        DatasetError: the file is missing or open3d cannot read it.
    """
    o3d = _open3d()

    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: no such mesh file (expected a PLY written by the dense stage)")
    m = o3d.t.io.read_triangle_mesh(str(path))
    if "positions" not in m.vertex or len(m.vertex.positions) == 0:
        return Mesh.empty()
    v = m.vertex.positions.numpy().astype(np.float64)
    tri = m.triangle.indices.numpy().astype(np.int64) if "indices" in m.triangle else np.zeros((0, 3), np.int64)
    col = m.vertex.colors.numpy().astype(np.float64) if "colors" in m.vertex else np.full((len(v), 3), 0.7)
    return Mesh(v, tri, col / (255.0 if col.max(initial=0) > 1 else 1.0))


# ----------------------------------------------------------------------------- scores


def voxel_downsample(points: np.ndarray, voxel_size: float) -> np.ndarray:
    """``(N, 3)`` → ``(M, 3)``: the mean of the points in each occupied cell of a grid of ``voxel_size``
    (m), cells in sorted order (deterministic). Makes a surface's point density uniform, so scores
    weigh surface area, not vertex density. The cells are centred on multiples of ``voxel_size``:
    marching-cubes vertices lie on the TSDF's lattice lines (multiples of the voxel size), which
    cells bounded there would split at random by rounding (measured: 1630 instead of 2500 points
    per m² on a plane)."""
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        return points
    keys = np.floor(points / voxel_size + 0.5).astype(np.int64)
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    out = np.stack([np.bincount(inverse, weights=points[:, k], minlength=len(counts)) for k in range(3)], axis=1)
    return out / counts[:, None]


def nearest_distances(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """``(N,)`` distance (m) from each point of ``src`` ``(N, 3)`` to its nearest point of ``dst`` ``(M, 3)``
    (open3d's KD-tree, ``compute_point_cloud_distance``)."""
    o3d = _open3d()

    a = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(src, np.float64).reshape(-1, 3)))
    b = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(dst, np.float64).reshape(-1, 3)))
    return np.asarray(a.compute_point_cloud_distance(b), np.float64)


@dataclass(frozen=True)
class SurfaceScores:
    """Scores of a predicted surface against a reference one (metres; fractions in [0, 1]).

    ``accuracy_m``: mean distance prediction → reference; ``completeness_m``: mean reference →
    prediction (plain means, no cap; medians beside them); ``precision`` / ``recall``: share of
    prediction / reference points closer than ``threshold_m`` to the other surface;
    ``fscore = 2PR / (P + R)`` (0 when both are 0). ``n_pred``, ``n_ref``: points scored.
    """

    accuracy_m: float
    completeness_m: float
    accuracy_median_m: float
    completeness_median_m: float
    precision: float
    recall: float
    fscore: float
    threshold_m: float
    n_pred: int
    n_ref: int

    def as_dict(self) -> dict[str, float]:
        """The scores by name (metres, fractions, counts)."""
        return dict(vars(self))


def score_points(pred: np.ndarray, ref: np.ndarray, threshold: float = FSCORE_THRESHOLD_M) -> SurfaceScores:
    """Accuracy, completeness, precision, recall and F-score (Tanks and Temples) of point sets.

    Args:
        pred, ref: ``(N, 3)``, ``(M, 3)`` surface samples in metres (already downsampled).
        threshold: distance (m) below which a point counts in precision / recall.

    Raises:
        GeometryError: either set is empty.
    """
    pred, ref = np.asarray(pred, np.float64).reshape(-1, 3), np.asarray(ref, np.float64).reshape(-1, 3)
    if len(pred) == 0 or len(ref) == 0:
        raise GeometryError(f"surface scores need points on both surfaces (prediction {len(pred)}, "
                            f"reference {len(ref)})")
    d_pr = np.sort(nearest_distances(pred, ref))  # sorted: sums independent of point order
    d_rp = np.sort(nearest_distances(ref, pred))
    p, r = float(np.mean(d_pr < threshold)), float(np.mean(d_rp < threshold))
    f = 2 * p * r / (p + r) if p + r > 0 else 0.0  # Knapitsch et al. 2017, §4
    return SurfaceScores(float(np.mean(d_pr)), float(np.mean(d_rp)), float(np.median(d_pr)), float(np.median(d_rp)),
                         p, r, f, float(threshold), len(pred), len(ref))


def score_surfaces(pred: Mesh, ref: Mesh, voxel_size: float, threshold: float = FSCORE_THRESHOLD_M) -> SurfaceScores:
    """:func:`score_points` of both meshes' vertices, each voxel-downsampled to ``voxel_size``."""
    return score_points(voxel_downsample(pred.vertices, voxel_size), voxel_downsample(ref.vertices, voxel_size),
                        threshold)


# ----------------------------------------------------------------------------- pictures

def render_mesh(mesh: Mesh, eye: np.ndarray, target: np.ndarray, up: np.ndarray, width: int = 480,
                height: int = 360, fov_deg: float = 70.0, threads: int = 0) -> np.ndarray:
    """Ray-cast picture of ``mesh`` (``open3d.t.geometry.RaycastingScene``), no display needed.

    Shading: ``albedo · (0.25 + 0.5·|n·v| + 0.25·max(0, n·l))``, ``n`` the hit triangle's normal
    turned towards the viewer, ``v`` the direction to the eye, ``l`` a light from above the eye;
    background white.

    Args:
        eye, target, up: ``(3,)`` camera position, look-at point and the direction that is up in the
            picture (world, metres).
        width, height: image size, pixels; fov_deg: horizontal field of view.
        threads: ray-casting threads (0 = open3d's choice).

    Returns:
        ``(height, width, 3)`` uint8 RGB.
    """
    o3d = _open3d()

    img = np.tile(np.asarray(BACKGROUND), (height, width, 1))
    if len(mesh.triangles):
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.core.Tensor(mesh.vertices.astype(np.float32)),
                            o3d.core.Tensor(mesh.triangles.astype(np.uint32)))
        c = o3d.core
        # open3d 0.20's first image row looks along −up (measured: up (0, −1, 0) gives row 0 rays with y > 0),
        # a picture turned by 180°: given −up, the picture is upright
        rays = scene.create_rays_pinhole(float(fov_deg), c.Tensor(np.asarray(target, np.float32)),
                                         c.Tensor(np.asarray(eye, np.float32)), c.Tensor(-np.asarray(up, np.float32)),
                                         int(width), int(height))
        hit = scene.cast_rays(rays, nthreads=int(threads))
        t = hit["t_hit"].numpy()
        ok = np.isfinite(t)
        d = rays.numpy()[..., 3:].astype(np.float64)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        n = hit["primitive_normals"].numpy().astype(np.float64)
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
        facing = np.sum(n * -d, axis=-1)
        n = n * np.where(facing < 0, -1.0, 1.0)[..., None]  # both sides of the surface are lit
        fwd = (np.asarray(target) - np.asarray(eye)) / max(np.linalg.norm(np.asarray(target) - eye), 1e-9)
        light = np.asarray(up) - 0.5 * fwd
        light = light / np.linalg.norm(light)
        shade = 0.25 + 0.5 * np.abs(facing) + 0.25 * np.clip(n @ light, 0.0, None)
        img[ok] = np.asarray(MESH_ALBEDO) * np.clip(shade[ok], 0, 1)[:, None]
    return np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
