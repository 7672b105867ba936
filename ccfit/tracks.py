"""The curriculum tracks by name: what `ccfit sweep --track` and a sweep's jobs dispatch on.
A new track is one `ccfit.runner.Track` class, listed in `TRACKS`."""

from __future__ import annotations

from ccfit.curriculum import OnlineTrack
from ccfit.offline.run import OfflineTrack
from ccfit.runner import Track

TRACKS: dict[str, type[Track]] = {t.name: t for t in (OnlineTrack, OfflineTrack)}


def track_of(config: dict) -> type[Track]:
    """The track of a run's config as plain data (config.json, sweep.json): the one whose loop
    settings it holds (`train` online, `fit` offline)."""
    return next(t for t in TRACKS.values() if t.loop in config)
