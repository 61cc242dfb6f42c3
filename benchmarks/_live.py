"""What reading live statistics every step costs: a curriculum's `on_reset` against the same
wrapped rollout without it, resolved below the run-to-run noise.

Medians of a few repeats do not resolve 0.1 percentage points on an H200 (two identical
programs have read 0.4% apart). So the pair is timed in many rounds, each round running
both programs back to back in alternating order, and what is reported is the median of the
per-round overheads with a distribution-free 95% confidence interval (order statistics of
the rounds): drift of the machine between rounds cancels within a round. Beside it, the
device time each program's kernels take per step (one profiled call each), which does not
depend on the wall clock at all, and the kernels each loop body launches.
"""

import math
import statistics
from collections.abc import Sequence

from . import _profile
from ._hlo import loop_body_ops
from ._report import Table
from ._timing import Variant, measure


def median_interval(values: Sequence[float], level: float = 0.95) -> tuple[float, float]:
    """A distribution-free confidence interval for the median of `values`: the order
    statistics `(x_(k), x_(n+1-k))` with the largest `k` for which the binomial(n, 1/2)
    tail below `k` is at most `(1 - level) / 2` (the whole range when `n` is too small)."""
    xs, n = sorted(values), len(values)
    tail, k = 0.0, 0
    while True:
        nxt = tail + math.comb(n, k) / 2**n
        if nxt > (1 - level) / 2 or k + 1 > n // 2:
            break
        tail, k = nxt, k + 1
    k = max(k, 1)
    return xs[k - 1], xs[n - k]


def live_read(
    pair: Sequence[Variant], hlo: dict[str, str], steps: int, rounds: int, profile: bool = True
) -> Table:
    """`pair` = (the rollout without the read, the rollout with it), each a whole blocking
    call of a `steps`-step scan; `hlo` their compiled texts by name."""
    base, live = pair
    timings, _ = measure(pair, rounds)
    pcts = [
        (b / a - 1) * 100
        for a, b in zip(timings[base.name].samples, timings[live.name].samples, strict=True)
    ]
    med = statistics.median(pcts)
    lo, hi = median_interval(pcts)
    t = Table(
        "live_read",
        f"Reading live statistics every step: {steps}-step scan, {rounds} paired rounds",
        ["variant", "ms/step", "kernels in step loop", "device busy us/step", "kernel us/step"],
    )
    busy, kern = {}, {}
    for v in pair:
        n = sum(loop_body_ops(hlo[v.name]).values())
        if profile:
            p = _profile.profile(v.run, hlo[v.name], steps)
            busy[v.name], kern[v.name] = p.busy_us_per_step, sum(k.us_per_step for k in p.kernels)
        ms = timings[v.name].median_s / steps * 1e3
        t.add(v.name, ms, n, busy.get(v.name), kern.get(v.name))
    t.notes.append(
        f"Per round, {live.name} over {base.name}: median {med:+.3f}%, 95% CI "
        f"[{lo:+.3f}, {hi:+.3f}]% (order statistics of {rounds} rounds, each running both "
        "in alternating order); ms/step: medians over the rounds."
    )
    if profile:
        d = busy[live.name] - busy[base.name]
        step_us = timings[base.name].median_s / steps * 1e6
        t.notes.append(
            f"Device busy time (the union of the kernels' intervals in one profiled call) "
            f"the read adds: {d:+.2f} us a step, {d / step_us * 100:+.3f}% of the step."
        )
    t.data = {
        "paired_pct": pcts,
        "median_pct": med,
        "ci_pct": [lo, hi],
        "busy_us_per_step": busy,
        "kernel_us_per_step": kern,
    }
    return t
