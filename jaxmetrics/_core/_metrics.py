"""The `Metrics` spec: static configuration plus the pure functions over `MetricsState`."""

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import _checkpoint, _count, _episode, _fresh, _inputs, _live, _report, _rows, _stream, _tags
from ._count import Count
from ._metrics_state import MetricsState
from ._report import Report, ReportLayout
from ._shard_fold import fold_shards, shard_counters
from ._sharding import like, shard_axes, shard_count, state_mesh, whole
from ._spec import Groups, Logged, MetricSpec, Term, reported
from ._tags import TagInfo
from ._validate import is_int


def _leading_shape(state: MetricsState) -> tuple[int, ...]:
    """The axes `state` has in front of one state's (e.g. a stack of seeds' states)."""
    one_state = (
        (None if state.running is None else state.running.steps, 2),  # [rows, num_envs]
        (None if state.shard_counts is None else state.shard_counts.hi, 2),  # [shards, K]
        (None if state.logged is None else state.logged.steps, 1),  # [rows]
        (None if state.counters is None else state.counters.hi, 1),  # [C]
    )
    for leaf, ndim in one_state:
        if leaf is not None:
            return tuple(leaf.shape[: leaf.ndim - ndim])
    return ()


class Metrics:
    """A static metrics spec and the pure functions over its `MetricsState`.

    Configuration is validated here; the methods are un-jitted pure functions that work
    under `jit`, `lax.scan`, `lax.cond` and `vmap`. Under `jax.grad` (or `jvp`) a state
    records primal values and carries no gradient: `update` and `log` take what they are
    given as `jax.lax.stop_gradient` would, so a loss logged inside the function being
    differentiated leaves its gradient as it was.

    Args:
      terms: name -> `Term` (or a bare function, meaning `Term(fn)`), evaluated by
        `update` on every env step.
      logged: names (default statistics) or name -> `Logged`, fed by `log`.
      counters: names of extra lifetime counters, fed by `increment`. "env_steps" and
        "episodes" are kept automatically whenever there are terms.
      nonfinite: default policy for NaN/inf values: "skip", "propagate" or "raise".
      episode_prefix: tag prefix of episode metrics.
      logged_prefix: tag prefix of logged values.
      counter_prefix: tag prefix of counters.
      groups: a `jaxmetrics.groups(fn, names)` for every term that has none of its own:
        each statistic is then also kept per group (`<prefix>/<metric>/<group>/...`),
        and the `ungrouped` counter counts episodes whose group index is out of range.
      dtype: float dtype of the state and its statistics: float32 (default) or float64
        (with `jax_enable_x64`). Terms and logged values may be of any float, int or bool
        dtype; they are converted.

    Examples:
      >>> import jax, jax.numpy as jnp, jaxmetrics as jm
      >>> metrics = jm.Metrics(terms={"reward": jm.Term(lambda r: r, reduce="sum")})
      >>> state = metrics.init(num_envs=2)
      >>> state = metrics.update(state, jnp.array([1.0, 2.0]), jnp.array([False, True]))
      >>> state = metrics.update(state, jnp.array([3.0, 4.0]), jnp.array([True, False]))
      >>> report = metrics.to_host(metrics.compute(state))
      >>> report["Episode_Metrics/reward"], report["Episode_Metrics/reward/count"]
      (3.0, 2)
    """

    def __init__(
        self,
        terms: Mapping[str, Term | Callable[..., Any]] | None = None,
        logged: Mapping[str, Logged] | Sequence[str] | None = None,
        counters: Sequence[str] = (),
        *,
        nonfinite: str = "skip",
        episode_prefix: str = "Episode_Metrics",
        logged_prefix: str = "Train",
        counter_prefix: str = "Counters",
        groups: Groups | None = None,
        dtype: Any = jnp.float32,
    ):
        rows = _rows.build(
            terms,
            logged,
            counters,
            nonfinite,
            episode_prefix,
            logged_prefix,
            counter_prefix,
            groups,
            dtype,
        )
        self._rows = rows
        self._spec = rows.identity
        self.counter_names = rows.counter_names
        self.prefixes = rows.prefixes
        self.dtype = rows.dtype
        self.tags: tuple[TagInfo, ...] = rows.tags
        self._layouts: dict[bool, ReportLayout] = {}  # per include_running, see `compute`

    # ------------------------------------------------------------------ static views

    @property
    def metric_specs(self) -> dict[str, MetricSpec]:
        """Every metric by name: episode metrics (`term` or `term/output`) and logged values."""
        out = {s.name: s for s in self._rows.ep_defined}
        out.update({s.name: s for s in (self._rows.lg_plan.rows if self._rows.lg_plan else ())})
        return out

    def histogram_edges(self, tag: str) -> np.ndarray:
        """The bin edges (float64, `bins + 1`) of a histogram tag; under/overflow excluded."""
        info = next((i for i in self.tags if i.tag == tag and i.stat == "histogram"), None)
        if info is None:
            raise KeyError(f"{tag!r} is not a histogram tag of this spec.")
        h = self.metric_specs[info.metric].stats.histogram
        assert h is not None
        return np.linspace(h.range[0], h.range[1], h.bins + 1)

    # ------------------------------------------------------------------ pure functions

    def init(self, num_envs: int, sharding: jax.sharding.Sharding | None = None) -> MetricsState:
        """A fresh state for `num_envs` envs (0 gives the identity element of `merge`).

        Args:
          num_envs: the size of the env batch.
          sharding: how the env batch is split over devices, e.g. `NamedSharding(mesh,
            P("env"))` or the `.sharding` of any `[num_envs, ...]` array of the batch
            (its first axis is the env axis). The state then keeps one set of
            finished-episode statistics per env shard, laid out on the same devices, and
            `update` runs without cross-device communication. None: one shard, the
            state on the default device (right for a single device).

        Raises:
          ValueError: if `num_envs` does not split evenly into the shards, or for a
            state of several shards whose spec has an EMA coefficient below 3.385e-4,
            which merging the shards could not serve exactly (see `merge`).
          TypeError: for a sharding other than a `NamedSharding` or a single device.
        """
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {num_envs!r}.")
        if num_envs < 0:
            raise ValueError(f"num_envs must be >= 0, got {num_envs}.")
        num_envs = int(num_envs)
        shards = shard_count(sharding, num_envs)
        if num_envs == 0 and sharding is None:
            shards = 0  # no shard at all: concatenating it in `merge` changes nothing
        if shards > 1 and self._rows.ep_plan is not None:
            _stream.check_mergeable(self._rows.ep_plan)  # refused here, not at the first flush
        if not isinstance(sharding, jax.sharding.NamedSharding):
            state = _fresh.fresh(self._rows, num_envs, shards)
            return state if sharding is None else jax.device_put(state, sharding)
        place = self.state_sharding(sharding)
        # out_shardings places it under Auto axes; device_put types it under Explicit ones.
        return jax.jit(
            lambda: jax.device_put(_fresh.fresh(self._rows, num_envs, shards), place),
            out_shardings=place,
        )()

    def state_sharding(self, sharding: jax.sharding.NamedSharding) -> MetricsState:
        """The layout `init(num_envs, sharding)` gives: a MetricsState-shaped tree of
        `NamedSharding`s (running episodes split like the envs, finished-episode
        statistics split by shard, logged values and counters replicated).

        Use it where a state crosses a `jit` boundary under Auto mesh axes, so that XLA
        keeps it split (`jax.jit(..., out_shardings=...)`, or
        `jax.lax.with_sharding_constraint(state, metrics.state_sharding(sharding))` on a
        state carried through your own loop); `jaxmetrics.brax.wrap(sharding=...)` does
        this on every step.

        Examples:
          >>> import jax, jaxmetrics as jm
          >>> from jax.sharding import NamedSharding, PartitionSpec as P
          >>> mesh = jax.make_mesh((1,), ("env",), devices=jax.devices()[:1])
          >>> m = jm.Metrics(terms={"r": jm.Term(lambda r: r)})
          >>> tuple(m.state_sharding(NamedSharding(mesh, P("env"))).running.steps.spec)
          (None, 'env')
        """
        if not isinstance(sharding, jax.sharding.NamedSharding):
            raise TypeError(
                "state_sharding(sharding) takes the env batch's NamedSharding, got "
                f"{type(sharding).__name__}."
            )
        mesh = sharding.mesh
        env_axes = tuple(sharding.spec)[0] if tuple(sharding.spec) else None
        return _fresh.per_field(
            self._rows,
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(None, env_axes)),
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(env_axes)),
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()),
        )

    @staticmethod
    def to_checkpoint(state: MetricsState) -> "_checkpoint.MetricsCheckpoint":
        """The state as saved: a `MetricsCheckpoint` of the state with its zero-size arrays
        (statistics the spec does not keep) set to None, for orbax-checkpoint, which
        refuses to save zero-size arrays, and of its layout (env shards and envs), so that
        a restore into another layout is told apart. Restore with `from_checkpoint`.
        flax.serialization takes the state as it is, or this tree.

        Examples:
          >>> import orbax.checkpoint as ocp, tempfile, jaxmetrics as jm
          >>> metrics = jm.Metrics(logged=["loss"])
          >>> state = metrics.log(metrics.init(0), {"loss": 2.0})
          >>> path = tempfile.mkdtemp() + "/ckpt"
          >>> with ocp.StandardCheckpointer() as ckpt:
          ...     ckpt.save(path, metrics.to_checkpoint(state))
          ...     ckpt.wait_until_finished()
          ...     target = metrics.to_checkpoint(metrics.init(0))
          ...     restored = metrics.from_checkpoint(ckpt.restore(path, target), metrics.init(0))
          >>> metrics.to_host(metrics.compute(restored))["Train/loss"]
          2.0
        """
        return _checkpoint.to_checkpoint(state)

    def checkpoint_target(self, num_envs: int, shards: int = 1) -> "_checkpoint.MetricsCheckpoint":
        """The restore target of a checkpoint saved with `shards` env shards (1 unsharded;
        the devices of the env axis when sharded) of `num_envs` envs, on the default
        device: orbax restores arrays into the target's shapes, so a checkpoint of another
        device count is restored against this one, then laid out by `from_checkpoint`.

        Examples:
          >>> import jaxmetrics as jm
          >>> metrics = jm.Metrics(terms={"r": jm.Term(lambda r: r)})
          >>> [int(v) for v in metrics.checkpoint_target(16, shards=4).layout]
          [4, 16]
        """
        if not (is_int(num_envs) and is_int(shards) and num_envs >= 0 and shards >= 0) or (
            num_envs % shards if shards else num_envs
        ):
            raise ValueError(
                f"checkpoint_target: {num_envs!r} envs in {shards!r} env shards is not the "
                "layout of a state (ints, the envs split evenly over at least one shard, or "
                "0 envs in 0 shards); pass the layout from_checkpoint's error names."
            )
        return _checkpoint.target(self._rows, int(num_envs), int(shards))

    def from_checkpoint(self, saved: Any, target: MetricsState) -> MetricsState:
        """A restored state, laid out like `target` (`init` with the `num_envs` and the
        sharding of the run that goes on): JAX arrays on the target's devices.

        `saved` is `to_checkpoint`'s tree as restored (orbax: `ckpt.restore(path,
        metrics.to_checkpoint(target))`), or a whole state as flax.serialization restores
        it (host arrays). Its None leaves become zero-size arrays. A checkpoint of another
        number of devices (env shards) is restored exactly: its shards are merged (as
        `compute` merges them) into the target's first shard, so every later report is the
        one the saved run would have made; orbax needs a target of the checkpoint's own
        layout for it (`checkpoint_target`).

        Raises:
          ValueError: for a checkpoint of another number of envs (the running episodes
            belong to their envs), one whose arrays orbax cut or padded to another layout
            (`strict=False`), or a tree of another spec, structure, shape or dtype
            (orbax's target-less restore gives plain dicts), each naming both layouts.
        """
        return _checkpoint.from_checkpoint(
            self._rows, saved, self._check_state(target, "from_checkpoint")
        )

    def empty(self) -> MetricsState:
        """The identity of `merge`: a state of zero envs with nothing recorded."""
        return self.init(0)

    def _check_state(self, state: Any, fn: str) -> MetricsState:
        if not isinstance(state, MetricsState):
            raise TypeError(
                f"{fn}: expected a MetricsState from this spec's init(), got "
                f"{type(state).__name__}."
            )
        if getattr(state.spec, "_fields", None) != self._spec._fields:
            raise ValueError(
                f"{fn}: this state was built by a different Metrics spec (other terms, "
                "logged values, counters, statistics, prefixes or dtype). Call init() on the "
                "spec that updates it; to restore a checkpoint, build the spec exactly as "
                "the one that saved it."
            )
        if any(isinstance(x, np.ndarray) for x in jax.tree.leaves(state)):
            # flax.serialization restores host arrays; the in-graph functions index the
            # state's arrays with `.at`, which only JAX arrays have.
            state = jax.tree.map(jnp.asarray, state)
        lead = _leading_shape(state)
        if lead:
            raise ValueError(
                f"{fn}: this state has leading axes {lead} (a stack of states, e.g. one per "
                f"seed); its statistics would be merged as if they were one run's. Apply "
                f"{fn} to each state: jax.vmap(metrics.{fn}) over the stacked axis, or "
                "merge the states first if they are one run's workers."
            )
        return state

    def update(self, state: MetricsState, step_input: Any, done: Any) -> MetricsState:
        """Folds one env step into the running episodes; finished episodes are reported.

        A state sharded over Explicit mesh axes is folded under its own mesh, so no
        `jax.set_mesh` is needed around the call.

        Args:
          state: the current state.
          step_input: anything the term functions take (e.g. a Brax `State`).
          done: `[num_envs]` bool (or integer, non-zero meaning done): whether each env's
            episode ends on this step. Floats are refused: Brax's `State.done` is a
            float32 0.0/1.0, pass `state.done.astype(bool)`.
            The step is part of the episode it ends.

        Returns:
          The new state.
        """
        state = self._check_state(state, "update")
        if state.running is None:
            return state
        with state_mesh(state):
            return self._update(state, step_input, done)

    def _update(self, state: MetricsState, step_input: Any, done: Any) -> MetricsState:
        assert state.running is not None
        num_envs = state.running.steps.shape[-1]
        done = _inputs.done_flags(done, num_envs)
        shards = state.shard_counts.hi.shape[0]  # type: ignore[union-attr]
        if num_envs == 0:
            raise ValueError(
                "update: this state has no envs: init(0) and empty() give the identity of "
                "merge, which nothing can be folded into. Use init(num_envs)."
            )
        if shards == 0 or num_envs % shards:
            raise ValueError(
                f"update: this state splits {num_envs} envs into {shards} shards, which is not "
                "an even split (a state merged from states of different sizes, or of no "
                "envs). Update a state made by init(num_envs, sharding=...)."
            )
        # A metric observes the step, and a gradient through its statistics means
        # nothing: the values are taken as constants. (JAX cannot differentiate the
        # fold's variadic reductions: their JVP fails on operands without a tangent.)
        x = like(
            jax.lax.stop_gradient(_inputs.term_values(self._rows, step_input, num_envs)),
            state.running.steps,
            "the term values",
        )
        done = like(done, state.running.steps[0], "done")
        if 1 < x.shape[0] <= 4:
            # On a GPU, XLA fuses a stack of 2 to 4 term rows into each kernel that reads
            # it, so that every input of the batch's fold became a kernel of its own (six
            # at 3 terms); from 5 rows on it writes the stack once, and a barrier on those
            # only adds a kernel (docs/benchmarks.md has the times).
            x = jax.lax.platform_dependent(
                x, cuda=jax.lax.optimization_barrier, default=lambda a: a
            )
        prop = jnp.asarray(self._rows.ep_propagate)[:, None]
        finite = jnp.isfinite(x)
        running, values, any_step = _episode.step(
            self._rows.episode_plan, state.running, x, finite | prop, done
        )
        ended = done[None, :] & any_step
        ok = ended & (jnp.isfinite(values) | prop)
        # Flags and counted rows are uint8 (each at most 2, or the number of groupings):
        # at 65,536 envs an int32 [M, E] array is 2.6 MB written and read again per step.
        bad = (~finite).astype(jnp.uint8) + (ended & ~ok).astype(jnp.uint8)
        group_ids = [
            like(i, state.running.steps[0], f"the group indices of {where}")
            for i, where in _inputs.group_ids(self._rows, step_input, num_envs)
        ]
        # Each device folds its own shard where the trace knows the devices' axes
        # (`_shard_fold`).
        axes = shard_axes(state.shard_counts.hi, shards)  # type: ignore[union-attr]
        segments_plan = self._rows.ep_segments
        segmented = segments_plan is not None and segments_plan.serves(num_envs // shards)
        rows, segments = _inputs.by_group(self._rows, values, ok, bad, group_ids, segmented)
        # Materialized once: without the barrier XLA recomputes the episode values from
        # the old accumulators inside each reduction, which makes it copy them every step.
        rows, segments = jax.lax.optimization_barrier((rows, segments))
        assert self._rows.ep_plan is not None
        finished, counts = fold_shards(
            self._rows.ep_plan,
            segments_plan,
            state.finished,
            state.shard_counts,
            rows,
            shard_counters(done, group_ids, self._rows.groupings),
            segments,
            axes,
        )
        return state._replace(running=running, finished=finished, shard_counts=counts)

    def log(self, state: MetricsState, values: Mapping[str, Any]) -> MetricsState:
        """Adds logged values: each scalar, or each element of an array, weighs 1.

        Args:
          state: the current state.
          values: logged name -> scalar or array; names not given are left alone.

        Returns:
          The new state.
        """
        state = self._check_state(state, "log")
        if not isinstance(values, Mapping):
            raise TypeError(
                f"log: values must be a dict name -> value, got {type(values).__name__}."
            )
        unknown = sorted(set(values) - set(self._rows.lg_index))
        if unknown:
            raise ValueError(
                f"log: unknown logged names {unknown}; declare them in "
                f"Metrics(logged=...). Known: {sorted(self._rows.lg_index)}."
            )
        flat = {}
        for name, v in values.items():
            # Taken as a constant, as `update` takes its term values.
            a = jax.lax.stop_gradient(_inputs.as_array(v, f"log: {name!r}"))
            if a.size:  # an empty array logs nothing
                flat[name] = a.reshape(-1).astype(self.dtype)
        if not flat:
            return state
        assert self._rows.lg_plan is not None and state.logged is not None
        width = max(a.shape[0] for a in flat.values())
        rows = len(self._rows.lg_plan.rows)
        v = jnp.zeros((rows, width), self.dtype)
        m = jnp.zeros((rows, width), jnp.bool_)
        for name, a in flat.items():
            i = self._rows.lg_index[name]
            v = v.at[i, : a.shape[0]].set(a)
            m = m.at[i, : a.shape[0]].set(True)
        finite = jnp.isfinite(v)
        ok = m & (finite | jnp.asarray(self._rows.lg_propagate)[:, None])
        bad = (m & ~finite).astype(jnp.uint8)
        logged = _stream.add(self._rows.lg_plan, state.logged, v, ok, bad)
        return state._replace(logged=logged)

    def increment(self, state: MetricsState, name: str, by: Any = 1) -> MetricsState:
        """Adds `by` (a scalar int; a Python int in [-2^31, 2^32)) to the lifetime counter
        `name`, exactly. A negative `by` subtracts."""
        state = self._check_state(state, "increment")
        if name not in self.counter_names:
            raise ValueError(
                f"increment: unknown counter {name!r}; declare it in Metrics(counters=...). "
                f"Known: {list(self.counter_names)}."
            )
        if isinstance(by, (int, np.integer)) and not isinstance(by, bool):
            if not -(2**31) <= by < 2**32:
                raise ValueError(f"increment: `by` must be in [-2^31, 2^32), got {by}.")
            # A Python int >= 2^31 does not fit the default int32.
            by = np.uint32(by) if by >= 0 else np.int32(by)
        by = jnp.asarray(by)
        if not jnp.issubdtype(by.dtype, jnp.integer) or by.shape != ():
            raise TypeError(
                f"increment: `by` must be a scalar int, got {by.dtype}{list(by.shape)}."
            )
        if name in self._rows.shard_counters:
            raise ValueError(f"increment: {name!r} is counted by update; it cannot be incremented.")
        j = self._rows.stored_counters.index(name)
        assert state.counters is not None
        return state._replace(counters=_count.add_at(state.counters, j, by))

    def reset_period(self, state: MetricsState) -> MetricsState:
        """Starts a new flush period: period statistics clear; windows, EMA, counters and
        running episodes carry on."""
        state = self._check_state(state, "reset_period")
        plan = self._rows.ep_plan
        logged = None
        if self._rows.lg_plan:
            assert state.logged is not None  # a state of this spec has logged rows
            logged = _stream.reset_period(self._rows.lg_plan, state.logged)
        return state._replace(
            finished=jax.vmap(lambda st: _stream.reset_period(plan, st))(state.finished)
            if plan
            else None,
            logged=logged,
        )

    def merge(self, a: MetricsState, b: MetricsState) -> MetricsState:
        """Combines the states of disjoint workers (devices, hosts, seeds) that ran side by
        side, as one run over both env batches (`b`'s envs after `a`'s).

        Mean/std are count-weighted (Chan); sum, count, min, max, histograms and counters
        are exact; windows keep the newest `n` by arrival step (`b`'s values after `a`'s
        of the same step); the EMA folds both workers' values in that order, exact to
        2^-32 of the values' range for states made by a sharded `init` and the average
        of the workers' EMAs otherwise (docs/semantics.md, "Merge"). Running episodes are
        concatenated along the env axis; env shards are concatenated when both states
        have the same envs per shard, else each state's shards are merged into one first.
        Associative, with `empty()` as identity.
        """
        a = self._check_state(a, "merge")
        b = self._check_state(b, "merge")
        finished, counts = None, None
        if self._rows.ep_plan is not None:
            finished, counts = self._merge_shards(a, b)
        logged = None
        if self._rows.lg_plan is not None:
            assert a.logged is not None and b.logged is not None  # states of this spec
            logged = _stream.merge(self._rows.lg_plan, a.logged, b.logged)
        return MetricsState(
            running=None
            if a.running is None
            else jax.tree.map(lambda x, y: jnp.concatenate([x, y], axis=-1), a.running, b.running),
            finished=finished,
            shard_counts=counts,
            logged=logged,
            counters=None
            if a.counters is None or b.counters is None  # both or neither: one spec
            else _count.merge(a.counters, b.counters),
            spec=self._spec,
        )

    def _merge_shards(self, a: MetricsState, b: MetricsState) -> tuple[Any, Count]:
        plan = self._rows.ep_plan
        assert plan is not None and a.shard_counts is not None and b.shard_counts is not None
        sa, sb = a.shard_counts.hi.shape[0], b.shard_counts.hi.shape[0]
        if sa == 0 or sb == 0:
            return (b.finished, b.shard_counts) if sa == 0 else (a.finished, a.shard_counts)
        per_a = a.running.steps.shape[-1] // sa  # type: ignore[union-attr]
        per_b = b.running.steps.shape[-1] // sb  # type: ignore[union-attr]
        fa, fb, ea, eb = a.finished, b.finished, a.shard_counts, b.shard_counts
        assert fa is not None and fb is not None  # with shard counts
        if per_a != per_b:
            # Shards of different sizes cannot stay blocks of one env axis: one shard.
            one = _stream.merge(plan, _stream.combine(plan, fa), _stream.combine(plan, fb))
            total = _count.merge(_count.total(ea), _count.total(eb))
            return jax.tree.map(lambda x: x[None], (one, total))
        width = max(
            (r.size for f in (fa, fb) for r in f.ema_rings),  # type: ignore[union-attr]
            default=0,
        )
        fa, fb = (_stream.pad_ema_history(f, width) for f in (fa, fb))  # type: ignore[arg-type]
        cat = lambda x, y: jnp.concatenate([x, y], axis=0)  # noqa: E731
        return jax.tree.map(cat, fa, fb), jax.tree.map(cat, ea, eb)

    def compute(self, state: MetricsState, include_running: bool = False) -> Report:
        """The report: a `Report`, tag -> small array (in-graph; O(metrics), not
        O(num_envs)). Its pytree leaves are one column per statistic, so that a jitted
        `compute` has a few outputs whatever the number of metrics and groups.

        Counts (`/count`, `/nonfinite`, `/histogram`, counters) are exact `Count` pairs;
        `to_host` turns them into Python ints. Empty statistics are NaN.

        Args:
          state: the current state.
          include_running: also report `<metric>/running`, the mean over envs of the
            running (unfinished) episodes' current values.
        """
        state = self._check_state(state, "compute")
        # (group, statistic, rows, values): `values[j]` is row `rows[j]`'s statistic; a row
        # is a stream row of the group's plan, an episode row, or a counter's index.
        columns: list[tuple[str, str, tuple[int, ...], jax.Array | Count]] = []
        finished, shard_counts = state.finished, state.shard_counts
        if shard_counts is not None and shard_counts.hi.shape[0] > 1:
            # The shards meet here, in one collective rather than one per leaf.
            with state_mesh(state):
                finished, shard_counts = whole((finished, shard_counts))
        if self._rows.ep_plan is not None:
            finished = _stream.combine(self._rows.ep_plan, finished)  # type: ignore[arg-type]
        for group, plan, st in (
            ("episode", self._rows.ep_plan, finished),
            ("logged", self._rows.lg_plan, state.logged),
        ):
            if plan is None:
                continue
            assert st is not None  # a state of this spec has the plan's rows
            columns += [(group, *column) for column in _stream.compute(plan, st)]
        if include_running and state.running is not None:
            run = _episode.running(self._rows.episode_plan, state.running)
            has = ~jnp.isnan(run)
            n = jnp.sum(has, axis=1)
            mean = jnp.sum(jnp.where(has, run, 0), axis=1) / jnp.maximum(n, 1).astype(self.dtype)
            mean = jnp.where(n > 0, mean, jnp.nan)
            columns.append(("running", "running", tuple(range(len(self._rows.ep_rows))), mean))
        names = self.counter_names
        if shard_counts is not None:
            rows = tuple(names.index(c) for c in self._rows.shard_counters)
            columns.append(("counter", "total", rows, _count.total(shard_counts)))
        if state.counters is not None:
            rows = tuple(names.index(c) for c in self._rows.stored_counters)
            columns.append(("counter", "total", rows, state.counters))
        layout = self._report_layout(include_running, columns)
        return Report(layout, tuple(values for *_, values in columns))

    def read(
        self, state: MetricsState, metric: str, statistic: str = "mean", *, by_group: bool = False
    ) -> jax.Array:
        """In-graph: one live statistic, the value `compute` reports under its tag now.

        For code that acts on statistics while it runs (a curriculum that advances when a
        group's windowed success rate passes a threshold, an adaptive setting driven by
        an EMA of returns): a JAX array under `jit`, `scan`, `vmap` and sharding, with no
        host sync. Under `jit` only this statistic is computed (XLA drops the rest of the
        report), so it is cheap enough to call every step. A state of several env shards
        (`init(..., sharding=...)`) is merged first, as `compute` merges it: the read then
        moves across devices what the statistic merges from (a few hundred bytes for a
        period statistic, a window's values, an EMA's exact-merge history; see
        docs/curriculum.md).

        Args:
          state: the current state.
          metric: a metric (`<term>`, `<term>/<output>`, a logged name, a group's own row
            `<metric>/<group>`) or a counter (`episodes`, `env_steps`, ...).
          statistic: one the metric reports (`mean`, `std`, `min`, `max`, `sum`, `count`,
            `ema`, `window_mean`, `window_std`, `window_min`, `window_max`,
            `window_values`, `window_p<p>`, `q<p>`, `histogram`, `nonfinite`; `total`
            for a counter), or `window_count`: the values in its window so far.
          by_group: the statistic of each of the metric's groups, `[groups]` in the
            order of their names, instead of the metric's over all episodes.

        Returns:
          The statistic (a scalar, `[groups]`, or with the trailing axis of window
          values and histograms), NaN where it is empty (as in the report). Counts are
          floats of the state's dtype (exact up to 2^24 in float32).

        Raises:
          ValueError: (at trace time) an unknown metric or a statistic it does not keep,
            naming what it has; `by_group` for a metric without groups.

        Examples:
          >>> import jax, jax.numpy as jnp, jaxmetrics as jm
          >>> metrics = jm.Metrics(
          ...     terms={"success": jm.Term(lambda s: s["ok"], stats=(jm.window(2),))},
          ...     groups=jm.groups(lambda s: s["level"], ("easy", "hard")),
          ... )
          >>> state = metrics.init(num_envs=2)
          >>> step = {"ok": jnp.array([1.0, 0.0]), "level": jnp.array([0, 1])}
          >>> state = jax.jit(metrics.update)(state, step, jnp.array([True, True]))
          >>> rate = jax.jit(lambda s: metrics.read(s, "success", "window_mean", by_group=True))
          >>> rate(state).tolist()
          [1.0, 0.0]
        """
        state = self._check_state(state, "read")
        return _live.read(self._rows, self.compute, state, metric, statistic, by_group)

    def _report_layout(
        self, include_running: bool, columns: list[tuple[str, str, tuple[int, ...], Any]]
    ) -> ReportLayout:
        """Where `compute`'s tags lie in its `columns` (built on the host, once per
        `include_running`: the columns' structure is the spec's). Tags come in the order
        of the stream rows, each row's reported statistics in registry order, then the
        running values and the counters."""
        if include_running in self._layouts:
            return self._layouts[include_running]
        where = {
            (group, stat, i): (c, j)
            for c, (group, stat, rows, _) in enumerate(columns)
            for j, i in enumerate(rows)
        }
        at: dict[str, tuple[int, int]] = {}
        for group, plan in (("episode", self._rows.ep_plan), ("logged", self._rows.lg_plan)):
            for i, spec in enumerate(plan.rows if plan is not None else ()):
                for stat in reported(spec.stats):
                    at[_tags.tag(self.prefixes[group], spec.name, stat)] = where[group, stat, i]
        for i, spec in enumerate(self._rows.ep_rows if include_running else ()):
            at[_tags.tag(self.prefixes["episode"], spec.name, "running")] = where[
                "running", "running", i
            ]
        for i, c in enumerate(self.counter_names):
            at[_tags.tag(self._rows.counter_prefix, c, "total")] = where["counter", "total", i]
        trailing = tuple(jax.tree.leaves(v)[0].ndim - 1 for *_, v in columns)
        layout = ReportLayout((self.config_id, include_running), tuple(at), at, trailing)
        self._layouts[include_running] = layout
        return layout

    # ------------------------------------------------------------------ host side

    def to_host(self, report: Mapping[str, Any]) -> dict[str, Any]:
        """Host side: fetches a report; scalars become floats, counts exact Python ints,
        histograms and window values numpy arrays."""
        if isinstance(report, Report):
            return _report.to_host(jax.device_get(report))
        fetched = jax.device_get(dict(report))
        out: dict[str, Any] = {}
        for k, v in fetched.items():
            if isinstance(v, Count):
                out[k] = _count.to_int(v)
            else:
                a = np.asarray(v)
                out[k] = float(a) if a.ndim == 0 else a
        return out

    def nonfinite(self, host_report: Mapping[str, Any]) -> list[tuple[TagInfo, str, int]]:
        """Host side: the metrics of `host_report` (from `to_host`) that saw non-finite
        values, in tag order.

        Returns:
          `(info, policy, count)` per such metric: the `TagInfo` of its `/nonfinite` tag
          (naming the metric and its group), its nonfinite policy ("skip", "propagate" or
          "raise") and the count. A `Logger` warns or raises accordingly, naming the run
          and the step.
        """
        specs = {("episode", s.name): s for s in self._rows.ep_defined}
        specs.update(
            {("logged", s.name): s for s in (self._rows.lg_plan.rows if self._rows.lg_plan else ())}
        )
        out = []
        for i in self.tags:
            count = host_report.get(i.tag, 0) if i.stat == "nonfinite" else 0
            if count:
                out.append((i, specs[(i.group, i.metric)].nonfinite, int(count)))
        return out

    @property
    def config_id(self) -> str:
        """The identity of this spec's configuration (the field name `MetricsState.spec`
        carries): specs built with the same configuration share it."""
        return type(self._spec)._fields[0]
