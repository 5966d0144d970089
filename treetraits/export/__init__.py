"""Exports of a recording for other tools, offline: `treetraits export foxglove`
(`foxglove`, docs/data.md). Needs the `export` extra (the Foxglove schemas, protobuf);
nothing on the robot imports it.
"""
