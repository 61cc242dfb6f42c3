"""Tag names and `TagInfo`: every tag string the library writes is built here.

`<prefix>/<metric>` is the mean (the mjlab / Isaac Lab convention: `Episode_Metrics/<term>`)
and a counter's lifetime total; every other statistic is `<prefix>/<metric><suffix>` with
its suffix from the statistics registry (`_statistics`). Derived tags (a counter's
`/per_sec`, a histogram's `/underflow`) extend their metric's tag the same way. Tags are
checked for collisions (after TensorBoard's sanitization) where they are made.

Pure Python: writers import this module without importing JAX.
"""

import dataclasses
import re
from collections.abc import Iterable

from . import _statistics

# TensorBoard replaces characters outside this set with "_" (tensorboard's
# `summary/_tf/summary.py` and tensorboardX's `_clean_tag`), so distinct tags can collide.
_INVALID = re.compile(r"[^-/\w.]")


@dataclasses.dataclass(frozen=True)
class TagInfo:
    """What a report tag holds.

    Attributes:
      tag: the tag.
      group: "episode", "logged" or "counter" (`jaxmetrics.brax.ProgressFn` adds "eval"
        and "brax").
      metric: the metric (`<term>`, `<term>/<output>`, a logged name or a counter name).
      stat: the statistic (`mean`, `std`, ..., `window_p50`, `nonfinite`; `total` for a
        counter, `per_sec` for its rate).
    """

    tag: str
    group: str
    metric: str
    stat: str


def tag(prefix: str, metric: str, stat: str) -> str:
    """The tag of `metric`'s statistic `stat` under `prefix` (no prefix when empty)."""
    head = f"{prefix}/{metric}" if prefix else metric
    return head + _statistics.get(stat).suffix


def info(prefix: str, group: str, metric: str, stat: str) -> TagInfo:
    """The `TagInfo` of `metric`'s statistic `stat` (see `tag`)."""
    return TagInfo(tag(prefix, metric, stat), group, metric, stat)


def metric_tag(i: TagInfo) -> str:
    """The tag without its statistic's suffix: the metric's mean tag, one per metric."""
    suffix = _statistics.get(i.stat).suffix
    return i.tag[: len(i.tag) - len(suffix)]


def derived(i: TagInfo, stat: str) -> TagInfo:
    """Another statistic of the same metric: a counter's `per_sec`, a histogram's tails."""
    return TagInfo(metric_tag(i) + _statistics.get(stat).suffix, i.group, i.metric, stat)


def timer(prefix: str, name: str) -> str:
    """The tag of a `Logger.timer` (seconds)."""
    return f"{prefix}/{name}"


def band(mean_tag: str, side: str) -> str:
    """The tag of a mean ± std band's `side` ("lower" or "upper") in TensorBoard."""
    return f"Margin/{mean_tag}/{side}"


def sanitize(t: str) -> str:
    """The tag as TensorBoard stores it."""
    return _INVALID.sub("_", t)


def origin(i: TagInfo) -> str:
    """Where a tag comes from, for collision messages."""
    return f"{i.group} {i.metric!r} ({i.stat})"


def check_unique(tags: Iterable[tuple[str, str]]) -> None:
    """Raises if two tags are equal once TensorBoard has sanitized them.

    Args:
      tags: (tag, where it comes from) pairs.
    """
    seen: dict[str, tuple[str, str]] = {}
    for t, where in tags:
        key = sanitize(t)
        if key in seen:
            other, other_where = seen[key]
            same = "" if other == t else f" (TensorBoard turns {other!r} and {t!r} into {key!r})"
            raise ValueError(
                f"tag collision: {where} and {other_where} both write {key!r}{same}. "
                "Rename one of the metrics or use another prefix."
            )
        seen[key] = (t, where)
