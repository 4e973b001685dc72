"""Sequences on disk: TUM RGB-D, ICL-NUIM, lab and synthetic folders (DESIGN §3).

Entry points: :func:`load_sequence` (registry name or folder → :class:`Sequence`),
:func:`list_datasets`, :func:`check_sequence`, and the TUM text readers/writers.
"""

from mutualslam_cli.datasets.associate import (
    associate,
    poses_at,
    read_list_file,
    read_tum_trajectory,
    write_tum_trajectory,
)
from mutualslam_cli.datasets.check import CheckReport, bench_loader, check_all, check_sequence
from mutualslam_cli.datasets.fy_sign import decide_fy_sign
from mutualslam_cli.datasets.icl_nuim import load_icl, load_icl_loop
from mutualslam_cli.datasets.registry import (
    detect_format,
    get_spec,
    list_datasets,
    load_sequence,
    load_spec,
    spec_from_folder,
)
from mutualslam_cli.datasets.sequence import Sequence
from mutualslam_cli.datasets.tum import load_tum

__all__ = [
    "CheckReport",
    "Sequence",
    "associate",
    "bench_loader",
    "check_all",
    "check_sequence",
    "decide_fy_sign",
    "detect_format",
    "get_spec",
    "list_datasets",
    "load_icl",
    "load_icl_loop",
    "load_sequence",
    "load_spec",
    "load_tum",
    "poses_at",
    "read_list_file",
    "read_tum_trajectory",
    "spec_from_folder",
    "write_tum_trajectory",
]
