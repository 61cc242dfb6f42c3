"""The MetricsState pytree: everything a `Metrics` spec accumulates, as fixed-shape arrays."""

from typing import NamedTuple

from ._count import Count
from ._episode import EpisodeState
from ._stream import StreamState


class MetricsState(NamedTuple):
    """One immutable pytree; fields are None where the spec has nothing of that kind.

    An empty spec gives a state with no leaves at all.
    """

    episode: EpisodeState | None  # running episodes, [rows, num_envs] per field
    episodes: StreamState | None  # report statistics over finished episodes
    logged: StreamState | None  # report statistics over logged values
    counters: Count | None  # [C] lifetime counters (exact past 2^31)
