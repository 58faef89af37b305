"""Data in and out: PointCloud2 codec, bags (through rosbags, imported lazily), trajectories.

Submodules: `pointcloud2` (codec), `bags` (ScanBagReader, read_odometry, BagWriter),
`ground_truth` (read_ground_truth, GroundTruthConfig), `tum` (read_tum, write_tum), `pcd`
(write_pcd, read_pcd: PCD files with per-point frequency and band).
"""
