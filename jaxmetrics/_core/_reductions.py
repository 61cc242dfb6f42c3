"""The registry of episode reductions: how a term's per-step values become one value per
episode. Validation and its message (here) and the reductions `success_rate` accepts (with
what each says about a flag) derive from `REDUCTIONS`. (`_episode` lays its accumulators
out in its own block order; `tests/test_layering.py` checks it covers the same names.)
"""

import dataclasses
from typing import Any, NamedTuple

from ._validate import is_number


class Reduction(NamedTuple):
    """One episode reduction.

    Attributes:
      name: what `Term(reduce=...)` takes.
      meaning: what it computes over the steps of one episode, per env.
      of_a_flag: what it says about a 0/1 flag (a success flag), or None where the
        result is not a rate or a flag.
      builder: for a reduction with a parameter, the call that makes it (`Term(reduce=...)`
        takes what it returns, not the name); None for one named by a string.
    """

    name: str
    meaning: str
    of_a_flag: str | None
    builder: str | None = None


REDUCTIONS = (
    Reduction("mean", "the per-step average", "fraction of steps"),
    Reduction("sum", "the return-style sum over the episode", None),
    Reduction("max", "the largest value", "at any step"),
    Reduction("min", "the smallest value", "at every step"),
    Reduction("last", "the value on the episode's last step", "at episode end"),
    Reduction("std", "the population std of the per-step values, ddof 0", None),
    Reduction(
        "discounted",
        "the discounted return sum(gamma^t x_t), t = 0 on the episode's first step",
        None,
        "jaxmetrics.discounted(gamma)",
    ),
)

NAMES = tuple(r.name for r in REDUCTIONS)
"""Every reduction's name (a parametrized one's is its `Discounted`'s `name`)."""

FLAG_REDUCTIONS = {r.name: r.of_a_flag for r in REDUCTIONS if r.of_a_flag is not None}
"""The reductions of a 0/1 flag that give a rate or a flag, and what each says."""


@dataclasses.dataclass(frozen=True)
class Discounted:
    """The discounted-return episode reduction: `sum_t gamma^t x_t` over the episode's
    steps, `t = 0` on its first step (see `discounted`)."""

    gamma: float
    name = "discounted"


def discounted(gamma: float) -> Discounted:
    """Episode reduction: the discounted return `sum_t gamma^t x_t`, `t = 0` on the
    episode's first step, for `Term(reduce=...)`.

    `t` counts every step of the episode, a non-finite step left out under the "skip"
    policy included (it adds nothing, later steps keep their discount); under
    `jaxmetrics.brax` with `action_repeat > 1` every physics sub-step is a step. `gamma`
    must be in (0, 1]; it is checked, naming the term, when the `Metrics` spec is built.

    Examples:
      >>> import jax.numpy as jnp, jaxmetrics as jm
      >>> m = jm.Metrics(terms={"ret": jm.Term(lambda r: r, reduce=jm.discounted(0.5))})
      >>> s = m.update(m.init(1), jnp.ones(1), jnp.zeros(1, bool))
      >>> s = m.update(s, jnp.ones(1), jnp.ones(1, bool))
      >>> m.to_host(m.compute(s))["Episode_Metrics/ret"]   # 1 + 0.5 * 1
      1.5
    """
    return Discounted(gamma)


def name(reduce: str | Discounted) -> str:
    """The registry name of a checked reduction."""
    return reduce.name if isinstance(reduce, Discounted) else reduce


def check(reduce: Any, where: str) -> str | Discounted:
    """`reduce` if it is a reduction's name or a valid `Discounted` (its gamma a float).

    Raises:
      ValueError: naming `where`, the problem and the fix.
    """
    if isinstance(reduce, Discounted):
        g = reduce.gamma
        if not is_number(g) or not (0.0 < g <= 1.0):
            raise ValueError(
                f"{where}: discounted(gamma) needs gamma in (0, 1], got {g!r}. Use e.g. "
                "reduce=jaxmetrics.discounted(0.99)."
            )
        return Discounted(float(g))
    builders = {r.name: r.builder for r in REDUCTIONS if r.builder is not None}
    if isinstance(reduce, str) and reduce in builders:
        raise ValueError(
            f"{where}: the {reduce!r} reduction takes a parameter; use "
            f"reduce={builders[reduce]}, e.g. reduce=jaxmetrics.discounted(0.99)."
        )
    if reduce not in NAMES:
        choices = ", ".join(f"{r.builder or repr(r.name)} ({r.meaning})" for r in REDUCTIONS)
        raise ValueError(
            f"{where}: unknown episode reduction {reduce!r}; expected one of {choices}."
        )
    return reduce
