"""gft_odom: LiDAR odometry with graph-frequency filtering of each scan before ICP."""

__version__ = '1.0.0'
