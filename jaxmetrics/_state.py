"""The MetricsState pytree: everything a `Metrics` spec accumulates, as fixed-shape arrays."""

from typing import NamedTuple

from ._count import Count
from ._episode import EpisodeState
from ._stream import StreamState


class MetricsState(NamedTuple):
    """One immutable pytree; fields are None where the spec has nothing of that kind.

    Finished-episode statistics are kept per env shard (a leading `[shards]` axis): shard
    `i` folds only the `i`-th contiguous block of envs, so a step needs no communication
    between devices when the envs are split over them; `Metrics.compute` merges the
    shards. An empty spec gives a state with no leaves at all.
    """

    running: EpisodeState | None  # running episodes, [rows, num_envs] per field
    finished: StreamState | None  # per shard: report statistics over finished episodes
    ended: Count | None  # [shards] episodes ended (done flags) per shard, lifetime
    logged: StreamState | None  # report statistics over logged values
    counters: Count | None  # [C] lifetime counters, "episodes" excepted (see `ended`)
