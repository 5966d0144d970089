"""ROS 1 and ROS 2 bags to recordings, without ROS (`treetraits import`, docs/import.md).

`convert` turns a bag into a recording, `topics` finds the topics to take, `frames` reads
the mounting of the IMU from `/tf_static`, `pointcloud2` decodes PointCloud2 messages.
"""
