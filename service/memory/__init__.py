"""The map's memory: each session's keyframes written to the long-term memory (`long_term`)
and the STM/WM/LTM bookkeeping of what the map update keeps in RAM (`working_memory`)."""
