"""rangeseg: range image segmentation and vacuum-gripper holdsites (Al-Hujazi & Sood, 1990).

The front door for Python users::

    from rangeseg_cli import load_config, run_pipeline
    result = run_pipeline(depth_array, load_config(preset="mm-depth"))
    result.labels, result.surfaces, result.holdsite
"""

from __future__ import annotations

from typing import Any

__version__ = "0.1.0"
__all__ = ["load_config", "run_pipeline", "__version__"]


def __getattr__(name: str) -> Any:
    # Lazy, so that `rangeseg --help` does not pay for numpy and scipy.
    if name == "load_config":
        from .config import load_config

        return load_config
    if name == "run_pipeline":
        from .pipeline import run_pipeline

        return run_pipeline
    raise AttributeError(f"module 'rangeseg_cli' has no attribute {name!r}")
