"""Global SLAM: loop closure by branch-and-bound matching against finished submaps, GTSAM pose graph."""
