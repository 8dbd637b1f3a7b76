"""Camera side of mnemoslam: the frame data model, dataset players, the synthetic scene
camera and (later) the Zenoh camera client and the planner's HTTP client."""
