"""Numerical core: numpy, scipy and open3d only (never rclpy, yaml, argparse or tqdm)."""
