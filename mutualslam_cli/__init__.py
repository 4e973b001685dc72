"""mslam: online mutual adaptation of deep depth prediction and visual SLAM.

Library entry points: :func:`mutualslam_cli.pipeline.run_sequence`,
:func:`mutualslam_cli.metrics.trajectory.ate`, :mod:`mutualslam_cli.datasets`.
"""

from __future__ import annotations

import logging
import os

from mutualslam_cli.errors import ConfigError, DatasetError, MslamError, ShapeError  # no torch: before the setting

#: How long an idle OpenMP thread spins before it sleeps (GNU OpenMP, torch's CPU runtime), set before torch is
#: loaded unless the environment sets it. The default (300 000) makes a step several times slower whenever another
#: process takes one of the cores torch's threads run on (every barrier waits on a descheduled spinner); 10 000
#: stays near the fair share there and changes nothing measurable on a quiet machine (``mslam bench contention``).
OMP_SPINCOUNT = "10000"
os.environ.setdefault("GOMP_SPINCOUNT", OMP_SPINCOUNT)

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = ["ConfigError", "DatasetError", "MslamError", "ShapeError", "__version__"]
