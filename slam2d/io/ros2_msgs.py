"""ROS 2 message definitions (``ros2msg`` text, dependencies appended) used in MCAP files."""
from __future__ import annotations

from decimal import Decimal

_SEP = "=" * 80

_DEFS = {
    "builtin_interfaces/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/Header": "builtin_interfaces/Time stamp\nstring frame_id",
    "geometry_msgs/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/Pose": "Point position\nQuaternion orientation",
    "geometry_msgs/PoseWithCovariance": "Pose pose\nfloat64[36] covariance",
    "geometry_msgs/Twist": "Vector3 linear\nVector3 angular",
    "geometry_msgs/TwistWithCovariance": "Twist twist\nfloat64[36] covariance",
    "geometry_msgs/Transform": "Vector3 translation\nQuaternion rotation",
    "geometry_msgs/TransformStamped": "std_msgs/Header header\nstring child_frame_id\nTransform transform",
    "geometry_msgs/PoseStamped": "std_msgs/Header header\nPose pose",
    "sensor_msgs/LaserScan": (
        "std_msgs/Header header\nfloat32 angle_min\nfloat32 angle_max\nfloat32 angle_increment\n"
        "float32 time_increment\nfloat32 scan_time\nfloat32 range_min\nfloat32 range_max\n"
        "float32[] ranges\nfloat32[] intensities"),
    "nav_msgs/Odometry": ("std_msgs/Header header\nstring child_frame_id\n"
                          "geometry_msgs/PoseWithCovariance pose\ngeometry_msgs/TwistWithCovariance twist"),
    "nav_msgs/MapMetaData": ("builtin_interfaces/Time map_load_time\nfloat32 resolution\nuint32 width\n"
                             "uint32 height\ngeometry_msgs/Pose origin"),
    "nav_msgs/OccupancyGrid": "std_msgs/Header header\nMapMetaData info\nint8[] data",
    "tf2_msgs/TFMessage": "geometry_msgs/TransformStamped[] transforms",
}

_DEPS = {
    "std_msgs/Header": ["builtin_interfaces/Time"],
    "geometry_msgs/Pose": ["geometry_msgs/Point", "geometry_msgs/Quaternion"],
    "geometry_msgs/PoseWithCovariance": ["geometry_msgs/Pose"],
    "geometry_msgs/Twist": ["geometry_msgs/Vector3"],
    "geometry_msgs/TwistWithCovariance": ["geometry_msgs/Twist"],
    "geometry_msgs/Transform": ["geometry_msgs/Vector3", "geometry_msgs/Quaternion"],
    "geometry_msgs/TransformStamped": ["std_msgs/Header", "geometry_msgs/Transform"],
    "geometry_msgs/PoseStamped": ["std_msgs/Header", "geometry_msgs/Pose"],
    "sensor_msgs/LaserScan": ["std_msgs/Header"],
    "nav_msgs/Odometry": ["std_msgs/Header", "geometry_msgs/PoseWithCovariance", "geometry_msgs/TwistWithCovariance"],
    "nav_msgs/MapMetaData": ["builtin_interfaces/Time", "geometry_msgs/Pose"],
    "nav_msgs/OccupancyGrid": ["std_msgs/Header", "nav_msgs/MapMetaData"],
    "tf2_msgs/TFMessage": ["geometry_msgs/TransformStamped"],
}


def _closure(name: str, seen: list[str]) -> None:
    for d in _DEPS.get(name, []):
        if d not in seen:
            seen.append(d)
            _closure(d, seen)


def msgdef(name: str) -> tuple[str, str]:
    """(schema name like 'sensor_msgs/msg/LaserScan', full ros2msg text with dependencies)."""
    deps: list[str] = []
    _closure(name, deps)
    parts = [_DEFS[name]]
    for d in deps:
        parts.append(f"{_SEP}\nMSG: {d}\n{_DEFS[d]}")
    pkg, typ = name.split("/")
    return f"{pkg}/msg/{typ}", "\n".join(parts) + "\n"


def stamp_from_text(text: str) -> tuple[int, int]:
    """Exact (sec, nanosec) of a decimal seconds string."""
    d = Decimal(text)
    sec = int(d // 1)
    nsec = int(((d - sec) * 1_000_000_000).to_integral_value())
    if nsec >= 1_000_000_000:
        sec, nsec = sec + 1, nsec - 1_000_000_000
    return sec, nsec


def stamp_text(sec: int, nsec: int) -> str:
    return f"{sec}.{nsec:09d}"
