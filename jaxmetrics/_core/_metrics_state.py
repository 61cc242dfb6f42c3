"""The MetricsState pytree: everything a `Metrics` spec accumulates, as fixed-shape arrays."""

import collections
import functools
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
    # [shards, K] lifetime counts per shard: env steps, episodes ended (done flags), and
    # with groups episodes of no group; then zeros up to a multiple of the episode rows.
    shard_counts: Count | None
    logged: StreamState | None  # report statistics over logged values
    counters: Count | None  # [C] lifetime counters fed by `increment`
    spec: tuple  # the spec's identity, in the tree structure only (see `spec_id`)


@functools.cache
def spec_id(fingerprint: str) -> NamedTuple:
    """The identity of the spec with this configuration fingerprint: a namedtuple whose
    one field is named after the fingerprint and holds None.

    It holds no leaves, so it costs nothing, and it goes wherever the tree structure
    goes: through `jit`, `scan` and `vmap` (a state of another spec is told apart at
    trace time), and into flax.serialization and orbax checkpoints, which store the
    field name and refuse to restore it into a state of another spec. Specs built with
    the same configuration share it, so a state checkpointed by one process restores
    into the same spec built in another.
    """
    return collections.namedtuple("MetricsSpec", [f"config_{fingerprint[:24]}"])(None)
