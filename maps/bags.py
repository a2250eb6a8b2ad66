"""Frames from ROS 1 and ROS 2 bags: the ``sensor_msgs/PointCloud2`` messages of one topic, in
the bag's order, read with the ``rosbags`` library (the ``map`` extra; no ROS install needed).

A ROS 1 bag is a ``.bag`` file; a ROS 2 bag is its folder (with ``metadata.yaml``), or its
``.db3`` / ``.mcap`` file. Each message's x, y, z fields (float32 or float64, any point step,
either byte order) become one frame; points with a NaN/Inf coordinate are dropped, as the file
readers do.
"""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from kbs.errors import CloudFileError, ParameterError

class TopicError(ParameterError):
    """The topic asked for is not a PointCloud2 topic of the bag, or none was named where several
    (or none) are (the command line reports it as a bad --topic, exit code 2)."""


#: PointField datatypes (sensor_msgs/PointField) -> numpy kinds.
_DATATYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
POINTCLOUD2 = ("sensor_msgs/msg/PointCloud2", "sensor_msgs/PointCloud2")


def is_bag(path: Path) -> bool:
    """Whether ``path`` looks like a ROS bag: a ``.bag``, ``.db3`` or ``.mcap`` file, or a folder
    holding a rosbag2 ``metadata.yaml``."""
    return (path.is_file() and path.suffix.lower() in (".bag", ".db3", ".mcap")) or (
        path.is_dir() and (path / "metadata.yaml").is_file())


def pointcloud2_xyz(msg) -> np.ndarray:
    """The finite x, y, z of a PointCloud2 message, (n, 3) float64.

    Raises
    ------
    ValueError
        No x, y or z field, or a data buffer shorter than its header says.
    """
    fields = {f.name: f for f in msg.fields}
    missing = [a for a in "xyz" if a not in fields]
    if missing:
        raise ValueError(f"no {', '.join(missing)} field (fields: {', '.join(fields) or 'none'})")
    order = ">" if msg.is_bigendian else "<"
    names, formats, offsets = [], [], []
    for a in "xyz":
        f = fields[a]
        if f.datatype not in _DATATYPES:
            raise ValueError(f"field {a} has PointField datatype {f.datatype}, not a number type")
        names.append(a)
        formats.append(order + _DATATYPES[f.datatype])
        offsets.append(f.offset)
    n = int(msg.width) * int(msg.height)
    dtype = np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": int(msg.point_step)})
    data = np.asarray(msg.data, dtype=np.uint8)
    rows = int(msg.height)
    if msg.row_step and rows > 1 and msg.row_step != msg.point_step * msg.width:  # padded rows
        data = data.reshape(rows, int(msg.row_step))[:, : int(msg.point_step * msg.width)].reshape(-1)
    if data.size < n * msg.point_step:
        raise ValueError(f"data holds {data.size} bytes for {n} points of {msg.point_step} bytes")
    rec = np.frombuffer(data[: n * msg.point_step].tobytes(), dtype=dtype, count=n)
    X = np.column_stack([rec[a].astype(np.float64) for a in "xyz"])
    return X[np.isfinite(X).all(axis=1)]


def read_bag(path: str | os.PathLike[str], topic: str | None = None):
    """The frames of a bag's PointCloud2 topic, in message order.

    Parameters
    ----------
    path : path of the bag (see the module's doc).
    topic : str, optional
        The topic; may be left out when the bag has exactly one PointCloud2 topic.

    Returns
    -------
    list of :class:`kbs.maps.drive.Frame`
        One per message, named ``<topic>#<index>``, points in memory; and the topic used.

    Raises
    ------
    ParameterError
        rosbags is not installed. :class:`TopicError` (a ParameterError): no topic given and the
        bag has none or several PointCloud2 topics; the topic is not in the bag or is not
        PointCloud2 (the message lists them).
    CloudFileError
        The bag cannot be read, a message cannot be decoded, or the topic has no message.
    """
    try:
        from rosbags.highlevel import AnyReader
    except ImportError as exc:
        raise ParameterError("reading ROS bags needs rosbags: pip install 'kbs[map]'") from exc
    from kbs.maps.drive import Frame

    path = Path(path)
    try:
        reader = AnyReader([path])
        reader.open()
    except Exception as exc:  # noqa: BLE001 - rosbags' errors for a damaged or foreign file
        raise CloudFileError(str(path), f"not a readable ROS bag ({type(exc).__name__}: {exc})") from exc
    try:
        clouds = sorted({c.topic for c in reader.connections if c.msgtype in POINTCLOUD2})
        if topic is None:
            if len(clouds) != 1:
                raise TopicError(f"{path}: name the topic of the point clouds (--topic); PointCloud2 topics in "
                                     f"the bag: {', '.join(clouds) or 'none'}")
            topic = clouds[0]
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns or conns[0].msgtype not in POINTCLOUD2:
            what = f"is {conns[0].msgtype}, not PointCloud2" if conns else "is not in the bag"
            raise TopicError(f"{path}: topic {topic!r} {what}; PointCloud2 topics: {', '.join(clouds) or 'none'}")
        frames = []
        for i, (conn, _, raw) in enumerate(reader.messages(connections=conns)):
            try:
                X = pointcloud2_xyz(reader.deserialize(raw, conn.msgtype))
            except Exception as exc:  # noqa: BLE001 - a message that does not decode
                raise CloudFileError(str(path), f"message {i} of {topic}: cannot decode the point cloud: {exc}") \
                    from exc
            if len(X) == 0:
                raise CloudFileError(str(path), f"message {i} of {topic} holds no finite point")
            frames.append(Frame(f"{topic}#{i}", None, X))
    finally:
        reader.close()
    if not frames:
        raise CloudFileError(str(path), f"no message on {topic}")
    return frames, topic
