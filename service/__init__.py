"""The mnemoslam SLAM server (`mnemoslam.service`), by stage: `tracking`, `mapping`, `memory`,
`semantics`; the shell at this level: `server`, `session`, `api`, `cli`, `pipeline`, `builder`,
`runner`, `recovery`, `demo`, `config`, `evaluation`, `metrics`, `viewer`, `ros`."""
