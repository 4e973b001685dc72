"""What a preset was tuned on: the ``# tuned-on:`` line of a config file's header.

A preset whose settings were chosen by reading accuracies on some sequences names them in its header
(``# tuned-on: tum_fr1_xyz, icl_lr_kt2``; ``# tuned-on: none`` for the paper's values), so that a figure
measured on those very sequences can be refused (:mod:`mutualslam_cli.book`: a preset is reported only on
data that had no say in it).
"""

from __future__ import annotations

import re
from pathlib import Path

from mutualslam_cli.config.yaml_file import read_text_file
from mutualslam_cli.errors import ConfigError

_LINE = re.compile(r"^#\s*tuned-on:\s*(?P<names>.*?)\s*$")


def tuned_on(path: str | Path) -> list[str] | None:
    """The sequences a preset was tuned on, from its first ``# tuned-on:`` comment line (``[]`` for
    ``none``); ``None`` when the file has no such line (unknown: a caller should assume the worst).

    Raises:
        ConfigError: the file cannot be read (missing, not UTF-8).
    """
    for line in read_text_file(path, ConfigError, "YAML config file").splitlines():
        m = _LINE.match(line.strip())
        if m:
            names = [n.strip() for n in m.group("names").split(",") if n.strip()]
            return [] if names in ([], ["none"]) else names
    return None
