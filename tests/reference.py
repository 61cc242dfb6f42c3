"""An independent host-side reference: plain Python loops over steps and envs, float64 numpy.

This is the "sequential host logger" DESIGN.md defines the semantics by: it loops over envs
in ascending index, keeps per-env episode lists, and keeps per-metric lists of values.
Nothing here imports jaxmetrics.
"""

import math
from collections import deque

import numpy as np

SIMPLE_STATS = ("mean", "std", "min", "max", "sum", "count")


def episode_value(values: list[float], reduce: str, skip_nonfinite: bool) -> float | None:
    """The value of one finished episode, or None when it has no (finite) step."""
    vals = [v for v in values if math.isfinite(v)] if skip_nonfinite else list(values)
    if not vals:
        return None
    with np.errstate(all="ignore"):  # inf - inf under "propagate" is meant to give NaN
        return _reduce(np.asarray(vals, np.float64), reduce)


def _reduce(a: np.ndarray, reduce: str) -> float:
    if reduce == "mean":
        return float(np.mean(a))
    if reduce == "sum":
        return float(np.sum(a))
    if reduce == "max":
        return float(np.max(a))
    if reduce == "min":
        return float(np.min(a))
    if reduce == "last":
        return float(a[-1])
    if reduce == "std":
        return float(np.std(a))
    raise ValueError(reduce)


def _percentile(w: np.ndarray, p: float) -> float:
    """numpy's default (linear) percentile; with infinities, the same definition without
    numpy's `inf * 0 = nan` artifact at exact order statistics."""
    if np.all(np.isfinite(w)) or np.any(np.isnan(w)):
        return float(np.percentile(w, p))
    a = np.sort(w)
    pos = p / 100 * (len(a) - 1)
    lo = math.floor(pos)
    if pos == lo:
        return float(a[lo])
    return float(a[lo] + (a[lo + 1] - a[lo]) * (pos - lo))


def episode_values(values, dones, reduce: str) -> np.ndarray:
    """Every finished episode's value in report order (by step, then env index), float64.

    `values` and `dones` are `[steps, num_envs]` records of one rollout.
    """
    values = np.asarray(values, np.float64)
    dones = np.asarray(dones, bool)
    running: list[list[float]] = [[] for _ in range(values.shape[1])]
    out = []
    for t in range(values.shape[0]):
        for e in range(values.shape[1]):
            running[e].append(float(values[t, e]))
            if dones[t, e]:
                out.append(episode_value(running[e], reduce, skip_nonfinite=False))
                running[e] = []
    return np.asarray(out, np.float64)


class RefStream:
    """Report statistics of one metric, fed value by value in arrival order."""

    def __init__(self, ema_coeff=None, window=None, percentiles=(), hist=None, skip=True):
        self.period: list[float] = []
        self.nonfinite = 0
        self.ema_coeff = ema_coeff
        self.ema: float | None = None
        self.window = deque(maxlen=window) if window else None
        self.percentiles = percentiles
        self.hist = hist  # (bins, lo, hi)
        self.skip = skip

    def add(self, v: float) -> None:
        """Adds one value; non-finite ones are dropped under "skip" (callers count them)."""
        if not math.isfinite(v) and self.skip:
            return
        self.period.append(v)
        if self.ema_coeff is not None:
            c = self.ema_coeff
            self.ema = v if self.ema is None else c * v + (1 - c) * self.ema
        if self.window is not None:
            self.window.append(v)

    def reset_period(self) -> None:
        self.period = []
        self.nonfinite = 0

    def report(self) -> dict:
        with np.errstate(all="ignore"):
            return self._report()

    def _report(self) -> dict:
        a = np.asarray(self.period, np.float64)
        n = len(a)
        out = {
            "count": n,
            "sum": float(np.sum(a)) if n else 0.0,
            "mean": float(np.mean(a)) if n else math.nan,
            "std": float(np.std(a)) if n else math.nan,
            "min": float(np.min(a)) if n else math.nan,
            "max": float(np.max(a)) if n else math.nan,
            "nonfinite": self.nonfinite,
        }
        if self.ema_coeff is not None:
            out["ema"] = math.nan if self.ema is None else self.ema
        if self.window is not None:
            w = np.asarray(self.window, np.float64)
            has = len(w) > 0
            out["window_mean"] = float(np.mean(w)) if has else math.nan
            out["window_std"] = float(np.std(w)) if has else math.nan
            out["window_min"] = float(np.min(w)) if has else math.nan
            out["window_max"] = float(np.max(w)) if has else math.nan
            padded = np.full(self.window.maxlen, np.nan)
            if has:
                padded[-len(w) :] = w
            out["window_values"] = padded
            for p in self.percentiles:
                out[f"window_p{p:g}"] = _percentile(w, p) if has else math.nan
        if self.hist is not None:
            bins, lo, hi = self.hist
            fin = a[~np.isnan(a)]
            counts, _ = np.histogram(fin, bins=bins, range=(lo, hi))
            out["histogram"] = np.concatenate(
                [[np.sum(fin < lo)], counts, [np.sum(fin > hi)]]
            ).astype(np.int64)
        return out


class RefEpisodes:
    """Per-env running episodes feeding one RefStream per metric."""

    def __init__(self, num_envs: int, metrics: dict[str, str], skip: bool = True, **stream_kw):
        self.metrics = metrics  # name -> episode reduction
        self.skip = skip
        self.running = {name: [[] for _ in range(num_envs)] for name in metrics}
        self.streams = {name: RefStream(skip=skip, **stream_kw) for name in metrics}
        self.num_envs = num_envs

    def step(self, values: dict[str, np.ndarray], done: np.ndarray) -> None:
        for name, red in self.metrics.items():
            s = self.streams[name]
            for e in range(self.num_envs):  # ascending env index
                v = float(values[name][e])
                if not math.isfinite(v):
                    s.nonfinite += 1
                self.running[name][e].append(v)
                if done[e]:
                    ev = episode_value(self.running[name][e], red, self.skip)
                    self.running[name][e] = []
                    if ev is None:
                        continue
                    if not math.isfinite(ev) and self.skip:
                        s.nonfinite += 1  # e.g. a sum that overflowed
                    s.add(ev)

    def reset_period(self) -> None:
        for s in self.streams.values():
            s.reset_period()
