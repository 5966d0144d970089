"""A ROS bag given where a recording or a capture is read: told apart from a missing or
foreign file, and refused with the command that converts it (docs/cli.md). Only looks:
no bag library is imported."""

from __future__ import annotations

import os
import shlex
from pathlib import Path

from treetraits.errors import SourceError

ROS1_MAGIC = b"#ROSBAG V2.0\n"
ROS2_METADATA = "metadata.yaml"
ROS2_STORAGE = (".db3", ".mcap")


def ros_bag(path: str | os.PathLike) -> Path | None:
    """The ROS bag `path` is or is part of (a ROS 2 bag's directory, or a ROS 1 .bag
    file), else None."""
    path = Path(path)
    if path.is_dir():
        return path if (path / ROS2_METADATA).is_file() else None
    if not path.is_file():
        return None
    if path.suffix in ROS2_STORAGE and (path.parent / ROS2_METADATA).is_file():
        return path.parent  # a storage file of a ROS 2 bag: the bag is its directory
    try:
        with open(path, "rb") as f:
            return path if f.read(len(ROS1_MAGIC)) == ROS1_MAGIC else None
    except OSError:
        return None  # the caller's own open says what the system refused


def refuse_ros_bag(path: str | os.PathLike, expected: str) -> None:
    """Raise `SourceError` (exit 2) when `path` is a ROS bag: what it is, and the exact
    `treetraits import` that makes a recording of it."""
    bag = ros_bag(path)
    if bag is None:
        return
    out = bag.with_suffix(".mcap") if bag.is_file() else bag.with_name(bag.name + ".mcap")
    command = f"treetraits import {shlex.quote(str(bag))} --out {shlex.quote(str(out))}"
    if bag != Path(path):
        what = f"a file of the ROS 2 bag {bag}"
    else:
        what = "a ROS 1 bag" if bag.is_file() else "a ROS 2 bag (a directory with metadata.yaml)"
    raise SourceError(
        f"{path}: {what}, not {expected}; make a recording of the bag first: {command}"
    )
