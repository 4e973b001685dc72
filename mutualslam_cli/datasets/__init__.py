"""Sequences on disk: TUM RGB-D, ICL-NUIM, 7-Scenes, lab, recorded and synthetic folders (DESIGN §3).

The top level is what every run reads: the :class:`Sequence` type (:mod:`.sequence`), the TUM text files
(:mod:`.associate`, :mod:`.layout`, :mod:`.image_files`), the loaders of each format (:mod:`.tum`,
:mod:`.icl_nuim`, the fy sign: :mod:`.fy_sign`), another network's saved predictions (:mod:`.predictions`),
the registry (:mod:`.registry`: a ``datasets.yaml`` name, folder or recording → :class:`Sequence`) and the
check (:mod:`.check`); :mod:`.splice` cuts and splices a TUM folder into a new one (re-entry sequences).
Three sub-packages own what only some commands need:

- :mod:`.recordings`: the user's own bags, videos and image folders, converted to the TUM layout;
- :mod:`.synthetic`: rendered rooms with exact depth and poses;
- :mod:`.download`: ``mslam datasets download``, fetching and unpacking published archives safely.

May import: the ground floor only (errors, types, geometry, pixels, atomic). Inside, the arrows point one
way: the file formats import no sub-package; ``recordings`` and ``synthetic`` import only the file
formats; the registry imports ``recordings`` (to open a recording); ``download`` imports the registry and
the check; nothing at the top imports ``download`` or ``synthetic`` (``tests/test_imports.py`` holds it).

Entry points: :func:`load_sequence` (registry name or folder → :class:`Sequence`), :func:`list_datasets`,
:func:`check_sequence`, and the TUM text readers/writers.
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
