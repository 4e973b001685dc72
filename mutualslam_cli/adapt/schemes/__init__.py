"""Adaptation schemes registry: ``SCHEMES[name]`` → :class:`Scheme` subclass (DESIGN §5).

Add a scheme by subclassing :class:`Scheme` (batch selection, photometric sources, regulariser) and
registering it here.
"""

from __future__ import annotations

from mutualslam_cli.adapt.schemes.base import NoTraining, Scheme
from mutualslam_cli.adapt.schemes.comoda import Comoda
from mutualslam_cli.adapt.schemes.luo import Luo
from mutualslam_cli.adapt.schemes.recent import Recent, RecentEWC
from mutualslam_cli.adapt.schemes.replay import Replay, ReplayEWC, ReplayMAS, ReplaySI
from mutualslam_cli.config import AdaptConfig
from mutualslam_cli.errors import ConfigError

SCHEMES: dict[str, type[Scheme]] = {
    cls.name: cls for cls in (NoTraining, Recent, Replay, RecentEWC, ReplayEWC, ReplayMAS, ReplaySI, Luo, Comoda)
}


def get_scheme(name: str, cfg: AdaptConfig | None = None) -> Scheme:
    """Instantiate the scheme registered as ``name`` with the settings ``cfg`` (default: the defaults).

    Raises:
        ConfigError: unknown name (the message lists the valid ones), or a setting of the scheme out of range.
    """
    try:
        cls = SCHEMES[name]
    except KeyError:
        raise ConfigError(f"adapt.scheme: unknown scheme {name!r}; valid schemes: {sorted(SCHEMES)}") from None
    return cls(cfg)


__all__ = ["SCHEMES", "Scheme", "get_scheme"]
