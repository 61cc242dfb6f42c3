"""What reading live statistics every step costs: a curriculum's `on_reset` against the same
wrapped rollout without it.

Timing: the pair is timed in many rounds, each round running both programs back to back,
the order alternating from round to round (A B, B A, A B, ...). A program that follows the
other one runs once untimed first (`paired_rounds`): on an H200 the program that ran second
in a round once ran 0.3-0.8% slower, varying as much as the read costs (in that order of
rounds the second program is the one that follows the other). Each estimate averages two
consecutive rounds of opposite orders, which cancels what order effect is left and slow
drift. Reported: the median of those estimates with a distribution-free 95% interval
(their order statistics). With the untimed call, rounds of one H200 agreed within 0.03%.

What that does not remove: two loads of one program ran 0.29% apart (95% CI [0.28, 0.30]),
as steadily, and the program with the read ran 0.28% from the same first load. So the wall
clock between separately loaded programs does not resolve 0.1 pt, and a second load of
the program without the read is timed as a control. What the read adds is measured as the
device's busy time per step (the union of the kernels' intervals in one profiled call),
with the control's beside it, and the kernels each loop body launches.
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


def _estimate(pair: Sequence[Variant], rounds: int) -> tuple[dict[str, Any], dict[str, list]]:
    """`summarize` of the second of `pair` over the first in `rounds` paired rounds, with
    the switch costs; and each program's timed calls."""
    a, b = pair
    samples, switch = paired_rounds(pair, rounds)
    pcts = [(y / x - 1) * 100 for x, y in zip(samples[a.name], samples[b.name], strict=True)]
    return {**summarize(pcts), "switch_pct": switch}, samples


def interval(s: dict[str, Any]) -> str:
    """An estimate of `summarize` as its median and 95% interval: `+0.185% [+0.138, +0.231]`."""
    lo, hi = s["ci_pct"]
    return f"{s['median_pct']:+.3f}% [{lo:+.3f}, {hi:+.3f}]"


def live_read(
    trio: Sequence[Variant], hlo: dict[str, str], steps: int, rounds: int, profile: bool = True
) -> Table:
    """`trio` = (the rollout without the read, the same program loaded again, the rollout
    with the read), each a whole blocking call of a `steps`-step scan; `hlo` their
    compiled texts by name. The read and the control (the second load) are each timed
    against the first load in `rounds` paired rounds; why a control, the module says.
    """
    base, again, live = trio
    read, samples = _estimate((base, live), rounds)
    control, control_samples = _estimate((base, again), rounds)
    samples[again.name] = control_samples[again.name]
    t = Table(
        "live_read",
        f"Reading live statistics every step: {steps}-step scan, {rounds} paired rounds "
        "for the read and for a second load of the program without it",
        ["variant", "ms/step", "kernels in step loop", "device busy us/step", "kernel us/step"],
    )
    busy, kern, kinds = {}, {}, {}
    for v in trio:
        n = sum(loop_body_ops(hlo[v.name]).values())
        if profile:
            p = _profile.profile(v.run, hlo[v.name], steps)
            busy[v.name], kern[v.name] = p.busy_us_per_step, sum(k.us_per_step for k in p.kernels)
            kinds[v.name] = _kinds(p.kernels)
        ms = statistics.median(samples[v.name]) / steps * 1e3
        t.add(v.name, ms, n, busy.get(v.name), kern.get(v.name))
    t.notes.append(
        f"Over {base.name}, each estimate the mean of two consecutive rounds run in opposite "
        f"orders: {live.name} {interval(read)}, {again.name} {interval(control)} (medians, "
        f"95% intervals from the order statistics of {len(read['pair_pct'])} estimates from "
        f"{rounds} rounds each); ms/step: medians "
        "over the rounds. A call that followed the other program was run untimed first; "
        f"it took {statistics.median(read['switch_pct'] + control['switch_pct']):+.3f}% "
        "(median) over the timed call after it."
    )
    if profile:
        step_us = statistics.median(samples[base.name]) / steps * 1e6
        d, d0 = busy[live.name] - busy[base.name], busy[again.name] - busy[base.name]
        added = _added(kinds[base.name], kinds[live.name])
        t.notes.append(
            f"Device busy time (the union of the kernels' intervals in one profiled call) "
            f"the read adds: {d:+.2f} us a step, {d / step_us * 100:+.3f}% of the step; the "
            f"second load: {d0:+.2f} us ({d0 / step_us * 100:+.3f}%). Kernels the read adds "
            "(shape: fused ops, us/step, launches/step): "
            + ("; ".join(f"{k}, {us:.2f}, {n:g}" for k, us, n in added) or "none")
            + "."
        )
        read["added_kernels"] = added
    t.data = {
        **read,
        "control": control,
        "busy_us_per_step": busy,
        "kernel_us_per_step": kern,
    }
    return t
