"""Writing loop closures (and optionally the replayed images) back to a rosbag2 folder (mcap)."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, TypesysError, get_types_from_msg, get_typestore

from pair_vpr_ros.errors import BagError, OutputError
from pair_vpr_ros.loops.records import LoopRecord
from pair_vpr_ros.messages import loop as loop_messages
from pair_vpr_ros.messages import loop_image
from pair_vpr_ros.messages.factor import FACTOR_TOPIC, FACTOR_TYPE, factor_msg
from pair_vpr_ros.offline.bags.opening import jazzy_typestore
from pair_vpr_ros.types import split_stamp


class LoopBagWriter:
    """Write loop closures (and optionally the replayed images) to a new rosbag2 folder (mcap).

    Loop messages are the node's (``loop_messages``) on ``/loop_closure``,
    ``/loop_closure/detail``, ``/loop_closure/json``, ``/loop_closure/typed`` (when the message
    definition is found: ``typed_definition``; else ``typed_note`` says why it is left out),
    (loops with a relative pose) ``/loop_closure/factor`` and ``/loop_closure/image``
    (``write_loop_image``, one per accepted loop), each written at the receive time of its
    query image so the output plays in step with the source bag. Use as a context manager;
    ``path`` must not exist.
    """

    def __init__(
        self, path: str | Path, image_topic: str | None = None, image_msgtype: str = ""
    ) -> None:
        self.path = Path(path)
        if self.path.exists():
            raise BagError(f"output bag {self.path} exists already: remove it or write elsewhere")
        self._ts = jazzy_typestore()
        self._writer = Writer(self.path, version=9, storage_plugin=StoragePlugin.MCAP)
        self._image_topic, self._image_msgtype = image_topic, image_msgtype
        self._connections: dict[str, Any] = {}
        self.typed_note = register_typed(self._ts)

    def __enter__(self) -> LoopBagWriter:
        try:
            self._writer.open()
        except OSError as err:
            raise BagError(f"cannot create output bag {self.path}: {err}") from err
        ts = self._ts
        float_array, string = loop_messages.FLOAT64_ARRAY_TYPE, loop_messages.STRING_TYPE
        for topic, msgtype in (
            (loop_messages.PAIR_TOPIC, float_array),
            (loop_messages.DETAIL_TOPIC, float_array),
            (loop_messages.JSON_TOPIC, string),
            (FACTOR_TOPIC, FACTOR_TYPE),
            (loop_image.IMAGE_TOPIC, loop_image.IMAGE_TYPE),
        ):
            self._connections[topic] = self._writer.add_connection(
                "/" + topic, msgtype, typestore=ts
            )
        if self.typed_note is None:
            self._connections[loop_messages.TYPED_TOPIC] = self._writer.add_connection(
                "/" + loop_messages.TYPED_TOPIC, loop_messages.TYPED_TYPE, typestore=ts
            )
        if self._image_topic is not None:
            self._connections["image"] = self._writer.add_connection(
                self._image_topic, self._image_msgtype, typestore=ts
            )
        return self

    def __exit__(self, *exc: object) -> None:
        try:
            self._writer.close()
        except OSError as err:
            if exc[0] is None:  # do not hide the error that ended the block
                raise self._failed(err) from err

    def _failed(self, err: OSError) -> OutputError:
        return OutputError(
            f"writing the output bag {self.path} failed ({err.strerror or err}); free disk "
            "space or write elsewhere"
        )

    def _write(self, connection: Any, log_time_ns: int, cdr: bytes) -> None:
        try:
            self._writer.write(connection, log_time_ns, cdr)
        except OSError as err:
            raise self._failed(err) from err

    def write_image(self, cdr: bytes, log_time_ns: int) -> None:
        """Copy one image message (CDR bytes) at its original receive time."""
        self._write(self._connections["image"], log_time_ns, cdr)

    def write_loop_image(self, record: Any, bgr: np.ndarray, log_time_ns: int) -> None:
        """Write one loop image (``messages.loop_image.draw_loop``) on ``/loop_closure/image``,
        stamped and framed as the loop's query image."""
        ts = self._ts
        sec, nanosec = split_stamp(record.query_stamp)
        header = ts.types["std_msgs/msg/Header"](
            stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
            frame_id=record.query_frame_id,
        )
        msg = ts.types[loop_image.IMAGE_TYPE](header=header, **loop_image.image_fields(bgr))
        cdr = ts.serialize_cdr(msg, loop_image.IMAGE_TYPE)
        self._write(self._connections[loop_image.IMAGE_TOPIC], log_time_ns, cdr)

    def write_loop(self, record: Any, log_time_ns: int) -> None:
        """Write the messages of one loop closure at ``log_time_ns``."""
        ts, content = self._ts, loop_messages.loop_messages(record)
        array, layout, dim = (
            ts.types["std_msgs/msg/Float64MultiArray"],
            ts.types["std_msgs/msg/MultiArrayLayout"],
            ts.types["std_msgs/msg/MultiArrayDimension"],
        )
        detail = array(
            layout=layout(
                dim=[dim(label=label, size=1, stride=1) for label in content.detail_labels],
                data_offset=0,
            ),
            data=np.asarray(content.detail, dtype=np.float64),
        )
        text = ts.types["std_msgs/msg/String"](data=content.json)
        msgs = []
        if content.pair is not None:  # None: the match is not older (loop_messages.pair_data)
            pair = array(layout=layout(dim=[], data_offset=0), data=np.asarray(content.pair))
            msgs.append((loop_messages.PAIR_TOPIC, pair))
        msgs += [
            (loop_messages.DETAIL_TOPIC, detail),
            (loop_messages.JSON_TOPIC, text),
        ]
        if content.factor is not None:
            msgs.append((FACTOR_TOPIC, factor_msg(content.factor, ts.types)))
        if self.typed_note is None:
            msgs.append((loop_messages.TYPED_TOPIC, loop_messages.typed_msg(record, ts.types)))
        for topic, msg in msgs:
            cdr = ts.serialize_cdr(msg, msg.__msgtype__)
            self._write(self._connections[topic], log_time_ns, cdr)


MSG_PATH = Path("share", "pair_vpr_ros_interfaces", "msg", "LoopClosure.msg")
# a source checkout: the interface package lives beside the Python package
SOURCE_MSG = Path(__file__).resolve().parents[3] / "interfaces" / "pair_vpr_ros_interfaces" / "msg"


def typed_definition() -> Path | None:
    """``LoopClosure.msg`` as installed (each ``AMENT_PREFIX_PATH`` prefix, then this Python's
    prefix: ``make setup`` builds it there) or in a source checkout; None if nowhere."""
    prefixes = [p for p in os.environ.get("AMENT_PREFIX_PATH", "").split(os.pathsep) if p]
    places = [Path(p) / MSG_PATH for p in [*prefixes, sys.prefix]]
    places.append(SOURCE_MSG / "LoopClosure.msg")
    return next((p for p in places if p.is_file()), None)


def register_typed(ts: Any) -> str | None:
    """Add ``loop_messages.TYPED_TYPE`` to the typestore ``ts``; None when done, else why not
    (the bag is then written without ``/loop_closure/typed``)."""
    if loop_messages.TYPED_TYPE in ts.types:
        return None
    path = typed_definition()
    if path is None:
        return (
            f"/{loop_messages.TYPED_TOPIC} is not written: the definition of "
            f"{loop_messages.TYPED_TYPE} was not found (build pair_vpr_ros_interfaces: "
            "docs/interfaces.md); the other loop-closure topics are written"
        )
    try:
        types = get_types_from_msg(path.read_text("utf-8"), loop_messages.TYPED_TYPE)
    except (OSError, UnicodeDecodeError, TypesysError) as err:
        return f"/{loop_messages.TYPED_TOPIC} is not written: cannot read {path}: {err}"
    probe = get_typestore(Stores.ROS2_JAZZY)  # tried apart: `ts` is shared, and kept clean
    try:  # another build's definition (fields missing or extra) fails here, not at a loop
        probe.register(types)
        sample = LoopRecord(0, 0.0, "", 0, 0.0, "", pair_score=0.0, global_similarity=0.0,
                            rank_before=1, rank_after=1)  # fmt: skip
        msg = loop_messages.typed_msg(sample, probe.types)
        probe.serialize_cdr(msg, loop_messages.TYPED_TYPE)
    except Exception as err:  # noqa: BLE001 - any failure means the definition does not fit
        return (
            f"/{loop_messages.TYPED_TOPIC} is not written: the definition {path} does not fit "
            f"this version ({type(err).__name__}: {err}); rebuild pair_vpr_ros_interfaces "
            "(docs/interfaces.md) or put this build first on AMENT_PREFIX_PATH; the other "
            "loop-closure topics are written"
        )
    ts.register(types)
    return None
