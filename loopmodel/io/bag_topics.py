"""Topic discovery in bags.

Which image topics form the stereo pair, and which camera_info belongs to an image topic. Pure
functions on topic names and per-topic statistics.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

IMAGE_MSGTYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_MSGTYPE = "sensor_msgs/msg/CameraInfo"

# Name tokens of a left/right pair, in order of confidence.
_PAIR_TOKENS = (
    ("left", "right"),
    ("l", "r"),
    ("cam0", "cam1"),
    ("camera0", "camera1"),
    ("infra1", "infra2"),
    ("ir1", "ir2"),
    ("image0", "image1"),
    ("image_0", "image_1"),
    ("image_l", "image_r"),
    ("cam1", "cam2"),
    ("camera1", "camera2"),
)


@dataclass
class ImageTopic:
    """What discovery learns of one image topic.

    Type, message count, rate (Hz, from the first messages' header stamps), size (width, height),
    encoding, its camera_info topic.
    """

    topic: str
    msgtype: str
    count: int
    rate_hz: float | None = None
    size: tuple[int, int] | None = None
    encoding: str = ""
    info_topic: str | None = None
    frame_id: str = ""

    def summary(self) -> dict[str, object]:
        """Plain values for ``loopmodel info``."""
        return {
            "type": self.msgtype.split("/")[-1],
            "messages": self.count,
            "rate_hz": None if self.rate_hz is None else round(self.rate_hz, 3),
            "size": list(self.size) if self.size else None,
            "encoding": self.encoding,
            "camera_info": self.info_topic,
        }


def _tokens(topic: str) -> list[str]:
    return [t for t in re.split(r"[/]+", topic.lower()) if t]


def _pair_rank(a: str, b: str) -> int | None:
    """Rank (lower is better) of ``a`` as left and ``b`` as right when the names differ in
    exactly one path component by a known left/right token, else None."""
    ta, tb = _tokens(a), _tokens(b)
    if len(ta) != len(tb):
        return None
    diff = [(x, y) for x, y in zip(ta, tb, strict=True) if x != y]
    if len(diff) != 1:
        return None
    x, y = diff[0]
    for rank, (lt, rt) in enumerate(_PAIR_TOKENS):
        if x == lt and y == rt:
            return rank
        # a token inside a component: camera_left / camera_right, stereo_l / stereo_r, left_cam
        for sep in ("_", "-"):
            px, py = x.split(sep), y.split(sep)
            if len(px) == len(py) > 1:
                d = [(u, v) for u, v in zip(px, py, strict=True) if u != v]
                if len(d) == 1 and d[0] == (lt, rt):
                    return rank
    return None


def guess_stereo_pair(topics: list[ImageTopic]) -> tuple[ImageTopic, ImageTopic]:
    """The most likely (left, right) pair.

    Names differing by a left/right token, the same message type, size and rate (within 10 %); raw
    images before rectified ones and Image before CompressedImage. Raises ``LookupError`` with the
    reason when none fits.
    """
    best: tuple[tuple[int, int, int, int], ImageTopic, ImageTopic] | None = None
    for a in topics:
        for b in topics:
            if a is b:
                continue
            rank = _pair_rank(a.topic, b.topic)
            if rank is None or a.msgtype != b.msgtype:
                continue
            if a.size is not None and b.size is not None and a.size != b.size:
                continue
            if a.rate_hz and b.rate_hz and abs(a.rate_hz - b.rate_hz) > 0.1 * max(a.rate_hz, b.rate_hz):
                continue
            key = (
                rank,
                0 if a.info_topic and b.info_topic else 1,
                1 if "rect" in a.topic.lower() else 0,
                1 if a.msgtype.endswith("CompressedImage") else 0,
            )
            if best is None or key < best[0]:
                best = (key, a, b)
    if best is None:
        names = ", ".join(t.topic for t in topics) or "none"
        raise LookupError(
            f"no stereo pair among the image topics ({names}): expected names differing by left/right, "
            "cam0/cam1 or infra1/infra2 with equal image size and rate; give --left and --right"
        )
    return best[1], best[2]


def camera_info_for(image_topic: str, info_topics: list[str]) -> str | None:
    """The camera_info topic of an image topic.

    ``camera_info`` beside the image topic or in a parent namespace (``/cam0/image_raw`` ->
    ``/cam0/camera_info``).
    """
    parts = [p for p in image_topic.split("/") if p]
    have = set(info_topics)
    lead = "/" if image_topic.startswith("/") else ""
    for k in range(len(parts), 0, -1):
        cand = lead + "/".join([*parts[:k], "camera_info"])
        if cand in have:
            return cand
    return None
