"""Reporting from inside an env wrapper, for trainers that keep the env state to themselves.

Brax's `ppo.train`, Playground's training script and any jitted loop that steps an env
without handing its state back give the user no place to call `Logger.flush`. A wrapper
built with a `Reporter` reports by itself: it counts its own steps in-graph and, at the
end of each period, hands the report to the Logger through the in-graph emit (an ordered
`io_callback` under `lax.cond`, taken on period ends only) and resets the period.

Under `pmap` (Brax's trainers split the envs over local devices, axis `"i"`) each device
folds its own envs with no communication per step. At a period end the devices gather
their finished-episode statistics (one `all_gather` of O(metrics) values, inside the
period-end branch), which is exactly a state sharded by device (`Metrics.init(...,
sharding=...)`), so the report is that of one run over all envs, with windows and EMAs in
the order of the global env index; one device writes it.
"""

import math
from typing import Any, Protocol

import jax
import jax.numpy as jnp

from .._core import _count, _fresh
from .._core._count import Count
from .._core._metrics import Metrics
from .._core._metrics_state import MetricsState
from .._core._validate import is_int
from ._emit_receiver import WrapperPeriod
from ._logger import Logger


class ReportSink(Protocol):
    """What a reporting wrapper hands its reports to (a `jaxmetrics.Logger`)."""

    include_running: bool  # the reports have running episodes (gathered with the rest)

    def emit_from_wrapper(
        self,
        state: MetricsState,
        step: Count,
        when: jax.Array,
        period: WrapperPeriod,
        source: object,
    ) -> MetricsState:
        """In-graph: reports `state` at `step` where `when`, and resets the period there;
        `period` is the wrapper's period (and what the trainer runs, where known),
        `source` the wrapper's `Reporter` (a sink takes the reports of one training's
        wrapper)."""
        ...


MAX_REPORT_EVERY = 2**62
DEFAULT_PERIOD_CALLS = 100
"""Without `report_every`, a wrapper reports every 100 steps of its env batch."""


def axis_size(axis_name: str | None) -> int | None:
    """The size of the mapped axis `axis_name` where the caller is traced under it (a
    `pmap` or `shard_map` of that name), else None."""
    if axis_name is None:
        return None
    try:
        return int(jax.lax.axis_size(axis_name))
    except NameError:  # not bound here: a plain jit, or the trainer's evaluator
        return None


class Reporter:
    """What a wrapper needs to report by itself: the Logger, the period and the device axis.

    Args:
      metrics: the wrapper's spec; the Logger must be of the same spec.
      logger: the `jaxmetrics.Logger` the reports go to.
      report_every: the period in env steps over all envs and devices (the units of the
        report's step, `Counters/env_steps`); None: every 100 steps of the env batch. A
        report is made at the first step that reaches the period, so it is exact when the
        period is a multiple of the env steps of one step of the batch.
      axis_name: the mapped axis the trainer splits the envs over (Brax's trainers: `"i"`),
        used where the env is stepped under it; elsewhere the batch is the whole run.
      where: the wrapper's name, for error messages.
    """

    def __init__(
        self,
        metrics: Metrics,
        logger: Any,
        report_every: int | None,
        axis_name: str | None,
        where: str,
    ):
        if not isinstance(logger, Logger):
            raise TypeError(f"{where}(logger=...) must be a jaxmetrics.Logger, got {logger!r}.")
        if logger.metrics.config_id != metrics.config_id:
            raise ValueError(
                f"{where}: the Logger was built for another Metrics spec; create it with the "
                "wrapper's spec: jm.Logger(metrics, writers)."
            )
        if "env_steps" not in metrics.counter_names:
            raise ValueError(
                f"{where}(logger=...): the spec has no terms, so it counts no env steps to "
                "report at; give it terms, or flush the state yourself."
            )
        if report_every is not None and (
            not is_int(report_every) or not 1 <= report_every <= MAX_REPORT_EVERY
        ):
            raise ValueError(
                f"{where}(report_every=...) must be an int in [1, 2^62] (env steps over all "
                f"envs) or None, got {report_every!r}."
            )
        if logger.closed:
            raise RuntimeError(
                f"{where}(logger=...): the Logger is closed; give the wrapper an open Logger "
                "(create a new one for each training)."
            )
        if axis_name is not None and not isinstance(axis_name, str):
            raise TypeError(f"{where}(axis_name=...) must be a str or None, got {axis_name!r}.")
        self.metrics = metrics
        self.logger: ReportSink = logger
        self.report_every = None if report_every is None else int(report_every)
        self.axis_name = axis_name
        self._env_steps = metrics._rows.shard_counters.index("env_steps")

    def init(self, num_envs: int) -> MetricsState:
        """The fresh state of one batch (`mergeable_init`)."""
        return mergeable_init(self.metrics, num_envs, self.axis_name)

    def batch_env_steps(self, num_envs: int, steps_per_call: int) -> int:
        """Env steps over all envs and devices in one step of the batch (trace time)."""
        return num_envs * steps_per_call * (axis_size(self.axis_name) or 1)

    def period_calls(self, num_envs: int, steps_per_call: int) -> int:
        """Steps of the batch per period: static, from the batch at trace time."""
        if self.report_every is None:
            return DEFAULT_PERIOD_CALLS
        batch = self.batch_env_steps(num_envs, steps_per_call)
        calls = max(1, math.ceil(self.report_every / batch))
        if calls > 2**31 - 1:  # the clock is an int32
            raise ValueError(
                f"report_every={self.report_every} is {calls} steps of this batch of "
                f"{batch} env steps, past the period clock's 2^31 - 1; give a report_every "
                f"of at most {(2**31 - 1) * batch}."
            )
        return calls

    def __call__(
        self,
        state: MetricsState,
        clock: jax.Array,
        num_envs: int,
        steps_per_call: int,
        planned: int | None = None,
    ) -> tuple[MetricsState, jax.Array]:
        """After one step of the batch: `(state, clock)`, reported and reset where the
        period ends (in-graph; no host traffic on the other steps). `planned`: the env
        steps (over all envs and devices) the trainer runs to its end, where known."""
        clock = jnp.asarray(clock, jnp.int32) + 1
        calls = self.period_calls(num_envs, steps_per_call)
        when = clock >= calls
        clock = jnp.where(when, jnp.zeros_like(clock), clock)
        batch = self.batch_env_steps(num_envs, steps_per_call)
        period = WrapperPeriod(calls * batch, batch, planned)
        if (axis_size(self.axis_name) or 1) == 1:
            # One device (Brax's trainers pmap over one): nothing to gather, and no
            # collective in the period-end branch.
            step = self._step(state)
            return self.logger.emit_from_wrapper(state, step, when, period, self), clock
        name = self.axis_name
        assert name is not None  # an axis of more than one device

        def report() -> None:
            merged = gathered(state, name, self.logger.include_running)

            def write() -> None:
                self.logger.emit_from_wrapper(merged, self._step(merged), when, period, self)

            jax.lax.cond(_first_device(name), write, lambda: None)

        # As in the emit: the conditionals have no outputs (no copy of the state a step).
        jax.lax.cond(when, report, lambda: None)
        new = self.metrics.reset_period(state)
        return jax.tree.map(lambda n, o: jnp.where(when, n, o), new, state), clock

    def _step(self, state: MetricsState) -> Count:
        """The report's step: env steps over every env of the state."""
        assert state.shard_counts is not None
        totals = _count.total(state.shard_counts)
        return Count(totals.hi[self._env_steps], totals.lo[self._env_steps])


def _first_device(name: str) -> jax.Array:
    """Whether this is the first device along `name`. Not `axis_index(name) == 0`: XLA's
    GSPMD partitioner (JAX with Shardy off, which Brax's `ppo.train` over several GPUs
    needs on JAX 0.11) refuses the `partition-id` it lowers to inside a conditional beside
    the ring channel's send. A reduce-scatter of `0..n-1` hands device `i` the value `n * i`."""
    n = axis_size(name)
    ids = jax.lax.psum_scatter(jnp.arange(n, dtype=jnp.int32), name, tiled=True)
    return ids[0] == 0


def mergeable_init(metrics: Metrics, num_envs: int, axis_name: str | None) -> MetricsState:
    """The fresh state of one batch whose statistics are merged over the device axis
    `axis_name` (at a report, or a live read). Where several devices may merge, it keeps
    each EMA's newest values, so that their states merge exactly: under the axis when it
    has more than one device, and outside it when the process has more than one device
    (a trainer may reset its envs unnamed: Brax's SAC `pmap`s its reset without an axis).
    One device merges nothing, and keeping that history costs a scatter every step."""
    size = axis_size(axis_name)
    many = size > 1 if size is not None else jax.device_count() > 1
    if axis_name is None or not many:
        return metrics.init(num_envs)
    return _fresh.fresh(metrics._rows, num_envs, 1, ema_history=True)


def gathered(state: MetricsState, name: str, running: bool = False) -> MetricsState:
    """Every device's statistics as shards of one state, in device order (the order of
    the global env index: the trainer gives device `d` the `d`-th block of envs); with
    `running`, every device's running episodes too (else the state keeps its own)."""

    def gather(tree: Any) -> Any:
        return jax.tree.map(lambda x: jax.lax.all_gather(x, name, tiled=True), tree)

    envs = state.running
    if running and envs is not None:
        envs = jax.tree.map(
            lambda x: jax.lax.all_gather(x, name, axis=x.ndim - 1, tiled=True), envs
        )
    return state._replace(
        running=envs,
        finished=gather(state.finished),
        shard_counts=gather(state.shard_counts),
    )
