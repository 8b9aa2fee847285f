"""Leaf numerics shared by every structure and by the CPU and GPU targets (STYLE §4.2)."""
