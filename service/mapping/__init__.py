"""The map update, per keyframe and behind tracking: vocabulary, loop detection (appearance
and proximity), geometric verification, the pose graph, and the `Mapper` that runs them
(`mapper`; in a child process with `loop.process`: `process`)."""
