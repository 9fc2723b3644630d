"""Geometry primitives shared by every stage: file I/O, surface sampling, voxels, SE(3), NCC."""
