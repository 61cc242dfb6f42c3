"""The registry of episode reductions: how a term's per-step values become one value per
episode. Validation and its message (here) and the reductions `success_rate` accepts (with
what each says about a flag) derive from `REDUCTIONS`. (`_episode` lays its accumulators
out in its own block order; `tests/test_layout.py` checks it covers the same names.)
"""

from typing import Any, NamedTuple


class Reduction(NamedTuple):
    """One episode reduction.

    Attributes:
      name: what `Term(reduce=...)` takes.
      meaning: what it computes over the steps of one episode, per env.
      of_a_flag: what it says about a 0/1 flag (a success flag), or None where the
        result is not a rate or a flag.
    """

    name: str
    meaning: str
    of_a_flag: str | None


REDUCTIONS = (
    Reduction("mean", "the per-step average", "fraction of steps"),
    Reduction("sum", "the return-style sum over the episode", None),
    Reduction("max", "the largest value", "at any step"),
    Reduction("min", "the smallest value", "at every step"),
    Reduction("last", "the value on the episode's last step", "at episode end"),
    Reduction("std", "the population std of the per-step values, ddof 0", None),
)

NAMES = tuple(r.name for r in REDUCTIONS)
"""Every reduction's name, as `Term(reduce=...)` takes it."""

FLAG_REDUCTIONS = {r.name: r.of_a_flag for r in REDUCTIONS if r.of_a_flag is not None}
"""The reductions of a 0/1 flag that give a rate or a flag, and what each says."""


def check(reduce: Any, where: str) -> str:
    """`reduce` if it is a reduction's name.

    Raises:
      ValueError: naming `where` and the valid names.
    """
    if reduce not in NAMES:
        choices = ", ".join(f"{r.name!r} ({r.meaning})" for r in REDUCTIONS)
        raise ValueError(
            f"{where}: unknown episode reduction {reduce!r}; expected one of {choices}."
        )
    return reduce
