"""Tracking, at frame rate: features, odometry (sparse PnP + dense RGB-D registration, pose
refinement, the stereo disparity offset) and the keyframe decision."""
