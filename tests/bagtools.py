"""Test helper: write a ROS 1 / ROS 2 bag from a TUM-layout folder (synthetic or real) with rosbags' writers.

::

    from bagtools import write_bag_from_tum
    info = write_bag_from_tum(folder, tmp / "seq.bag", ros_version=1, depth="32FC1")
    open_recording(info["bag"], RecordingOptions(rgb_topic=info["rgb"], depth_topic=info["depth"], ...))

Messages carry the TUM timestamps as ``header.stamp`` (parsed from the text, exact to the nanosecond);
the bag's record times lag them by ``record_delay_ns`` so that a reader using record times is caught.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from mutualslam_cli.datasets.tum import read_intrinsics_txt
from mutualslam_cli.types import Intrinsics

RGB_RAW = "/camera/rgb/image_color"
RGB_COMPRESSED = "/camera/rgb/image_color/compressed"
DEPTH_RAW = "/camera/depth/image"
DEPTH_COMPRESSED = "/camera/depth/image/compressedDepth"
CAMERA_INFO = "/camera/rgb/camera_info"
POSE = "/camera/pose"
POSE_TYPES = {"pose": "geometry_msgs/msg/PoseStamped", "transform": "geometry_msgs/msg/TransformStamped",
              "odometry": "nav_msgs/msg/Odometry"}


def parse_stamp(text: str) -> tuple[int, int]:
    """``"1305031105.175159"`` → ``(sec, nanosec)``, exactly (no float arithmetic)."""
    whole, _, frac = text.strip().partition(".")
    return int(whole), int((frac + "000000000")[:9])


def _entries(path: Path) -> list[tuple[str, str]]:
    """``(timestamp text, file)`` of a TUM list/trajectory file, in file order."""
    out = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.strip() and not line.startswith("#"):
            f = line.split()
            out.append((f[0], " ".join(f[1:])))
    return out


def encode_jpeg(path: Path, quality: int = 90) -> bytes:
    """The JPEG bytes the helper stores for a colour file (the file itself when it is a JPEG)."""
    if path.suffix.lower() in (".jpg", ".jpeg"):
        return path.read_bytes()
    ok, buf = cv2.imencode(".jpg", cv2.imread(str(path), cv2.IMREAD_COLOR), [cv2.IMWRITE_JPEG_QUALITY, quality])
    assert ok
    return buf.tobytes()


def compressed_depth_bytes(mm: np.ndarray) -> bytes:
    """``16UC1; compressedDepth`` payload: compressed_depth_image_transport's 12-byte header + a 16-bit PNG."""
    ok, png = cv2.imencode(".png", mm)
    assert ok
    return np.array([0], "<i4").tobytes() + np.array([0.0, 0.0], "<f4").tobytes() + png.tobytes()


class _Msgs:
    """Builds messages of one ROS version from a typestore (ROS 1 headers carry ``seq``; field case differs)."""

    def __init__(self, ros_version: int):
        from rosbags.typesys import Stores, get_typestore

        self.ros1 = ros_version == 1
        self.ts = get_typestore(Stores.ROS1_NOETIC if self.ros1 else Stores.ROS2_HUMBLE)

    def make(self, msgtype: str, **kw: Any) -> Any:
        cls = self.ts.types[msgtype]
        names = {f.name for f in dataclasses.fields(cls)}
        return cls(**{k: v for k, v in kw.items() if k in names})

    def header(self, stamp: tuple[int, int], seq: int = 0, frame: str = "camera") -> Any:
        t = self.make("builtin_interfaces/msg/Time", sec=stamp[0], nanosec=stamp[1])
        return self.make("std_msgs/msg/Header", seq=seq, stamp=t, frame_id=frame)

    def serialize(self, msg: Any, msgtype: str) -> bytes:
        return bytes(self.ts.serialize_ros1(msg, msgtype) if self.ros1 else self.ts.serialize_cdr(msg, msgtype))

    def image(self, hdr: Any, arr: np.ndarray, encoding: str, pad: int = 0, bigendian: bool = False) -> Any:
        h, w = arr.shape[:2]
        a = arr.astype(arr.dtype.newbyteorder(">" if bigendian else "<"))
        rows = a.reshape(h, -1).view(np.uint8)
        data = np.concatenate([rows, np.full((h, pad), 0xAB, np.uint8)], axis=1).reshape(-1)
        return self.make("sensor_msgs/msg/Image", header=hdr, height=h, width=w, encoding=encoding,
                         is_bigendian=int(bigendian), step=rows.shape[1] + pad, data=np.ascontiguousarray(data))

    def compressed(self, hdr: Any, data: bytes, fmt: str) -> Any:
        return self.make("sensor_msgs/msg/CompressedImage", header=hdr, format=fmt,
                         data=np.frombuffer(data, np.uint8).copy())

    def camera_info(self, hdr: Any, k: Intrinsics, dist: tuple[float, ...] | None, model: str) -> Any:
        K = np.array([k.fx, 0, k.cx, 0, k.fy, k.cy, 0, 0, 1], np.float64)
        P = np.array([k.fx, 0, k.cx, 0, 0, k.fy, k.cy, 0, 0, 0, 1, 0], np.float64)
        D = np.array(dist if dist is not None else [0.0] * 5, np.float64)
        roi = self.make("sensor_msgs/msg/RegionOfInterest", x_offset=0, y_offset=0, height=0, width=0,
                        do_rectify=False)
        arrays = {"D": D, "K": K, "R": np.eye(3).reshape(-1), "P": P}
        arrays = arrays if self.ros1 else {n.lower(): v for n, v in arrays.items()}
        return self.make("sensor_msgs/msg/CameraInfo", header=hdr, height=k.height, width=k.width,
                         distortion_model=model, binning_x=0, binning_y=0, roi=roi, **arrays)

    def pose(self, hdr: Any, kind: str, v: list[float]) -> Any:
        point = self.make("geometry_msgs/msg/Point", x=v[0], y=v[1], z=v[2])
        vec = self.make("geometry_msgs/msg/Vector3", x=v[0], y=v[1], z=v[2])
        quat = self.make("geometry_msgs/msg/Quaternion", x=v[3], y=v[4], z=v[5], w=v[6])
        pose = self.make("geometry_msgs/msg/Pose", position=point, orientation=quat)
        if kind == "pose":
            return self.make(POSE_TYPES[kind], header=hdr, pose=pose)
        if kind == "transform":
            tf = self.make("geometry_msgs/msg/Transform", translation=vec, rotation=quat)
            return self.make(POSE_TYPES[kind], header=hdr, child_frame_id="camera", transform=tf)
        cov = self.make("geometry_msgs/msg/PoseWithCovariance", pose=pose, covariance=np.zeros(36))
        zero = self.make("geometry_msgs/msg/Vector3", x=0.0, y=0.0, z=0.0)
        twist = self.make("geometry_msgs/msg/TwistWithCovariance", covariance=np.zeros(36),
                          twist=self.make("geometry_msgs/msg/Twist", linear=zero, angular=zero))
        return self.make(POSE_TYPES[kind], header=hdr, child_frame_id="camera", pose=cov, twist=twist)


def _colour(path: Path, encoding: str) -> np.ndarray:
    """The colour file as pixels of a raw ``Image`` encoding (unknown encodings: RGB bytes as they are)."""
    rgb = cv2.cvtColor(cv2.imread(str(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
    conv = {"bgr8": rgb[..., ::-1], "rgba8": np.dstack([rgb, np.full(rgb.shape[:2], 255, np.uint8)]),
            "mono8": cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)}
    conv["bgra8"] = conv["rgba8"][..., [2, 1, 0, 3]]
    return np.ascontiguousarray(conv.get(encoding, rgb))


def write_bag_from_tum(folder: Path, bag_path: Path, ros_version: int = 1, rgb: str = "raw",
                       depth: str | None = "16UC1", camera_info: bool = True, dist: tuple[float, ...] | None = None,
                       pose_topic: bool | str = True, *, intrinsics: Intrinsics | None = None,
                       rgb_encoding: str = "rgb8", pad: int = 0, bigendian: bool = False, depth_scale: float = 5000.0,
                       dist_model: str = "plumb_bob", max_frames: int = 0, storage: str = "sqlite3",
                       record_delay_ns: int = 12_345_678) -> dict[str, Any]:
    """Write the folder's frames (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``) as a bag.

    Args:
        folder: a TUM-layout folder (depth PNGs at ``depth_scale`` units per metre).
        bag_path: a ``.bag`` file (ROS 1) or a folder to create (ROS 2).
        rgb: ``raw`` (``Image`` with ``rgb_encoding``), ``jpeg`` or ``png`` (``CompressedImage``; PNG files as
            they are).
        depth: ``16UC1`` (millimetres, rounded), ``32FC1`` (metres, float32; 0 → NaN), ``compressedDepth``
            (``16UC1; compressedDepth``: millimetres in a PNG after a 12-byte header) or ``None``.
        camera_info: publish ``CameraInfo`` (K from ``intrinsics`` or ``intrinsics.txt``) with each colour frame.
        dist: ``(k1, k2, p1, p2, k3)`` in ``CameraInfo.D`` (model ``dist_model``), or zeros.
        pose_topic: publish ``groundtruth.txt`` as ``PoseStamped`` (``True``/``"pose"``), ``"transform"``
            (``TransformStamped``) or ``"odometry"`` (``Odometry``).
        pad, bigendian: extra bytes per row (``step``) and byte order of raw images.
        max_frames: the first this many colour/depth entries (0 = all); GT limited to their time span ±1 s.
        storage: ROS 2 storage plugin, ``sqlite3`` or ``mcap``.

    Returns:
        ``{"bag": path, "rgb": topic, "depth": topic or None, "camera_info": topic or None, "pose": topic or None,
        "frames": colour frames written}``.
    """
    folder, bag_path = Path(folder), Path(bag_path)
    m = _Msgs(ros_version)
    rgb_l = _entries(folder / "rgb.txt")
    dep_l = _entries(folder / "depth.txt") if depth is not None else []
    if max_frames:
        rgb_l, dep_l = rgb_l[:max_frames], dep_l[:max_frames]
    gt_l = _entries(folder / "groundtruth.txt") if pose_topic and (folder / "groundtruth.txt").is_file() else []
    if gt_l and max_frames:
        lo, hi = float(rgb_l[0][0]) - 1.0, float(rgb_l[-1][0]) + 1.0
        gt_l = [e for e in gt_l if lo <= float(e[0]) <= hi]
    kind = "pose" if pose_topic is True else str(pose_topic)
    intr = intrinsics or (read_intrinsics_txt(folder / "intrinsics.txt") if camera_info else None)
    topics = {"rgb": RGB_RAW if rgb == "raw" else RGB_COMPRESSED,
              "depth": None if depth is None else DEPTH_COMPRESSED if depth == "compressedDepth" else DEPTH_RAW,
              "camera_info": CAMERA_INFO if camera_info else None, "pose": POSE if gt_l else None}
    types = {"rgb": "sensor_msgs/msg/Image" if rgb == "raw" else "sensor_msgs/msg/CompressedImage",
             "depth": "sensor_msgs/msg/Image" if depth in ("16UC1", "32FC1") else "sensor_msgs/msg/CompressedImage",
             "camera_info": "sensor_msgs/msg/CameraInfo", "pose": POSE_TYPES.get(kind)}
    events = [(parse_stamp(s), "rgb", i) for i, (s, _) in enumerate(rgb_l)]
    events += [(parse_stamp(s), "camera_info", i) for i, (s, _) in enumerate(rgb_l) if camera_info]
    events += [(parse_stamp(s), "depth", i) for i, (s, _) in enumerate(dep_l)]
    events += [(parse_stamp(s), "pose", i) for i, (s, _) in enumerate(gt_l)]
    events.sort(key=lambda e: (e[0], e[1]))

    def build(role: str, stamp: tuple[int, int], i: int) -> Any:
        hdr = m.header(stamp, seq=i)
        if role == "rgb":
            path = folder / rgb_l[i][1]
            if rgb == "raw":
                return m.image(hdr, _colour(path, rgb_encoding), rgb_encoding, pad, bigendian)
            if rgb == "png":
                data = path.read_bytes() if path.suffix.lower() == ".png" else cv2.imencode(
                    ".png", cv2.imread(str(path), cv2.IMREAD_COLOR))[1].tobytes()
                return m.compressed(hdr, data, "png")
            return m.compressed(hdr, encode_jpeg(path), "rgb8; jpeg compressed bgr8")
        if role == "camera_info":
            return m.camera_info(hdr, intr, dist, dist_model)  # type: ignore[arg-type]
        if role == "pose":
            return m.pose(hdr, kind, [float(x) for x in gt_l[i][1].split()])
        raw = cv2.imread(str(folder / dep_l[i][1]), cv2.IMREAD_UNCHANGED).astype(np.float64)
        if depth == "32FC1":
            metres = (raw / depth_scale).astype(np.float32)
            return m.image(hdr, np.where(raw > 0, metres, np.float32(np.nan)), "32FC1", pad, bigendian)
        mm = np.round(raw * 1000.0 / depth_scale).astype(np.uint16)
        if depth == "compressedDepth":
            return m.compressed(hdr, compressed_depth_bytes(mm), "16UC1; compressedDepth")
        return m.image(hdr, mm, "16UC1", pad, bigendian)

    def write_all(add: Any, write: Any) -> None:
        conns = {role: add(topic, types[role]) for role, topic in topics.items() if topic is not None}
        for stamp, role, i in events:
            data = m.serialize(build(role, stamp, i), types[role])  # type: ignore[arg-type]
            write(conns[role], stamp[0] * 1_000_000_000 + stamp[1] + record_delay_ns, data)

    if ros_version == 1:
        from rosbags.rosbag1 import Writer as Writer1

        with Writer1(bag_path) as w1:
            write_all(lambda t, ty: w1.add_connection(t, ty, typestore=m.ts), w1.write)
    else:
        from rosbags.rosbag2 import StoragePlugin
        from rosbags.rosbag2 import Writer as Writer2

        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        with Writer2(bag_path, version=9, storage_plugin=plugin) as w2:
            write_all(lambda t, ty: w2.add_connection(t, ty, typestore=m.ts), w2.write)
    return {"bag": bag_path, **topics, "frames": len(rgb_l)}
