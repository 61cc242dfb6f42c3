"""A `progress_fn` for Brax's own PPO trainer that writes through jaxmetrics writers.

Brax's `brax.training.agents.ppo.train` reports already-reduced host values to
`progress_fn(step, metrics)`; `ProgressFn` renames them to jaxmetrics' tags and hands one
`Record` per call to the writers, so a Brax run and a jaxmetrics training loop land in
the same TensorBoard layout.
"""

import threading
import time
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._core import _tags
from .._core._tags import TagInfo
from .._host._record import RecordBuilder, Writer, check_writers

# Brax PPO's learner values (brax/training/agents/ppo/losses.py) -> jaxmetrics names.
_LEARNER_NAMES = {
    "policy_loss": "policy_loss",
    "v_loss": "value_loss",
    "entropy_loss": "entropy_loss",
    "total_loss": "total_loss",
    "kl_mean": "approx_kl",
    "learning_rate": "learning_rate",
}
# Brax's episode sums (EpisodeWrapper's `sum_reward`/`length`, the Evaluator's `reward`).
_EPISODE_NAMES = {
    "sum_reward": "episode_return",
    "reward": "episode_return",
    "length": "episode_length",
}


def _learner(name: str) -> str | None:
    if name in _LEARNER_NAMES:
        return _LEARNER_NAMES[name]
    return name if name.startswith("policy_dist_") else None


class ProgressFn:
    """`progress_fn` for `brax.training.agents.ppo.train`, writing through jaxmetrics writers.

    Each call writes one `Record` at `step` (Brax's env steps) to every writer. Brax's keys
    become these tags (prefixes configurable):

    - `eval/episode_reward`, `eval/avg_episode_length`, `eval/episode_<m>` (Brax's
      Evaluator: one episode per eval env, with its deterministic policy by default) ->
      `Eval_Metrics/episode_return`, `Eval_Metrics/episode_length`, `Eval_Metrics/<m>`,
      and their `_std` / `std_` forms -> `.../std`. Brax sums every `State.metrics` entry
      over the eval episode (divided by the length for names ending in `_per_step`).
    - `training/<loss>` (means over the epoch's gradient steps) -> `Train/<name>`:
      `policy_loss`, `v_loss` -> `value_loss`, `entropy_loss`, `total_loss`, `kl_mean` ->
      `approx_kl` (Brax's closed-form KL between the old and new action distributions),
      `learning_rate`, `policy_dist_*`. The values are Brax's own (e.g. its `v_loss`
      includes its `vf_loss_coefficient`).
    - `episode/sum_reward`, `episode/length`, `episode/<m>` (with
      `log_training_metrics=True`: means over the last 100 training episodes) ->
      `Episode_Metrics/episode_return/window_mean`, `.../episode_length/window_mean`,
      `Episode_Metrics/<m>/window_mean`: the `window(100)` mean of a jaxmetrics term.
      Learner values in that stream (`episode/policy_loss`, ...: means over the last 100
      gradient steps) -> `Train/<name>/window_mean`.
    - `Counters/env_steps`: `step`, and `Counters/env_steps/per_sec`: its growth per
      second of wall time since the previous call with a larger step (as `Logger`
      computes it). Brax's own timings and rates (`training/sps`, `eval/walltime`, ...)
      -> `Brax/<key>`; any other key -> `Brax/<key>` as well.

    Non-finite values are left out of the record (a gap, never a fake 0). Writers are
    opened on the first call, with the tags of that call (the TensorBoard mean ± std
    layout covers the metrics of that call), so a run that fails before Brax's first
    report leaves no event file; they are closed by `close()` (or leaving a `with`
    block). Calls are serialized (Brax may call from a callback thread).

    Brax 0.14.2's `ppo.train` itself calls `jax.device_put_replicated`, which JAX 0.10
    removed from its public namespace: on that pair of versions it fails before training,
    whatever `progress_fn`, unless the name is restored first (docs/brax.md's "Brax's own
    trainer" shows the three lines).

    Args:
      writers: jaxmetrics writers, e.g. `[jaxmetrics.TensorBoardWriter(logdir)]`.
      eval_prefix: tag prefix of Brax's eval episodes.
      episode_prefix: tag prefix of Brax's training-episode windows.
      logged_prefix: tag prefix of learner values.
      counter_prefix: tag prefix of the env-step counter.
      other_prefix: tag prefix of everything else.

    Examples:
      >>> import jaxmetrics as jm, jaxmetrics.brax as jmb
      >>> memory = jm.MemoryWriter()
      >>> with jmb.ProgressFn([memory]) as progress_fn:   # ppo.train(..., progress_fn=...)
      ...     progress_fn(0, {"eval/episode_reward": 4.5, "eval/episode_reward_std": 1.5})
      ...     progress_fn(2048, {"training/v_loss": 0.25, "training/sps": 900.0})
      >>> for tag, value in memory.records[0].scalars.items():
      ...     print(tag, value)
      Counters/env_steps 0
      Eval_Metrics/episode_return 4.5
      Eval_Metrics/episode_return/std 1.5
      >>> [t for t in memory.records[1].scalars if not t.endswith("/per_sec")]
      ['Counters/env_steps', 'Train/value_loss', 'Brax/training/sps']
    """

    def __init__(
        self,
        writers: Sequence[Writer],
        *,
        eval_prefix: str = "Eval_Metrics",
        episode_prefix: str = "Episode_Metrics",
        logged_prefix: str = "Train",
        counter_prefix: str = "Counters",
        other_prefix: str = "Brax",
    ):
        self._writers = check_writers(writers, "ProgressFn")
        prefixes = (eval_prefix, episode_prefix, logged_prefix, counter_prefix, other_prefix)
        for p in prefixes:
            if not isinstance(p, str) or not p:
                raise ValueError(f"ProgressFn: prefixes must be non-empty strings, got {p!r}.")
        if len(set(prefixes)) != len(prefixes):
            raise ValueError(f"ProgressFn: prefixes must differ, got {prefixes!r}.")
        self._eval, self._episode, self._logged = eval_prefix, episode_prefix, logged_prefix
        self._other = other_prefix
        self._counter = _tags.info(counter_prefix, "counter", "env_steps", "total")
        self._records = RecordBuilder({})
        self._lock = threading.Lock()
        self._opened = self._closed = False
        self._last_step: int | None = None

    def tag_info(self, key: str, metrics: Mapping[str, Any]) -> TagInfo:
        """Where Brax's `key` goes (`metrics` is the call's dict: a `_std` key is a std
        only when its mean is in it too)."""
        space, _, name = key.partition("/")
        if space == "eval":
            if name in ("avg_episode_length", "std_episode_length"):
                stat = "mean" if name.startswith("avg") else "std"
                return _tags.info(self._eval, "eval", "episode_length", stat)
            if name.startswith("episode_"):
                metric, stat = name[len("episode_") :], "mean"
                if metric.endswith("_std") and f"eval/episode_{metric[:-4]}" in metrics:
                    metric, stat = metric[:-4], "std"
                return _tags.info(self._eval, "eval", _EPISODE_NAMES.get(metric, metric), stat)
        elif space == "training" and name not in ("sps", "walltime"):
            return _tags.info(self._logged, "logged", _learner(name) or name, "mean")
        elif space == "episode" and name != "sps":
            learner = _learner(name)
            if learner is not None:
                return _tags.info(self._logged, "logged", learner, "window_mean")
            metric = _EPISODE_NAMES.get(name, name)
            return _tags.info(self._episode, "episode", metric, "window_mean")
        return _tags.info(self._other, "brax", key, "mean")

    def __call__(self, step: Any, metrics: Mapping[str, Any]) -> None:
        """Writes Brax's `metrics` at `step` (what `ppo.train` passes to `progress_fn`)."""
        if not isinstance(metrics, Mapping):
            raise TypeError(f"ProgressFn: metrics must be a dict, got {type(metrics).__name__}.")
        step = int(step)
        infos = [self.tag_info(k, metrics) for k in metrics]
        values: list[tuple[TagInfo, Any]] = [(self._counter, step)]
        for key, info in zip(metrics, infos):
            v = np.asarray(metrics[key])
            if v.size != 1 or not np.issubdtype(v.dtype, np.number):
                raise TypeError(
                    f"ProgressFn: Brax metric {key!r} is {v.dtype}{list(v.shape)}; expected a "
                    "number."
                )
            if any(info.tag == seen.tag for seen, _ in values):
                raise ValueError(f"ProgressFn: {key!r} and another key both map to {info.tag!r}.")
            values.append((info, float(v.reshape(()))))
        with self._lock:
            if self._closed:
                raise RuntimeError("ProgressFn: called after close(); create a new one.")
            # Brax calls twice at one step (training windows, then eval and learner values):
            # the env-step rate spans steps, not calls.
            new_point = self._last_step is None or step > self._last_step
            if new_point:
                self._last_step = step
            record = self._records(values, step, time.time(), {}, new_point=new_point)
            if not self._opened:
                self._opened = True
                rate = _tags.derived(self._counter, "per_sec")
                for w in self._writers:
                    w.open((self._counter, rate, *infos))
            for w in self._writers:
                w.write(record)

    def close(self) -> None:
        """Closes the writers (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        for w in self._writers:
            w.close()

    def __enter__(self) -> "ProgressFn":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
