"""The map's memory: each session's keyframes written to the long-term memory (`long_term`),
and the node life cycle of the map update (`manager`): what it keeps in RAM as STM and WM,
moved to and from LTM as `working_memory` decides, and rehearsal's merges."""
