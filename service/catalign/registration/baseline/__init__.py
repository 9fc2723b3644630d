"""Baselines used only for comparison: the classic FPFH + RANSAC + ICP recipe (Open3D)."""
