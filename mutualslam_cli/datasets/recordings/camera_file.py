"""Camera files for recordings without ``CameraInfo``: pinhole intrinsics and OpenCV distortion.

Accepted formats, told apart by their content:

- OpenCV calibration YAML or XML as ``cv2.FileStorage`` writes it (``%YAML:1.0``,
  ``camera_matrix: !!opencv-matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``;
  the keys ``K``/``D`` and ``cameraMatrix``/``distCoeffs`` work too).
- ROS ``camera_calibration`` YAML (``image_width``, ``image_height``, ``camera_matrix: {rows, cols, data}``,
  ``distortion_model``, ``distortion_coefficients: {rows, cols, data}``), and Kalibr ``camchain`` YAML
  (``cam0: {intrinsics: [fu, fv, pu, pv], distortion_coeffs, resolution}``).
- Plain text: one line ``fx fy cx cy`` or ``fx fy cx cy k1 k2 p1 p2 [k3]``, or a 3×3 camera matrix
  on three lines (``#`` comments allowed).

Distortion is OpenCV's radial-tangential ``(k1, k2, p1, p2, k3)``: four coefficients get ``k3 = 0``,
longer vectors (rational model) keep their first five; none or all zero give ``dist = None``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import TYPE_CHECKING, TypeAlias

import numpy as np

from mutualslam_cli.config.yaml_file import StrictLoader, is_refusal
from mutualslam_cli.errors import CameraFileError, DatasetError
from mutualslam_cli.types import Intrinsics, Scalar

if TYPE_CHECKING:
    import cv2

FileValue: TypeAlias = Scalar | np.ndarray | list["FileValue"] | dict[str, "FileValue"]
"""A value of a camera file as parsed, before it is checked: YAML's (JSON-like) or OpenCV FileStorage's (matrices as
``float64`` arrays)."""
FileMapping: TypeAlias = dict[str, FileValue]
"""A camera file's top-level mapping (or a Kalibr camera's), as parsed."""

EXPECTED = ("expected an OpenCV calibration YAML/XML (camera_matrix, distortion_coefficients), a ROS "
            "camera_calibration YAML, or a text line 'fx fy cx cy [k1 k2 p1 p2 [k3]]'")

_MATRIX_KEYS = ("camera_matrix", "K", "cameraMatrix", "camera_matrix_K", "intrinsic_matrix")
_DIST_KEYS = ("distortion_coefficients", "D", "distCoeffs", "dist_coeffs", "distortion_coeffs")
_WIDTH_KEYS = ("image_width", "width", "imageWidth")
_HEIGHT_KEYS = ("image_height", "height", "imageHeight")
_DIST_LENGTHS = (0, 4, 5, 8, 12, 14)  # the lengths cv2.undistort accepts
_RADTAN_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "radial-tangential", "pinhole", "")


def read_camera_file(path: Path) -> Intrinsics:
    """Read a camera file (see the module docstring for the formats).

    Args:
        path: the camera file.

    Returns:
        Intrinsics in pixels: ``fx, fy`` focal lengths, ``cx, cy`` principal point (origin at the
        centre of the top-left pixel, as OpenCV); ``width``/``height`` the image size the file gives,
        else 0; ``dist`` ``(k1, k2, p1, p2, k3)`` or ``None``.

    Raises:
        DatasetError: a missing or unreadable file, an unknown format, a camera matrix that is not
            3×3, a focal length ≤ 0 — one line naming the file, the accepted formats and the fault.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: camera file not found; {EXPECTED}")
    try:
        raw = path.read_bytes()
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise CameraFileError("not a text file") from None
        if not text.strip():
            raise CameraFileError("empty file")
        head = text.lstrip()
        if head.startswith("%YAML:") or "!!opencv-matrix" in text or head.startswith(("<?xml", "<opencv_storage")):
            return _from_mapping(_read_filestorage(path), "OpenCV")
        mapping = _yaml_mapping(text)
        if mapping is not None:
            return _from_mapping(mapping, "YAML")
        return _from_text(text)
    except CameraFileError as e:
        raise DatasetError(f"{path}: {e}; {EXPECTED}") from None


# --- OpenCV FileStorage -------------------------------------------------------------------------------------------

def _read_filestorage(path: Path) -> FileMapping:
    """The top level of a ``cv2.FileStorage`` file as plain Python (matrices as arrays)."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        msg = str(e.__cause__ or e).strip().splitlines()
        raise CameraFileError(f"OpenCV cannot parse it ({msg[-1] if msg else 'parse error'})") from None
    try:
        if not fs.isOpened():
            raise CameraFileError("OpenCV cannot open it")
        root = fs.root()
        return {k: _fs_value(fs.getNode(k)) for k in root.keys()}  # noqa: SIM118 (a cv2.FileNode: keys() is its API, `in` is not)
    finally:
        fs.release()


def _fs_value(node: cv2.FileNode) -> FileValue:
    if node.isMap():
        keys = node.keys()
        if "dt" in keys and "data" in keys:
            try:
                return np.asarray(node.mat(), dtype=np.float64)
            except Exception:  # a malformed matrix: read its parts below
                pass
        return {k: _fs_value(node.getNode(k)) for k in keys}
    if node.isSeq():
        return [_fs_value(node.at(i)) for i in range(node.size())]
    if node.isInt() or node.isReal():
        return node.real()
    if node.isString():
        return node.string()
    return None


# --- YAML mappings (ROS, Kalibr, OpenCV key names) ---------------------------------------------------------------

def _yaml_mapping(text: str) -> FileMapping | None:
    """The file as a YAML mapping, or ``None`` when it is not one (then it is read as plain text); read strictly
    (:class:`~mutualslam_cli.config.yaml_file.StrictLoader`): a key given twice or an alias bomb is refused."""
    import yaml

    try:
        data = yaml.load(text, Loader=StrictLoader)  # a SafeLoader
    except (yaml.YAMLError, RecursionError) as e:
        if is_refusal(e):
            raise CameraFileError(f"line {e.problem_mark.line + 1}: {e.problem}") from None
        return None
    return data if isinstance(data, dict) else None


def _first(mapping: FileMapping, keys: tuple[str, ...]) -> tuple[str, FileValue] | None:
    for k in keys:
        if k in mapping and mapping[k] is not None:
            return k, mapping[k]
    return None


def _numbers(name: str, value: FileValue) -> np.ndarray:
    """A matrix value (array, nested or flat list, or ``{rows, cols, data}``) as a 2-D float array; anything else
    raises :class:`CameraFileError`."""
    try:
        if isinstance(value, dict):
            if "data" not in value:
                raise CameraFileError(f"{name} has no 'data'")
            data = np.asarray(value["data"], dtype=np.float64).ravel()
            rows, cols = value.get("rows"), value.get("cols")
            if rows is None or cols is None:
                return data[None, :]
            n_rows, n_cols = _whole(rows), _whole(cols)
            if n_rows * n_cols != data.size:
                raise CameraFileError(f"{name} says {n_rows}×{n_cols} but holds {data.size} numbers")
            return data.reshape(n_rows, n_cols)
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraFileError(f"{name} is not a list of numbers") from None
    return arr.reshape(1, -1) if arr.ndim < 2 else arr


def _camera_matrix(name: str, value: FileValue) -> tuple[float, float, float, float]:
    K = _numbers(name, value)
    if K.size == 9 and K.shape[0] == 1:  # a flat list of 9 (ROS 'K: [...]')
        K = K.reshape(3, 3)
    if K.shape != (3, 3):
        raise CameraFileError(f"{name} is {'×'.join(str(s) for s in K.shape)}; expected 3×3")
    if not np.allclose([K[1, 0], K[2, 0], K[2, 1], K[2, 2]], [0, 0, 0, 1], atol=1e-9):
        raise CameraFileError(f"{name} is not a camera matrix (its lower part must be [0 fy cy; 0 0 1])")
    return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])


def _dist(name: str, value: FileValue) -> tuple[float, ...] | None:
    d = _numbers(name, value).ravel() if value is not None else np.zeros(0)
    if d.size not in _DIST_LENGTHS:
        raise CameraFileError(f"{name} has {d.size} coefficients; expected 4, 5, 8, 12 or 14 "
                              "(OpenCV k1 k2 p1 p2 [k3 ...])")
    if not np.all(np.isfinite(d)):
        raise CameraFileError(f"{name} holds a non-finite number")
    return _radtan(d)


def _radtan(d: np.ndarray) -> tuple[float, ...] | None:
    d5 = np.concatenate([d, np.zeros(1)]) if d.size == 4 else d[:5]
    return None if d5.size == 0 or not np.any(d5) else tuple(float(x) for x in d5)


def _whole(value: FileValue) -> int:
    """``int(value)`` of a scalar; ``TypeError`` for a list, a mapping or ``None`` (as ``int`` raises)."""
    if value is None or isinstance(value, (list, dict)):
        raise TypeError(f"not a number: {value!r}")
    return int(value)


def _size(mapping: FileMapping, keys: tuple[str, ...]) -> int:
    hit = _first(mapping, keys)
    if hit is None:
        return 0
    try:
        if hit[1] is None or isinstance(hit[1], (list, dict)):
            raise TypeError
        v = float(hit[1])
        if v < 0 or v != int(v):
            raise ValueError
    except (TypeError, ValueError):
        raise CameraFileError(f"{hit[0]} is {hit[1]!r}; expected a whole number of pixels") from None
    return int(v)


def _from_mapping(mapping: FileMapping, kind: str) -> Intrinsics:
    cams = [v for k, v in mapping.items() if re.fullmatch(r"cam\d+", str(k)) and isinstance(v, dict)]
    if _first(mapping, _MATRIX_KEYS) is None and cams:  # Kalibr camchain: the first camera
        return _from_kalibr(cams[0])
    if _first(mapping, _MATRIX_KEYS) is None and "intrinsics" in mapping:
        return _from_kalibr(mapping)
    hit = _first(mapping, _MATRIX_KEYS)
    if hit is None:
        raise CameraFileError(f"{kind} file without camera_matrix (or K / cameraMatrix)")
    fx, fy, cx, cy = _camera_matrix(*hit)
    model = str(mapping.get("distortion_model", "") or "").strip().lower()
    if model not in _RADTAN_MODELS:
        raise CameraFileError(f"distortion_model '{model}' is not supported; expected plumb_bob or rational_polynomial")
    dhit = _first(mapping, _DIST_KEYS)
    dist = _dist(*dhit) if dhit is not None else None
    return _checked(fx, fy, cx, cy, _size(mapping, _WIDTH_KEYS), _size(mapping, _HEIGHT_KEYS), dist)


def _from_kalibr(cam: FileMapping) -> Intrinsics:
    model = str(cam.get("camera_model", "pinhole")).lower()
    dmodel = str(cam.get("distortion_model", "radtan")).lower()
    if model != "pinhole" or dmodel not in _RADTAN_MODELS:
        raise CameraFileError(f"Kalibr model {model}-{dmodel} is not supported; expected pinhole-radtan")
    v = _numbers("intrinsics", cam.get("intrinsics")).ravel()
    if v.size != 4:
        raise CameraFileError(f"intrinsics has {v.size} numbers; expected 4 (fu fv pu pv)")
    dist = _dist("distortion_coeffs", cam["distortion_coeffs"]) if cam.get("distortion_coeffs") is not None else None
    res = _numbers("resolution", cam["resolution"]).ravel() if cam.get("resolution") is not None else np.zeros(2)
    if res.size != 2 or np.any(res < 0) or np.any(res != np.round(res)):
        raise CameraFileError("resolution must be [width, height] in whole pixels")
    fx, fy, cx, cy = (float(x) for x in v)  # 4 numbers, checked above
    return _checked(fx, fy, cx, cy, int(res[0]), int(res[1]), dist)


# --- plain text ---------------------------------------------------------------------------------------------------

def _from_text(text: str) -> Intrinsics:
    rows: list[list[float]] = []
    for k, raw in enumerate(text.splitlines(), start=1):
        s = raw.split("#", 1)[0].replace(",", " ").strip()
        if not s:
            continue
        try:
            rows.append([float(x) for x in s.split()])
        except ValueError:
            raise CameraFileError(f"line {k} is {s[:40]!r}, not numbers") from None
    if len(rows) == 3 and all(len(r) == 3 for r in rows):  # a 3×3 camera matrix
        return _checked(*_camera_matrix("the camera matrix", np.asarray(rows, dtype=np.float64)), 0, 0, None)
    if len(rows) != 1:
        raise CameraFileError(f"{len(rows)} lines of numbers; expected one line")
    v = rows[0]
    if len(v) not in (4, 8, 9):
        raise CameraFileError(f"{len(v)} numbers; expected 4 (fx fy cx cy), 8 or 9 (with k1 k2 p1 p2 [k3])")
    dist = _radtan(np.asarray(v[4:], dtype=np.float64)) if len(v) > 4 else None
    return _checked(v[0], v[1], v[2], v[3], 0, 0, dist)


def _checked(fx: float, fy: float, cx: float, cy: float, width: int, height: int,
             dist: tuple[float, ...] | None) -> Intrinsics:
    for name, v in (("fx", fx), ("fy", fy), ("cx", cx), ("cy", cy)):
        if not math.isfinite(v):
            raise CameraFileError(f"{name} is {v}; expected a finite number")
    if fx <= 0 or fy <= 0:
        raise CameraFileError(f"{'fx' if fx <= 0 else 'fy'} is {fx if fx <= 0 else fy:g}; fx and fy must be > 0")
    if (width == 0) != (height == 0):
        raise CameraFileError(f"image size {width}×{height}: give both width and height, or neither")
    return Intrinsics(float(fx), float(fy), float(cx), float(cy), int(width), int(height), dist)
