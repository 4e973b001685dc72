"""What Algorithm 1's loop reads of its run (:class:`OnlineRun`): the stages' ``RunContext`` has it, and a test
may pass anything that does; the loop never writes a run file or a summary key (the adaptation stage does)."""

from __future__ import annotations

from typing import Protocol

import torch

from mutualslam_cli.config import RunConfig
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.types import Progress


class OnlineRun(Protocol):
    """The run as the online loop sees it: its sequence, resolved config, device and progress callback."""

    seq: Sequence
    cfg: RunConfig
    device: torch.device
    progress: Progress | None
