"""mslam: online mutual adaptation of deep depth prediction and visual SLAM.

Library entry points: :func:`mutualslam_cli.pipeline.run_sequence`,
:func:`mutualslam_cli.metrics.trajectory.ate`, :mod:`mutualslam_cli.datasets`.
"""

from __future__ import annotations

import logging

from mutualslam_cli.errors import ConfigError, DatasetError, MslamError, ShapeError

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["ConfigError", "DatasetError", "MslamError", "ShapeError", "__version__"]
