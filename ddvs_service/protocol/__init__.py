"""The ddvs message protocol: key expressions, ROS 2 CDR codecs, JSON control plane, Zenoh session helpers."""
