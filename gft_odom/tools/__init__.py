"""User-facing front ends: the `gft-odom` CLI, progress bars, tables, figures."""
