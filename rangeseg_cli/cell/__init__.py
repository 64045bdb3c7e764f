"""The robot cell: what may be picked.

The support, the background, the region of interest and the camera's
intrinsics.
"""
