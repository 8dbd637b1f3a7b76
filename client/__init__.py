"""Camera side of mnemoslam (`mnemoslam.client`): the shared kernel both sides speak (`kernel`:
frames, geometry, trajectory, the wire protocol), the dataset players (`datasets`), the synthetic
scene (`synthetic`), the Zenoh camera client (`streamer`, `transport`, `capture`), ROS 2 CDR
messages (`ros_cdr`) and the planner's HTTP client (`planner`)."""
