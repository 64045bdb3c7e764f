"""The batch runner: images in, files out.

Atomic writes, the manifest, resuming, Dask; pictures, point clouds, the
Rerun log and the HTML report.
"""
