"""`pairvpr-posegraph`: recorded odometry and replay loops through the reference pose graph."""
