"""The mnemoslam SLAM server: tracking, mapping, memory, semantics and the REST API."""
