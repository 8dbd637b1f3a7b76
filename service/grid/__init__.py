"""Maps a planner can use (issue 25): a 2-D occupancy grid per keyframe from its depth
(`local`), stored with the node; the map's global grid assembled from the optimised poses
(`assembly`, `maps`); paths on it (`path`); the coloured point cloud (`cloud`); the files
(`files`). See docs/grid.md."""
