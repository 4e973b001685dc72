"""ROS 1 ``.bag`` and ROS 2 bags (``metadata.yaml`` + ``.db3``/``.mcap``) → a TUM-layout folder.

Read with :class:`rosbags.highlevel.AnyReader` (pure Python, no ROS install). One pass over the
selected topics in record order, one message in memory at a time:

- colour (``sensor_msgs/Image`` ``rgb8``/``bgr8``/``rgba8``/``bgra8``/``mono8``, or
  ``CompressedImage`` JPEG/PNG, whose bytes are stored as they are);
- depth (``16UC1``/``mono16`` millimetres → ``depth_scale`` 1000; ``32FC1`` metres → uint16 at
  5000/m, i.e. quantised to 0.2 mm; ``compressedDepth`` and plain 16-bit PNG ``CompressedImage``);
- intrinsics from the first ``sensor_msgs/CameraInfo``;
- GT poses (camera-to-world) from ``PoseStamped``, ``TransformStamped`` or ``Odometry``.

Times are the messages' ``header.stamp`` (seconds, float64), never the bag's record times.
"""

from __future__ import annotations

import struct
from pathlib import Path
from typing import Any, Literal

import cv2
import numpy as np

from mutualslam_cli.datasets.recordings.conversion import RecordingOptions, TumWriter
from mutualslam_cli.datasets.recordings.messages import Header, RawImage, Stamped
from mutualslam_cli.errors import DatasetError
from mutualslam_cli.geometry import pose_from_tq
from mutualslam_cli.types import JSON, Intrinsics, JSONObject, Trajectory

IMAGE = "sensor_msgs/msg/Image"
COMPRESSED = "sensor_msgs/msg/CompressedImage"
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry")
IMAGE_TYPES = (IMAGE, COMPRESSED)
#: Raw depth units per metre of 16-bit depth (ROS ``16UC1``: millimetres).
MM_SCALE = 1000.0
#: Raw units per metre that ``32FC1`` depth (metres) is quantised to, and the scale without depth.
FLOAT_SCALE = 5000.0
_PNG = b"\x89PNG\r\n\x1a\n"
_JPEG = b"\xff\xd8\xff"
#: Raw ``Image`` colour encodings: (channels, channel order to RGB, or None for grey).
_COLOR = {"rgb8": (3, [0, 1, 2]), "bgr8": (3, [2, 1, 0]), "rgba8": (4, [0, 1, 2]), "bgra8": (4, [2, 1, 0]),
          "mono8": (1, None)}


def bag_source(path: Path) -> Path:
    """What :class:`AnyReader` opens: a ``.bag`` file, a ROS 2 bag folder, or a lone ``.db3``/``.mcap``
    (its folder when that holds ``metadata.yaml``, so split bags read whole)."""
    path = Path(path)
    if path.is_file() and path.suffix in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def _one_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def stamp_seconds(header: Header) -> float:
    """``header.stamp`` as float64 seconds: ``sec + nanosec / 1e9``."""
    return float(np.float64(header.stamp.sec) + np.float64(header.stamp.nanosec) / 1e9)


def _raw_pixels(msg: RawImage, where: str, dtype: str, channels: int) -> np.ndarray:
    """``(H, W, C)`` pixels of a raw ``Image`` in native byte order (``step`` padding dropped)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    item = np.dtype(dtype).itemsize
    row = w * channels * item
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if step < row or data.size < h * step:
        raise DatasetError(f"{where}: {msg.encoding} image {w}×{h} with step {step} has {data.size} bytes; "
                           f"expected step ≥ {row} and height×step = {h * step} bytes")
    rows = np.ascontiguousarray(data[: h * step].reshape(h, step)[:, :row])
    order: Literal[">", "<"] = ">" if int(msg.is_bigendian) else "<"
    arr = rows.view(np.dtype(dtype).newbyteorder(order)).reshape(h, w, channels)
    return arr.astype(np.dtype(dtype).newbyteorder("="), copy=False)


def decode_color(msg: Any, msgtype: str, where: str) -> tuple[bytes | np.ndarray, str, str]:
    """A colour message → ``(image, ext, encoding)`` for :meth:`TumWriter.add_rgb` (``where``: bag and topic).

    ``CompressedImage``: the JPEG/PNG bytes unchanged (``ext`` ``.jpg``/``.png`` from the bytes'
    signature). ``Image``: an ``(H, W, 3)`` uint8 RGB or ``(H, W)`` uint8 grey array.
    """
    if msgtype == COMPRESSED:
        data = bytes(msg.data)
        fmt = str(msg.format)
        if data.startswith(_JPEG):
            return data, ".jpg", fmt or "jpeg"
        if data.startswith(_PNG):
            return data, ".png", fmt or "png"
        raise DatasetError(f"{where}: CompressedImage format '{fmt}' is not JPEG or PNG bytes; expected a colour "
                           "image (format 'jpeg', 'png', 'rgb8; jpeg compressed bgr8' …)")
    enc = str(msg.encoding)
    if enc not in _COLOR:
        raise DatasetError(f"{where}: colour encoding '{enc}' is not supported; expected one of {', '.join(_COLOR)}")
    channels, order = _COLOR[enc]
    px = _raw_pixels(msg, where, "u1", channels)
    return (np.ascontiguousarray(px[..., order]) if order is not None else px[..., 0].copy()), ".png", enc


def quantise_metres(depth: np.ndarray) -> tuple[np.ndarray, int]:
    """``(H, W)`` float depth in metres → ``(uint16 at 5000/m, pixels beyond 65535/5000 m)``.

    NaN, ±inf, ≤ 0 and depths beyond 13.107 m become 0 (invalid); others ``round(d·5000)``.
    """
    d = np.asarray(depth, dtype=np.float64)
    finite = np.isfinite(d)
    far = finite & (d > 65535.0 / FLOAT_SCALE)
    valid = finite & (d > 0) & ~far
    out = np.zeros(d.shape, np.uint16)
    out[valid] = np.round(d[valid] * FLOAT_SCALE).astype(np.uint16)
    return out, int(far.sum())


def _png_of(data: bytes, where: str, fmt: str) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        what = "undecodable" if img is None else f"{img.dtype} with shape {img.shape}"
        raise DatasetError(f"{where}: compressed depth (format '{fmt}') is {what}; expected a 16-bit 1-channel PNG")
    return img


def decode_depth(msg: Any, msgtype: str, where: str) -> tuple[np.ndarray, float, str, int]:
    """A depth message → ``(uint16 (H, W) raw depth, depth_scale, encoding, far pixels zeroed)`` (``where``:
    bag and topic, for messages).

    ``16UC1``/``mono16`` (and 16-bit PNG ``CompressedImage``): millimetres, scale 1000, as they are.
    ``32FC1`` (also ``compressedDepth``'s inverse-depth PNG): metres quantised by :func:`quantise_metres`.
    """
    if msgtype == COMPRESSED:
        fmt = str(msg.format)
        data = bytes(msg.data)
        enc = fmt.split(";")[0].strip() or "png"
        if "compresseddepth" in fmt.lower():
            if "rvl" in fmt.lower():
                raise DatasetError(f"{where}: compressedDepth RVL ('{fmt}') is not supported; expected PNG")
            # compressed_depth_image_transport: ConfigHeader {int32 format; float32 depthParam[2]} then a PNG
            body = data if data.startswith(_PNG) else data[12:]
            if not body.startswith(_PNG):
                raise DatasetError(f"{where}: compressedDepth message (format '{fmt}') holds no PNG after its "
                                   "12-byte header")
            raw = _png_of(body, where, fmt)
            if enc.upper() == "32FC1":
                quant_a, quant_b = struct.unpack("<ff", data[4:12])
                inv = raw.astype(np.float64)
                with np.errstate(divide="ignore", invalid="ignore"):
                    metres = np.where(raw > 0, quant_a / (inv - quant_b), np.nan)
                out, far = quantise_metres(metres)
                return out, FLOAT_SCALE, "32FC1; compressedDepth", far
            if enc.upper() not in ("16UC1", "MONO16"):
                raise DatasetError(f"{where}: compressedDepth of '{enc}' is not supported; expected 16UC1 or 32FC1")
            return raw, MM_SCALE, "16UC1; compressedDepth", 0
        if not data.startswith(_PNG):
            raise DatasetError(f"{where}: depth CompressedImage format '{fmt}' is not PNG; expected a 16-bit PNG "
                               "(millimetres) or '16UC1; compressedDepth'")
        return _png_of(data, where, fmt), MM_SCALE, fmt or "png", 0
    enc = str(msg.encoding)
    if enc in ("16UC1", "mono16"):
        return _raw_pixels(msg, where, "u2", 1)[..., 0].copy(), MM_SCALE, enc, 0
    if enc == "32FC1":
        out, far = quantise_metres(_raw_pixels(msg, where, "f4", 1)[..., 0])
        return out, FLOAT_SCALE, enc, far
    raise DatasetError(f"{where}: depth encoding '{enc}' is not supported; expected 16UC1 or mono16 (millimetres) "
                       "or 32FC1 (metres)")


def intrinsics_of(msg: Any, where: str) -> Intrinsics | None:
    """A ``CameraInfo`` → :class:`Intrinsics` (``None`` when ``K`` is zero: an uncalibrated camera).

    ROS 2 names the fields ``k``/``d``, ROS 1 ``K``/``D``. ``plumb_bob`` and ``rational_polynomial``
    give OpenCV ``(k1, k2, p1, p2, k3)``; all-zero coefficients give ``dist=None``.
    """
    k = np.asarray(msg.k if hasattr(msg, "k") else msg.K, np.float64).reshape(-1)  # ROS 2 k, ROS 1 K
    d = np.asarray(msg.d if hasattr(msg, "d") else msg.D, np.float64).reshape(-1)
    model = str(msg.distortion_model).strip()
    if k.size != 9 or k[0] == 0 or k[4] == 0:
        return None
    if int(msg.binning_x) > 1 or int(msg.binning_y) > 1 or int(msg.roi.width) or int(msg.roi.height):
        raise DatasetError(f"{where}: CameraInfo with binning or a region of interest is not supported; "
                           "give a camera file with --camera")
    dist = None
    if d.size and np.any(d != 0):
        if model not in ("plumb_bob", "rational_polynomial"):
            raise DatasetError(f"{where}: distortion model '{model}' is not supported; expected plumb_bob or "
                               "rational_polynomial (or give a camera file with --camera)")
        if model == "rational_polynomial" and np.any(d[5:] != 0):
            raise DatasetError(f"{where}: rational_polynomial k4–k6 = {list(d[5:8])} are not zero; only "
                               "(k1, k2, p1, p2, k3) are supported (give a camera file with --camera)")
        dist = tuple(float(x) for x in np.concatenate([d[:5], np.zeros(5)])[:5])
    return Intrinsics(float(k[0]), float(k[4]), float(k[2]), float(k[5]), int(msg.width), int(msg.height), dist)


def pose_tq(msg: Any, msgtype: str) -> list[float]:
    """``[tx, ty, tz, qx, qy, qz, qw]`` of a ``PoseStamped`` / ``TransformStamped`` / ``Odometry``."""
    if msgtype.endswith("TransformStamped"):
        p, q = msg.transform.translation, msg.transform.rotation
    else:
        pose = msg.pose.pose if msgtype.endswith("Odometry") else msg.pose
        p, q = pose.position, pose.orientation
    return [float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w)]


def select_topics(name: Path, topics: dict[str, str | None], opts: RecordingOptions) -> dict[str, str]:
    """Decide the topics used: ``{"rgb": …, "depth"?: …, "camera_info"?: …, "pose"?: …}``.

    Args:
        name: the bag (for messages).
        topics: every topic of the bag → its message type (``None``: mixed types).
    """
    listing = ", ".join(f"{t} ({ty or 'mixed types'})" for t, ty in sorted(topics.items())) or "no topics"

    def need(topic: str, kinds: tuple[str, ...], flag: str) -> str:
        if topic not in topics and f"/{topic}" in topics:
            topic = f"/{topic}"
        if topic not in topics:
            raise DatasetError(f"{name}: topic '{topic}' ({flag}) not found; the bag has: {listing}")
        if topics[topic] not in kinds:
            raise DatasetError(f"{name}: topic '{topic}' ({flag}) is {topics[topic]}; expected {' or '.join(kinds)}")
        return topic

    images = sorted(t for t, ty in topics.items() if ty in IMAGE_TYPES)
    if opts.rgb_topic is not None:
        rgb = need(opts.rgb_topic, IMAGE_TYPES, "--rgb-topic")
    else:
        colour = [t for t in images if "depth" not in t.lower()]
        if len(colour) != 1:
            found = f"the image topics are {', '.join(images)}" if images else f"no image topic; the bag has: {listing}"
            raise DatasetError(f"{name}: cannot tell the colour topic ({found}); choose one with --rgb-topic")
        rgb = colour[0]
    sel = {"rgb": rgb}
    if opts.depth_topic is not None:
        sel["depth"] = need(opts.depth_topic, IMAGE_TYPES, "--depth-topic")
        if sel["depth"] == rgb:
            raise DatasetError(f"{name}: topic '{rgb}' given as both colour and depth; expected two topics")
    if opts.pose_topic is not None:
        sel["pose"] = need(opts.pose_topic, POSE_TYPES, "--pose-topic")
    infos = sorted(t for t, ty in topics.items() if ty == CAMERA_INFO)
    if opts.camera_info_topic is not None:
        sel["camera_info"] = need(opts.camera_info_topic, (CAMERA_INFO,), "--camera-info-topic")
    else:
        parts = rgb.strip("/").split("/")
        beside = ["/" + "/".join(parts[:k] + ["camera_info"]) for k in range(len(parts) - 1, -1, -1)]
        match = [t for t in beside if t in infos] or (infos if len(infos) == 1 else [])
        if match:
            sel["camera_info"] = match[0]
        elif infos:
            raise DatasetError(f"{name}: no CameraInfo beside '{rgb}' and several others ({', '.join(infos)}); "
                               "choose one with --camera-info-topic or give --camera")
    return sel


class _Converter:
    """State of one pass: counts, encodings, the depth unit, intrinsics, GT poses."""

    def __init__(self, name: Path, sel: dict[str, str], writer: TumWriter):
        self.name, self.sel, self.writer = name, sel, writer
        self.role = {topic: role for role, topic in sel.items()}
        self.counts = {t: 0 for t in sel.values()}
        self.encodings: dict[str, set[str]] = {t: set() for t in sel.values()}
        self.last_t: dict[str, float] = {}
        self.out_of_order = {t: 0 for t in sel.values()}
        self.depth_scale: float | None = None
        self.depth_enc: str | None = None
        self.far = 0
        self.intr: Intrinsics | None = None
        self.info_seen = False
        self.info_changed = 0
        self.poses: list[tuple[float, list[float]]] = []

    def _time(self, topic: str, msg: Stamped) -> float:
        t = stamp_seconds(msg.header)
        if t == 0.0 and self.last_t.get(topic) == 0.0:  # one zero stamp may be a time origin, two are unset
            raise DatasetError(f"{self.name}: messages on '{topic}' have zero header stamps; expected sensor "
                               "times in header.stamp (record times are not used)")
        if topic in self.last_t and t <= self.last_t[topic]:
            self.out_of_order[topic] += 1
        self.last_t[topic] = t
        return t

    def handle(self, topic: str, msgtype: str, msg: Any) -> None:
        role = self.role[topic]
        self.counts[topic] += 1
        if role == "camera_info":
            intr = intrinsics_of(msg, f"{self.name} topic {topic}")
            if not self.info_seen:
                self.intr, self.info_seen = intr, True
            elif intr != self.intr:
                self.info_changed += 1
            return
        t = self._time(topic, msg)
        if role == "rgb":
            image, ext, enc = decode_color(msg, msgtype, f"{self.name} topic {topic}")
            self.encodings[topic].add(enc)
            self.writer.add_rgb(t, image, ext)
        elif role == "depth":
            depth, scale, enc, far = decode_depth(msg, msgtype, f"{self.name} topic {topic}")
            if self.depth_scale is not None and scale != self.depth_scale:
                raise DatasetError(f"{self.name}: depth on '{topic}' changes unit at {t:.6f} s ({enc} after "
                                   f"{self.depth_enc}); expected one depth encoding throughout")
            self.depth_scale, self.depth_enc, self.far = scale, self.depth_enc or enc, self.far + far
            self.encodings[topic].add(enc)
            self.writer.add_depth(t, depth)
        else:
            tq = pose_tq(msg, msgtype)
            if np.linalg.norm(tq[3:]) < 1e-12:
                raise DatasetError(f"{self.name}: pose on '{topic}' at {t:.6f} s has a zero quaternion; "
                                   "expected a unit rotation")
            self.poses.append((t, tq))

    def finish(self) -> tuple[Intrinsics | None, float, JSONObject]:
        notes: list[JSON] = []
        if self.depth_scale == FLOAT_SCALE:
            notes.append("depth 32FC1 (metres) quantised to 0.2 mm: uint16 at 5000/m; NaN, inf, ≤ 0 and depths "
                         f"beyond 13.107 m set to 0 (invalid; {self.far} pixels were beyond)")
        elif self.depth_scale == MM_SCALE:
            notes.append("depth 16-bit millimetres stored as they are (depth_scale 1000)")
        if "camera_info" in self.sel and self.info_seen and self.intr is None:
            notes.append(f"CameraInfo on {self.sel['camera_info']} has a zero K (uncalibrated camera): not used")
        if self.info_changed:
            notes.append(f"CameraInfo changed in {self.info_changed} later messages; the first one is used")
        notes += [f"{n} header stamps on {t} not increasing" for t, n in self.out_of_order.items() if n]
        if self.poses:
            self.poses.sort(key=lambda p: p[0])
            times = np.array([p[0] for p in self.poses])
            keep = np.concatenate([[True], np.diff(times) > 0])
            if not keep.all():
                notes.append(f"{int((~keep).sum())} GT poses with repeated stamps dropped")
            tq = np.array([p[1] for p in self.poses])[keep]
            self.writer.set_gt(Trajectory(times[keep], pose_from_tq(tq[:, :3], tq[:, 3:])))
        meta: JSONObject = {
            "what": f"expected image messages on {self.sel['rgb']}",
            "topics": dict(self.sel),
            "messages": dict(self.counts),
            "encodings": {t: list[JSON](sorted(e)) for t, e in self.encodings.items() if e},
            "notes": notes,
        }
        if self.intr is not None:
            meta["intrinsics_source"] = f"CameraInfo {self.sel['camera_info']}"
        return self.intr, self.depth_scale if self.depth_scale is not None else FLOAT_SCALE, meta


def convert_bag(path: Path, opts: RecordingOptions, writer: TumWriter) -> tuple[Intrinsics | None, float, JSONObject]:
    """Convert a ROS bag's colour, depth, CameraInfo and pose topics into ``writer`` in one pass.

    Args:
        path: a ROS 1 ``.bag``, a ROS 2 bag folder, or its ``.db3``/``.mcap`` file.
        opts: the topics (see :class:`RecordingOptions`); ``None`` topics are chosen from the bag.
        writer: receives frames (times from ``header.stamp``, seconds) and GT poses (camera-to-world).

    Returns:
        ``(intrinsics or None, depth_scale (raw units per metre: 1000 for 16UC1, 5000 for 32FC1 or
        no depth), meta)``; ``meta`` holds the topics, message counts, encodings, ``intrinsics_source``
        and notes.

    Raises:
        DatasetError: an unreadable bag, a missing or ambiguous topic (the bag's topics listed),
            an unsupported encoding or distortion model — one line naming the bag or topic.
    """
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.rosbag1 import ReaderError as ReaderError1
    from rosbags.rosbag2 import ReaderError as ReaderError2
    from rosbags.typesys import Stores, get_typestore

    path = Path(path)
    src = bag_source(path)
    bad = (AnyReaderError, ReaderError1, ReaderError2, OSError)
    expected = "expected a ROS 1 .bag or a ROS 2 bag folder with metadata.yaml and .db3/.mcap files"
    try:
        store = get_typestore(Stores.ROS1_NOETIC if src.suffix == ".bag" else Stores.ROS2_HUMBLE)
        reader = AnyReader([src], default_typestore=store)
        reader.open()
    except bad as err:
        raise DatasetError(f"{path}: cannot read the bag ({_one_line(err)}); {expected}") from None
    try:
        topics = {t: info.msgtype for t, info in reader.topics.items()}
        sel = select_topics(path, topics, opts)
        conv = _Converter(path, sel, writer)
        conns = [c for c in reader.connections if c.topic in conv.role]
        messages = reader.messages(connections=conns)
        while True:
            try:
                item = next(messages, None)
                if item is None:
                    break
                conn, msg = item[0], reader.deserialize(item[2], item[0].msgtype)
            except bad as err:
                raise DatasetError(f"{path}: cannot read a message after {sum(conv.counts.values())} on "
                                   f"{', '.join(conv.role)} ({_one_line(err)})") from None
            conv.handle(conn.topic, conn.msgtype, msg)
        intr, scale, meta = conv.finish()
        meta["bag"] = {"format": "ROS 1" if src.suffix == ".bag" else "ROS 2", "path": str(src),
                       "topics": {t: ty for t, ty in sorted(topics.items())}}
        return intr, scale, meta
    finally:
        reader.close()
