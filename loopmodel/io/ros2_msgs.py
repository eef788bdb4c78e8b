"""ROS 2 message definitions, and conversions between messages and our types.

The definitions (concatenated form) cover the topics of DESIGN.md, so MCAP files can be written
without a ROS installation.
"""

from __future__ import annotations

_SEP = "=" * 80

_TIME = "int32 sec\nuint32 nanosec\n"
_HEADER = "builtin_interfaces/Time stamp\nstring frame_id\n"
_ROI = "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n"
_POINT_FIELD = (
    "uint8 INT8=1\nuint8 UINT8=2\nuint8 INT16=3\nuint8 UINT16=4\nuint8 INT32=5\n"
    "uint8 UINT32=6\nuint8 FLOAT32=7\nuint8 FLOAT64=8\n"
    "string name\nuint32 offset\nuint8 datatype\nuint32 count\n"
)
_POINT = "float64 x\nfloat64 y\nfloat64 z\n"
_QUATERNION = "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n"
_POSE = "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n"


def _concat(main: str, deps: list[tuple[str, str]]) -> str:
    parts = [main]
    for name, text in deps:
        parts.append(f"{_SEP}\nMSG: {name}\n{text}")
    return "\n".join(parts)


_HEADER_DEPS = [("std_msgs/Header", _HEADER), ("builtin_interfaces/Time", _TIME)]

MSGDEFS: dict[str, str] = {
    "sensor_msgs/msg/Image": _concat(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\n"
        "uint8 is_bigendian\nuint32 step\nuint8[] data\n",
        _HEADER_DEPS,
    ),
    "sensor_msgs/msg/CompressedImage": _concat("std_msgs/Header header\nstring format\nuint8[] data\n", _HEADER_DEPS),
    "sensor_msgs/msg/CameraInfo": _concat(
        "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\n"
        "float64[] d\nfloat64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\n"
        "uint32 binning_y\nsensor_msgs/RegionOfInterest roi\n",
        [*_HEADER_DEPS, ("sensor_msgs/RegionOfInterest", _ROI)],
    ),
    "sensor_msgs/msg/PointCloud2": _concat(
        "std_msgs/Header header\nuint32 height\nuint32 width\nsensor_msgs/PointField[] fields\n"
        "bool is_bigendian\nuint32 point_step\nuint32 row_step\nuint8[] data\nbool is_dense\n",
        [*_HEADER_DEPS, ("sensor_msgs/PointField", _POINT_FIELD)],
    ),
    "geometry_msgs/msg/PoseStamped": _concat(
        "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
        [
            *_HEADER_DEPS,
            ("geometry_msgs/Pose", _POSE),
            ("geometry_msgs/Point", _POINT),
            ("geometry_msgs/Quaternion", _QUATERNION),
        ],
    ),
}

POINTFIELD_FLOAT32 = 7


def header(t_ns: int, frame_id: str) -> dict:
    """A std_msgs/Header dict for a nanosecond time."""
    return {"stamp": {"sec": int(t_ns // 1_000_000_000), "nanosec": int(t_ns % 1_000_000_000)}, "frame_id": frame_id}


def stamp_ns(msg: object) -> int:
    """Nanoseconds of a decoded message's header stamp."""
    st = msg.header.stamp  # type: ignore[attr-defined]
    return int(st.sec) * 1_000_000_000 + int(st.nanosec)
