"""Tag names: stable, documented, checked for collisions when the spec is built.

`<prefix>/<metric>` is the mean (the mjlab / Isaac Lab convention: `Episode_Metrics/<term>`),
every other statistic is `<prefix>/<metric>/<stat>`.
"""

import re
from collections.abc import Iterable

# TensorBoard replaces characters outside this set with "_" (tensorboard's
# `summary/_tf/summary.py` and tensorboardX's `_clean_tag`), so distinct tags can collide.
_INVALID = re.compile(r"[^-/\w.]")

STAT_SUFFIX = {
    "mean": "",
    "std": "/std",
    "min": "/min",
    "max": "/max",
    "sum": "/sum",
    "count": "/count",
    "ema": "/ema",
    "window_mean": "/window_mean",
    "window_std": "/window_std",
    "window_min": "/window_min",
    "window_max": "/window_max",
    "window_values": "/window_values",
    "histogram": "/histogram",
    "nonfinite": "/nonfinite",
    "running": "/running",
}


def tag(prefix: str, metric: str, stat: str) -> str:
    suffix = STAT_SUFFIX.get(stat)
    if suffix is None:  # window percentiles: window_p50, window_p99.9
        suffix = "/" + stat
    return f"{prefix}/{metric}{suffix}" if prefix else f"{metric}{suffix}"


def sanitize(t: str) -> str:
    return _INVALID.sub("_", t)


def check_unique(tags: Iterable[tuple[str, str]]) -> None:
    """Raises if two tags are equal once TensorBoard has sanitized them.

    Args:
      tags: (tag, where it comes from) pairs.
    """
    seen: dict[str, tuple[str, str]] = {}
    for t, origin in tags:
        key = sanitize(t)
        if key in seen:
            other, other_origin = seen[key]
            same = "" if other == t else f" (TensorBoard turns {other!r} and {t!r} into {key!r})"
            raise ValueError(
                f"tag collision: {origin} and {other_origin} both write {key!r}{same}. "
                "Rename one of the metrics or use another prefix."
            )
        seen[key] = (t, origin)
