"""What reading live statistics every step costs: a curriculum's `on_reset` against the same
wrapped rollout without it, resolved below the run-to-run noise.

Medians of a few repeats do not resolve 0.1 percentage points on an H200 (two identical
programs have read 0.4% apart). So the pair is timed in many rounds, each round running
both programs back to back, the order alternating from round to round (A B, B A, A B, ...).
On an H200 the program that ran second in a round ran 0.3-0.8% slower than when it ran
first (21 rounds of `ant`, 4,096 envs), more than the read costs and varying as much; in
that order of rounds the second program of a round is the one that follows the other
program, the first follows itself. So a run that follows the other program is not timed:
it runs once untimed first (`paired_rounds`), and what a switch costs is recorded apart.
Each estimate still averages two consecutive rounds of opposite orders, which cancels
what order effect is left and slow drift. Reported: the median of those estimates with a
distribution-free 95% confidence interval (their order statistics). Beside it, the device
time each program's kernels take per step (one profiled call each), which does not depend
on the wall clock at all, and the kernels each loop body launches.
"""

import math
import statistics
import time
from collections.abc import Sequence
from typing import Any

from . import _profile
from ._hlo import loop_body_ops
from ._report import Table
from ._timing import Variant


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


def summarize(pcts: Sequence[float]) -> dict[str, Any]:
    """From the per-round overheads of the second variant over the first (`pcts`, rounds
    alternating which of the two runs first, the first round the first variant), the
    order-balanced estimates (the mean of rounds 2j and 2j + 1), their median and 95%
    interval, and the mean slowdown of whichever program ran second in its round."""
    if len(pcts) < 2:
        raise ValueError(
            f"the live read's estimates pair a round of each order: {len(pcts)} round(s) "
            "timed; give --e2e-live-rounds 2 or more (an even number uses every round)"
        )
    pair = [(pcts[j] + pcts[j + 1]) / 2 for j in range(0, len(pcts) - 1, 2)]
    order = [(pcts[j] - pcts[j + 1]) / 2 for j in range(0, len(pcts) - 1, 2)]
    lo, hi = median_interval(pair)
    return {
        "paired_pct": list(pcts),
        "pair_pct": pair,
        "median_pct": statistics.median(pair),
        "ci_pct": [lo, hi],
        "order_pct": statistics.mean(order),
    }


def paired_rounds(
    pair: Sequence[Variant], rounds: int
) -> tuple[dict[str, list[float]], list[float]]:
    """Times `pair` = (a, b) in `rounds` rounds, a then b in even rounds and b then a in
    odd ones, after a warm-up call of each (b's first, so that a follows itself). A
    program that follows the other one runs once untimed before its timed call. Returns
    each program's timed calls (seconds, one a round), and each untimed call's time over
    the timed call after it (%): what a switch of program costs the call after it."""
    a, b = pair
    b.run()
    a.run()
    last, samples, switch = a.name, {a.name: [], b.name: []}, []
    for r in range(rounds):
        for v in (a, b) if r % 2 == 0 else (b, a):
            untimed = None
            if v.name != last:
                t0 = time.perf_counter()
                v.run()
                untimed = time.perf_counter() - t0
            t0 = time.perf_counter()
            v.run()
            samples[v.name].append(time.perf_counter() - t0)
            last = v.name
            if untimed is not None:
                switch.append((untimed / samples[v.name][-1] - 1) * 100)
    return samples, switch


def _kinds(kernels: Sequence[_profile.Kernel]) -> dict[str, tuple[float, float]]:
    """Per kind of kernel (`shape: fused ops`, which two compiles of one program share where
    their kernel names differ), its us and launches per step, summed over the kernels."""
    out: dict[str, tuple[float, float]] = {}
    for k in kernels:
        key = f"{k.shape}: {k.ops}" if k.shape or k.ops else k.name
        us, n = out.get(key, (0.0, 0.0))
        out[key] = (us + k.us_per_step, n + k.launches_per_step)
    return out


def _added(
    base: dict[str, tuple[float, float]], live: dict[str, tuple[float, float]]
) -> list[tuple[str, float, float]]:
    """The kinds of kernel `live` launches more often a step than `base`, with the extra
    device time and launches, most launches first."""
    out = []
    for key, (us, n) in live.items():
        b_us, b_n = base.get(key, (0.0, 0.0))
        if n > b_n + 1e-9:
            out.append((key, us - b_us, n - b_n))
    return sorted(out, key=lambda a: (-a[2], -a[1]))


def live_read(
    pair: Sequence[Variant], hlo: dict[str, str], steps: int, rounds: int, profile: bool = True
) -> Table:
    """`pair` = (the rollout without the read, the rollout with it), each a whole blocking
    call of a `steps`-step scan; `hlo` their compiled texts by name."""
    base, live = pair
    samples, switch = paired_rounds(pair, rounds)
    pcts = [(b / a - 1) * 100 for a, b in zip(samples[base.name], samples[live.name], strict=True)]
    s = summarize(pcts)
    med, (lo, hi) = s["median_pct"], s["ci_pct"]
    t = Table(
        "live_read",
        f"Reading live statistics every step: {steps}-step scan, {rounds} paired rounds",
        ["variant", "ms/step", "kernels in step loop", "device busy us/step", "kernel us/step"],
    )
    busy, kern, kinds = {}, {}, {}
    for v in pair:
        n = sum(loop_body_ops(hlo[v.name]).values())
        if profile:
            p = _profile.profile(v.run, hlo[v.name], steps)
            busy[v.name], kern[v.name] = p.busy_us_per_step, sum(k.us_per_step for k in p.kernels)
            kinds[v.name] = _kinds(p.kernels)
        ms = statistics.median(samples[v.name]) / steps * 1e3
        t.add(v.name, ms, n, busy.get(v.name), kern.get(v.name))
    t.notes.append(
        f"{live.name} over {base.name}, each estimate the mean of two consecutive rounds "
        f"run in opposite orders: median {med:+.3f}%, 95% CI [{lo:+.3f}, {hi:+.3f}]% "
        f"(order statistics of {len(s['pair_pct'])} estimates from {rounds} rounds); the "
        f"second program of a round ran {s['order_pct']:+.3f}% slower than the first (mean); "
        "ms/step: medians over the rounds. A call that followed the other program was run "
        "untimed first"
        + (
            f"; it took {statistics.median(switch):+.3f}% (median of {len(switch)}) over "
            "the timed call after it."
            if switch
            else "."
        )
    )
    if profile:
        d = busy[live.name] - busy[base.name]
        step_us = statistics.median(samples[base.name]) / steps * 1e6
        added = _added(kinds[base.name], kinds[live.name])
        t.notes.append(
            f"Device busy time (the union of the kernels' intervals in one profiled call) "
            f"the read adds: {d:+.2f} us a step, {d / step_us * 100:+.3f}% of the step. "
            "Kernels it adds (shape: fused ops, us/step, launches/step): "
            + ("; ".join(f"{k}, {us:.2f}, {n:g}" for k, us, n in added) or "none")
            + "."
        )
        s["added_kernels"] = added
    t.data = {
        **s,
        "switch_pct": switch,
        "busy_us_per_step": busy,
        "kernel_us_per_step": kern,
    }
    return t
