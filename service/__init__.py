"""The mnemoslam SLAM server, by stage: `tracking`, `mapping`, `memory` (semantics later);
the shell at this level: `server`, `session`, `api`, `cli`, `pipeline`, `builder`, `runner`,
`recovery`, `demo`, `config`, `evaluation`."""
