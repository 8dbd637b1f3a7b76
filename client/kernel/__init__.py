"""The shared kernel: what the camera side and the service side both speak.

`frames` (Frame, Calibration, the pixel and pose conventions), `geometry` (SE(3) helpers),
`trajectory` (TUM trajectory files, ATE) and `protocol` (the wire format on Zenoh). Nothing here
imports the rest of `mnemoslam.client`, `mnemoslam.service` or `mnemoslam.storage`: both sides
import it, it imports neither.
"""
