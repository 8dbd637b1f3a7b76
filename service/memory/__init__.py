"""The map's memory: each session's keyframes written to the long-term memory as tracking
makes them (`keyframes.KeyframeWriter`), and the node life cycle of the map update
(`manager.Memory`, RTAB-Map's Memory): what it keeps in RAM as STM and WM, moved to and from
LTM as `working_memory` decides, rehearsal's merges, the map's visual vocabulary
(`vocabulary`) and the keyframes' dense views (`views`). It imports nothing of the map update
(`service.mapping`), which calls it."""
