"""The curriculum tracks by name: what `ccfit sweep --track` and a sweep's jobs dispatch on.
A new track is one `ccfit.runner.Track` class, listed in `TRACKS`."""

from __future__ import annotations

from ccdata.errors import InputError
from ccfit.curriculum import OnlineTrack
from ccfit.offline.run import OfflineTrack
from ccfit.runner import Track

TRACKS: dict[str, type[Track]] = {t.name: t for t in (OnlineTrack, OfflineTrack)}


def track_of(config: dict) -> type[Track]:
    """The track of a run's config as plain data (config.json, sweep.json): the one whose loop
    settings it holds (`train` online, `fit` offline)."""
    found = [t for t in TRACKS.values() if t.loop in config]
    if len(found) != 1:
        loops = " or ".join(f"'{t.loop}'" for t in TRACKS.values())
        raise InputError(
            f"a run config holds exactly one of the loops {loops} (which names "
            f"its track), this one {len(found)}: not a ccfit run's config"
        )
    return found[0]
