"""The approximate time synchroniser lives in rg_core (no ROS import) so `rg map BAG` pairs colour,
depth and CameraInfo exactly as the node does; re-exported here for the node and its tests."""
from rg_core.io.sync import ApproximateTimeSync, SyncedSet  # noqa: F401
