"""A run's ``dense.png`` (:func:`dense_picture`): the pre-trained, adapted and GT meshes ray-cast
from one viewpoint behind and above the cameras, side by side with their scores."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mutualslam_cli.atomic import atomic_path
from mutualslam_cli.dense import tsdf

#: Panel titles of ``dense.png``, left to right.
LABELS = {"pretrained": "pre-trained", "adapted": "adapted", "gt": "GT depth + GT poses"}
#: Horizontal field of view of the pictures, degrees.
FOV_DEG = 70.0


def dense_picture(path: Path, meshes: dict[str, tsdf.Mesh], poses_wc: np.ndarray,
                  scores: dict[str, dict[str, float | None]], heading: str, width: int = 480, threads: int = 0,
                  mirror: bool = False) -> None:
    """The meshes (keys of :data:`LABELS`) ray-cast from one viewpoint, side by side, as a PNG.

    Args:
        meshes: ``pretrained`` / ``adapted`` / ``gt`` meshes in one world frame (metres).
        poses_wc: ``(N, 4, 4)`` cameras the view is placed behind and above
            (:func:`look_from_cameras`), then moved so the GT mesh (else a
            prediction) fills the picture (:func:`fit_view`).
        scores: per mesh, ``fscore_5cm``, ``accuracy_m``, ``completeness_m`` (None: not scored).
        width: pixels per panel (height ¾ of it).
        mirror: the cameras have ``fy < 0`` (ICL-NUIM): their images' up is +y, a left-handed frame, so
            the reconstruction is the mirror image of the scene and a right-handed renderer shows it
            mirrored; the pictures are flipped left–right to show the scene as the frames do.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [n for n in LABELS if n in meshes]
    ref = next((meshes[n] for n in ("gt", "adapted", "pretrained") if n in meshes and len(meshes[n].vertices)), None)
    target = np.median(ref.vertices, axis=0) if ref is not None else poses_wc[:, :3, 3].mean(0) + poses_wc[0, :3, 2]
    h = width * 3 // 4
    eye, target, up = look_from_cameras(poses_wc, target, y_down=not mirror)
    if ref is not None:  # the reference fills the picture, centred
        eye, target = fit_view(ref.vertices, eye, target, up, FOV_DEG, h / width)
    gap, top = 8, 56  # pixels between panels, above them (titles)
    fig = plt.figure(figsize=((len(names) * (width + gap) - gap) / 100, (h + top) / 100), dpi=100)
    fig_w = len(names) * (width + gap) - gap
    for k, name in enumerate(names):
        ax = fig.add_axes(((k * (width + gap)) / fig_w, 0, width / fig_w, h / (h + top)))
        img = tsdf.render_mesh(meshes[name], eye, target, up, width, h, fov_deg=FOV_DEG, threads=threads)
        ax.imshow(img[:, ::-1] if mirror else img)
        s = scores.get(name, {})
        f, a, c = s.get("fscore_5cm"), s.get("accuracy_m"), s.get("completeness_m")
        sub = (f"F@5cm {f:.3f} · acc {a:.3f} m · comp {c:.3f} m" if None not in (f, a, c)
               else "reference" if name == "gt" else "no score (no reference)")
        ax.set_title(f"{LABELS[name]}\n{sub}", fontsize=9)
        ax.axis("off")
    fig.suptitle(heading, fontsize=10, y=1 - 4 / (h + top), va="top")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=100)
    plt.close(fig)


def look_from_cameras(poses_wc: np.ndarray, target: np.ndarray, pull_back: float = 0.6, lift: float = 0.35,
                      y_down: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A viewpoint behind and above a set of cameras, looking at ``target``.

    Args:
        poses_wc: ``(N, 4, 4)`` camera-to-world poses (camera z forward).
        target: ``(3,)`` the point to look at (e.g. the reference mesh's median vertex).
        pull_back, lift: eye offset along −forward and +up, as fractions of the mean camera's
            distance to ``target`` (at least 0.5 m).
        y_down: the cameras' y axis points down their images (``fy > 0``); ICL-NUIM's (``fy < 0``) points up.

    Returns:
        ``(eye, target, up)``, each ``(3,)``; ``up``: the cameras' mean up, orthogonal to their mean forward.
    """
    poses_wc = np.asarray(poses_wc, np.float64).reshape(-1, 4, 4)
    target = np.asarray(target, np.float64)
    centre = poses_wc[:, :3, 3].mean(axis=0)
    fwd = poses_wc[:, :3, 2].mean(axis=0)
    up = (-1.0 if y_down else 1.0) * poses_wc[:, :3, 1].mean(axis=0)
    fwd = fwd / max(np.linalg.norm(fwd), 1e-9)
    up = up - up.dot(fwd) * fwd
    up = up / max(np.linalg.norm(up), 1e-9)
    dist = max(float(np.linalg.norm(target - centre)), 0.5)
    return centre - pull_back * dist * fwd + lift * dist * up, target, up


def fit_view(points: np.ndarray, eye: np.ndarray, target: np.ndarray, up: np.ndarray, fov_deg: float = 70.0,
             aspect: float = 0.75, keep: float = 0.96, iterations: int = 40) -> tuple[np.ndarray, np.ndarray]:
    """Move a view sideways and along its line of sight until the central ``keep`` of ``points`` (per
    image axis) fills the picture, centred; the direction of view stays.

    Args:
        points: ``(N, 3)`` what to frame (e.g. the reference mesh's vertices; up to 20000 are used).
        eye, target, up: ``(3,)`` the view (:func:`look_from_cameras`).
        fov_deg, aspect: horizontal field of view and height / width of the picture.

    Returns:
        ``(eye, target)``, each ``(3,)``.
    """
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    pts = pts[:: max(1, len(pts) // 20000)]
    eye, target = np.asarray(eye, np.float64).copy(), np.asarray(target, np.float64).copy()
    if len(pts) < 10:
        return eye, target
    f = (target - eye) / max(np.linalg.norm(target - eye), 1e-9)
    r = np.cross(f, up)
    r /= max(np.linalg.norm(r), 1e-9)
    u = np.cross(r, f)
    lim = np.tan(np.radians(fov_deg) / 2) * np.array([1.0, aspect])  # tangent of the half-angles
    q = 50 * (1 - keep)
    for _ in range(iterations):
        rel = pts - eye
        z = rel @ f
        dist = float(np.linalg.norm(target - eye))
        if np.mean(z > 1e-3 * dist) < keep:  # too much behind the eye: back off
            eye -= 0.5 * dist * f
            continue
        front = z > 1e-3 * dist
        xy = np.stack([rel[front] @ r, rel[front] @ u], axis=1) / z[front, None]
        lo, hi = np.percentile(xy, [q, 100 - q], axis=0)
        centre, need = (lo + hi) / 2, float(np.max((hi - lo) / (2 * lim)))
        # half steps: the points lie at many depths, and full steps overshoot (the near ones move most)
        shift = 0.5 * (r * centre[0] + u * centre[1]) * float(np.median(z))
        eye, target = eye + shift, target + shift
        eye = target - f * dist * np.sqrt(need)  # the spread shrinks about as 1 / distance
        if abs(need - 1) < 0.01 and np.all(np.abs(centre) < 0.01 * lim):
            break
    return eye, target
