"""Side-by-side odometry benchmark: paper ICP, our registration, each with and without the
graph-frequency filter, and kiss-icp, on the same simulated scans with the same clock and the
same metrics code (`gft_odom.replay.summarize`)."""
