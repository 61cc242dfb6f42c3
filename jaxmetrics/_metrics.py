"""The `Metrics` spec: static configuration plus the pure functions over `MetricsState`."""

import dataclasses
import hashlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import _count, _episode, _reductions, _statistics, _stream, _tags
from ._count import Count
from ._layout import env_layout, like, state_mesh
from ._spec import Groups, Logged, MetricSpec, Term, check_name, check_policy, parse_stats
from ._state import MetricsState, spec_id
from ._tags import TagInfo

BUILTIN_COUNTERS = ("env_steps", "episodes")
GROUP_COUNTER = "ungrouped"
# Counted per env shard in MetricsState.ended, one column each, in this order (the last
# only with groups): a step updates them in one kernel, with no cross-device reduction.
_SHARD_COUNTERS = ("env_steps", "episodes", GROUP_COUNTER)

# Version of the MetricsState's array layout, part of the spec's identity: a checkpoint of
# another layout is refused as another spec's instead of being misread. 2: running
# episodes in three slots per env (`_episode.SLOTS`); EMA fields and window positions of
# every stream row. 3: env steps counted per shard (`ended`); arrival steps per row.
# 4: `ended` padded to whole multiples of the episode rows (`_stream.tally_width`); a
# histogram's step counts kept (zero) in the state. 5: a ring slot (windows, EMA history)
# holds its value's bits and its arrival stamp in one `uint32` array (`_stream.Ring.data`).
STATE_LAYOUT = 5


def _is_numeric(dtype) -> bool:
    return jnp.issubdtype(dtype, jnp.bool_) or (
        jnp.issubdtype(dtype, jnp.number) and not jnp.issubdtype(dtype, jnp.complexfloating)
    )


def _as_array(v: Any, what: str) -> jax.Array:
    """A term's or logged value as a JAX array of a numeric dtype, or an error naming it
    (`what`, e.g. "term 'x'").

    Host integers wider than JAX's default int32 (numpy int64, Python ints past 2^31)
    become float64 on the host first: JAX would wrap them (3_000_000_000 ->
    -1294967296).
    """
    fix = "give float, int or bool values"
    if v is None:
        raise TypeError(f"{what}: got None; {fix}.")
    if not isinstance(v, jax.Array | jax.core.Tracer):
        try:
            host = np.asarray(v)
        except (TypeError, ValueError) as e:
            raise TypeError(
                f"{what}: got a {type(v).__name__}, not an array ({e}); {fix}."
            ) from None
        if host.dtype.kind in "USVMm":
            raise TypeError(f"{what}: got {v!r} (numpy dtype {host.dtype}); {fix}.")
        if host.dtype.kind in "iuO" and not jax.config.jax_enable_x64:
            try:
                host = host.astype(np.float64)
            except (TypeError, ValueError):
                raise TypeError(f"{what}: got {type(v).__name__} of non-numbers; {fix}.") from None
        v = host
    try:
        a = jnp.asarray(v)
    except TypeError as e:
        raise TypeError(f"{what}: not a numeric array ({e}); {fix}.") from None
    if not _is_numeric(a.dtype):
        raise TypeError(f"{what}: got dtype {a.dtype}; {fix}.")
    return a


def _canonical(x: Any) -> Any:
    """`x` in a form whose repr is the same in every process: sets sorted (their order
    follows string hashing, which is salted per process), dataclasses as field tuples."""
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        fields = dataclasses.fields(x)
        return (type(x).__name__, tuple((f.name, _canonical(getattr(x, f.name))) for f in fields))
    if isinstance(x, set | frozenset):
        return ("set", tuple(sorted((_canonical(v) for v in x), key=repr)))
    if isinstance(x, Mapping):
        return ("map", tuple(sorted(((k, _canonical(v)) for k, v in x.items()), key=repr)))
    if isinstance(x, list | tuple):
        return tuple(_canonical(v) for v in x)
    return x


def _count_overflow(row: dict[str, Any]) -> dict[str, Any]:
    """Adds to a row's `nonfinite` count the statistics that overflowed the dtype: a
    period statistic that is not finite although the period has values (all finite: the
    others were left out), or an EMA or window statistic that is infinite (values near
    float32's limit: their sum is inf, their mean NaN), or a quantile that fell on values
    outside its sketch's magnitude range. Such a statistic is not written, so the count
    is what makes the loss visible (warned about or raised at flush)."""
    has = ~_count.is_zero(row["count"])
    quantiles = [k for k in row if _statistics.get(k).source == "quantiles"]
    bad = [has & ~jnp.isfinite(row[k]) for k in ("mean", "std", "sum", *quantiles)]
    bad += [
        jnp.isinf(v)
        for k, v in row.items()
        if (k == "ema" or k.startswith("window_")) and k != "window_values"
    ]
    n = jnp.sum(jnp.stack(bad), dtype=jnp.uint32)
    return {**row, "nonfinite": _count.merge(row["nonfinite"], Count(jnp.uint32(0), n))}


def _flatten_terms(
    terms: Mapping[str, Any], policy: str, default_groups: Groups | None
) -> tuple[list[Term], list[MetricSpec], list[Groups | None]]:
    """The terms, their metrics (one per output) and each metric's grouping."""
    if not isinstance(terms, Mapping):
        raise TypeError(
            f"terms must be a dict of name -> jaxmetrics.Term (or function), got "
            f"{type(terms).__name__}."
        )
    out_terms, specs, groupings = [], [], []
    for name, t in terms.items():
        where = f"term {name!r}"
        check_name(name, where)
        if not isinstance(t, Term):
            if not callable(t):
                raise TypeError(f"{where}: expected jaxmetrics.Term or a function, got {t!r}.")
            t = Term(t)
        if not callable(t.fn):
            raise TypeError(f"{where}: fn must be callable, got {t.fn!r}.")
        if not isinstance(t.params, Mapping):
            raise TypeError(f"{where}: params must be a dict of keyword arguments.")
        outputs = (None,) if t.outputs is None else tuple(t.outputs)
        if t.outputs is not None:
            if isinstance(t.outputs, str) or not outputs:
                raise ValueError(
                    f"{where}: outputs must be a non-empty sequence of names, got {t.outputs!r}."
                )
            for o in outputs:
                check_name(o, where)
            if len(set(outputs)) != len(outputs):
                raise ValueError(f"{where}: duplicate output names in {outputs!r}.")
        if isinstance(t.reduce, Mapping):
            if t.outputs is None:
                raise ValueError(
                    f"{where}: a dict `reduce` needs `outputs`; for one output use a string."
                )
            extra = set(t.reduce) - set(outputs)
            if extra:
                raise ValueError(
                    f"{where}: reduce names unknown outputs {sorted(extra)}; outputs are "
                    f"{list(outputs)}."
                )
            reduces = {o: t.reduce.get(o, "mean") for o in outputs}
        else:
            reduces = {o: t.reduce for o in outputs}
        reduces = {o: _reductions.check(r, where) for o, r in reduces.items()}
        stats = parse_stats(t.stats, where)
        nonfinite = check_policy(t.nonfinite if t.nonfinite is not None else policy, where)
        grouping = t.groups if t.groups is not None else default_groups
        if grouping is not None and not isinstance(grouping, Groups):
            raise TypeError(
                f"{where}: groups must be jaxmetrics.groups(fn, names), got {grouping!r}."
            )
        for o in outputs:
            metric = name if o is None else f"{name}/{o}"
            specs.append(MetricSpec(metric, name, reduces[o], stats, nonfinite))
            groupings.append(grouping)
        out_terms.append(t)
    return out_terms, specs, groupings


def _with_groups(spec: MetricSpec, grouping: Groups | None) -> list[MetricSpec]:
    """A metric's report rows: the metric over all envs, then one row per group."""
    names = () if grouping is None else grouping.names
    return [spec] + [dataclasses.replace(spec, name=f"{spec.name}/{g}", group=g) for g in names]


def _flatten_logged(logged: Mapping[str, Any] | Sequence[str], policy: str) -> list[MetricSpec]:
    if isinstance(logged, str):
        raise TypeError(f"logged must be a dict or a list of names, got the string {logged!r}.")
    if not isinstance(logged, Mapping):
        logged = {n: Logged() for n in logged}
    specs = []
    for name, spec in logged.items():
        where = f"logged value {name!r}"
        check_name(name, where)
        if not isinstance(spec, Logged):
            raise TypeError(f"{where}: expected jaxmetrics.Logged(...), got {spec!r}.")
        nonfinite = check_policy(spec.nonfinite if spec.nonfinite is not None else policy, where)
        specs.append(MetricSpec(name, name, None, parse_stats(spec.stats, where), nonfinite))
    return specs


class Metrics:
    """A static metrics spec and the pure functions over its `MetricsState`.

    Configuration is validated here; the methods are un-jitted pure functions that work
    under `jit`, `lax.scan`, `lax.cond` and `vmap`.

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
        check_policy(nonfinite, "Metrics(nonfinite=...)")
        dt = jnp.dtype(dtype)
        if not jnp.issubdtype(dt, jnp.floating):
            raise TypeError(f"Metrics(dtype=...) must be a float dtype, got {dt}.")
        if jnp.finfo(dt).bits < 32:
            raise ValueError(
                f"Metrics(dtype={dt}): statistics kept in {dt} are wrong past a few hundred "
                "values (in bfloat16 the mean of 1..1000 comes out as 256; in float16 the "
                "sum overflows at 65504). Use float32 (the default) or float64; terms may "
                f"still return {dt} values."
            )
        if groups is not None and not isinstance(groups, Groups):
            raise TypeError(
                f"Metrics(groups=...) takes jaxmetrics.groups(fn, names), got {groups!r}."
            )
        self._terms, ep_specs, ep_groupings = _flatten_terms(terms or {}, nonfinite, groups)
        # Distinct groupings (each evaluated once per step), with the first term using it.
        self._groupings: tuple[Groups, ...] = ()
        self._grouping_terms: tuple[str, ...] = ()
        for spec, g in zip(ep_specs, ep_groupings):
            if g is not None and g not in self._groupings:
                self._groupings += (g,)
                self._grouping_terms += (spec.term,)
        lg_specs = _flatten_logged(logged or {}, nonfinite)
        if isinstance(counters, str):
            raise TypeError(f"counters must be a list of names, got the string {counters!r}.")
        user_counters = tuple(check_name(c, "counter") for c in counters)
        builtin = BUILTIN_COUNTERS if ep_specs else ()
        builtin += (GROUP_COUNTER,) if self._groupings else ()
        clash = set(user_counters) & set(builtin)
        if clash:
            raise ValueError(f"counters {sorted(clash)} are built in; choose other names.")
        if len(set(user_counters)) != len(user_counters):
            raise ValueError(f"duplicate counter names in {list(user_counters)}.")
        self.counter_names = builtin + user_counters
        # "env_steps", "episodes" and "ungrouped" are counted per env shard
        # (MetricsState.ended).
        self._shard_counters = tuple(c for c in _SHARD_COUNTERS if c in builtin)
        self._stored_counters = tuple(c for c in self.counter_names if c not in _SHARD_COUNTERS)
        for arg, prefix in (
            ("episode_prefix", episode_prefix),
            ("logged_prefix", logged_prefix),
            ("counter_prefix", counter_prefix),
        ):
            check_name(prefix, f"Metrics({arg}=...)")
        self.prefixes = {"episode": episode_prefix, "logged": logged_prefix}
        self._counter_prefix = counter_prefix
        self.dtype = dt

        # Episode rows sorted by reduction (stable): each reduction is one block.
        order = sorted(
            range(len(ep_specs)),
            key=lambda i: _episode.ORDER.index(_reductions.name(ep_specs[i].reduce)),
        )
        self._ep_rows = tuple(ep_specs[i] for i in order)
        # Per episode row, the index of its grouping in self._groupings (None: ungrouped).
        self._ep_row_groups = tuple(
            None if ep_groupings[i] is None else self._groupings.index(ep_groupings[i])
            for i in order
        )
        # Report rows: each metric, then its groups; in definition order for the tag table.
        self._ep_defined = tuple(
            r for spec, g in zip(ep_specs, ep_groupings) for r in _with_groups(spec, g)
        )
        stream_rows = [r for i in order for r in _with_groups(ep_specs[i], ep_groupings[i])]
        # Per report row: its episode row, its grouping (len(groupings): none) and group.
        src, kind, group = [], [], []
        for r, k in enumerate(self._ep_row_groups):
            names = () if k is None else self._groupings[k].names
            src += [r] * (1 + len(names))
            kind += [len(self._groupings)] + [k] * len(names)  # type: ignore[list-item]
            group += [0, *range(len(names))]
        self._report_rows = tuple(np.asarray(a, np.int32) for a in (src, kind, group))
        self._episode_plan = _episode.EpisodePlan.build([s.reduce for s in self._ep_rows], dt)
        self._ep_plan = _stream.StreamPlan.build(stream_rows, dt) if ep_specs else None
        self._lg_plan = _stream.StreamPlan.build(lg_specs, dt) if lg_specs else None
        self._lg_index = {s.name: i for i, s in enumerate(lg_specs)}
        self._ep_propagate = np.array([s.nonfinite == "propagate" for s in self._ep_rows], bool)
        self._lg_propagate = np.array([s.nonfinite == "propagate" for s in lg_specs], bool)

        infos: list[TagInfo] = []
        for group, specs in (("episode", self._ep_defined), ("logged", lg_specs)):
            for s in specs:
                for stat in _statistics.reported(s.stats):
                    infos.append(_tags.info(self.prefixes[group], group, s.name, stat))
        for c in self.counter_names:
            infos.append(_tags.info(counter_prefix, "counter", c, "total"))
        _tags.check_unique((i.tag, _tags.origin(i)) for i in infos)
        self.tags: tuple[TagInfo, ...] = tuple(infos)
        config = (self._ep_defined, lg_specs, self.counter_names, self.prefixes, counter_prefix)
        canon = repr(_canonical((config, dt.name, STATE_LAYOUT))).encode()
        self._spec = spec_id(hashlib.sha256(canon).hexdigest())

    # ------------------------------------------------------------------ static views

    @property
    def metric_specs(self) -> dict[str, MetricSpec]:
        """Every metric by name: episode metrics (`term` or `term/output`) and logged values."""
        out = {s.name: s for s in self._ep_defined}
        out.update({s.name: s for s in (self._lg_plan.rows if self._lg_plan else ())})
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
          ValueError: if `num_envs` does not split evenly into the shards.
          TypeError: for a sharding other than a `NamedSharding` or a single device.
        """
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {num_envs!r}.")
        if num_envs < 0:
            raise ValueError(f"num_envs must be >= 0, got {num_envs}.")
        num_envs = int(num_envs)
        shards = env_layout(sharding, num_envs)
        if num_envs == 0 and sharding is None:
            shards = 0  # no shard at all: concatenating it in `merge` changes nothing
        if not isinstance(sharding, jax.sharding.NamedSharding):
            state = self._fresh(num_envs, shards)
            return state if sharding is None else jax.device_put(state, sharding)
        place = self.state_sharding(sharding)
        # out_shardings places it under Auto axes; device_put types it under Explicit ones.
        return jax.jit(
            lambda: jax.device_put(self._fresh(num_envs, shards), place), out_shardings=place
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
        return self._fresh_layout(
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(None, env_axes)),
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec(env_axes)),
            jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()),
        )

    def _fresh(self, num_envs: int, shards: int, ema_history: bool = False) -> MetricsState:
        """A zero state; `ema_history` keeps each EMA row's newest values even with one
        shard, for a state that will be merged with other devices' (one per device under
        `pmap`), as a sharded state keeps them."""
        has_ep = self._ep_plan is not None
        n_counters = len(self._stored_counters)

        def per_shard(x: jax.Array) -> jax.Array:
            return jnp.broadcast_to(x, (shards, *x.shape))

        return MetricsState(
            running=_episode.init(self._episode_plan, num_envs) if has_ep else None,
            finished=jax.tree.map(per_shard, _stream.init(self._ep_plan, ema_history or shards > 1))
            if has_ep
            else None,
            ended=_count.zeros(
                (shards, _stream.tally_width(self._ep_plan, len(self._shard_counters)))
            )
            if has_ep
            else None,
            logged=_stream.init(self._lg_plan) if self._lg_plan else None,
            counters=_count.zeros((n_counters,)) if n_counters else None,
            spec=self._spec,
        )

    def _fresh_layout(self, running: Any, per_shard: Any, replicated: Any) -> MetricsState:
        """A MetricsState-shaped tree of one leaf value per field group."""
        plan = self._ep_plan
        has_ep = plan is not None

        def fill(tree: Any, v: Any) -> Any:
            return jax.tree.map(lambda _: v, tree)

        shapes = jax.eval_shape(lambda: self._fresh(0, 2))
        return MetricsState(
            running=fill(shapes.running, running) if has_ep else None,
            finished=fill(shapes.finished, per_shard) if has_ep else None,
            ended=fill(shapes.ended, per_shard) if has_ep else None,
            logged=fill(shapes.logged, replicated) if self._lg_plan else None,
            counters=fill(shapes.counters, replicated) if shapes.counters is not None else None,
            spec=self._spec,
        )

    @staticmethod
    def to_checkpoint(state: MetricsState) -> MetricsState:
        """The state with its zero-size arrays (statistics the spec does not keep) set to
        None, for orbax-checkpoint, which refuses to save zero-size arrays. Restore
        with `from_checkpoint`. flax.serialization takes the state as it is.

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
        return jax.tree.map(lambda x: None if x.size == 0 else x, state)

    def from_checkpoint(self, saved: MetricsState, target: MetricsState) -> MetricsState:
        """A state restored from `to_checkpoint`'s tree: its None leaves become `target`'s
        zero-size arrays (`target`: `init` with the same `num_envs` and sharding).

        Restore the checkpoint with its target (orbax: `ckpt.restore(path,
        metrics.to_checkpoint(target))`), so that it comes back as a MetricsState; a
        tree of another structure (orbax's target-less restore gives plain dicts), shape
        or dtype is refused here, before any of it is used.
        """
        target = self._check_state(target, "from_checkpoint")
        want = self.to_checkpoint(target)
        if not isinstance(saved, MetricsState) or (
            jax.tree.structure(saved) != jax.tree.structure(want)
        ):
            raise ValueError(
                f"from_checkpoint: the saved tree ({type(saved).__name__}) is not the "
                "MetricsState that to_checkpoint(target) gives. Restore the checkpoint with "
                "its target, e.g. orbax's ckpt.restore(path, metrics.to_checkpoint("
                "metrics.init(num_envs))), with the spec, num_envs and sharding it was "
                "saved with."
            )
        for (path, x), y in zip(jax.tree_util.tree_leaves_with_path(saved), jax.tree.leaves(want)):
            if jnp.shape(x) != y.shape or jnp.result_type(x) != y.dtype:
                where = jax.tree_util.keystr(path)
                raise ValueError(
                    f"from_checkpoint: {where} is {jnp.result_type(x)}{list(jnp.shape(x))}, "
                    f"but the target has {y.dtype}{list(y.shape)}: pass init() of the spec, "
                    "num_envs and sharding the checkpoint was made with."
                )
        it = iter(jax.tree.leaves(saved))
        leaves = [x if x.size == 0 else next(it) for x in jax.tree.leaves(target)]
        return jax.tree.unflatten(jax.tree.structure(target), leaves)

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
        return state

    def _evaluate(self, step_input: Any, num_envs: int) -> jax.Array:
        values: dict[str, jax.Array] = {}
        for name, term in zip(self._term_names(), self._terms):
            out = term.fn(step_input, **term.params)
            if term.outputs is None:
                if isinstance(out, Mapping):
                    raise TypeError(
                        f"term {name!r} returned a dict with keys {sorted(out)} but declares "
                        f"no outputs; declare them: Term(fn, outputs={sorted(out)!r})."
                    )
                values[name] = self._check_value(out, name, num_envs)
                continue
            if not isinstance(out, Mapping):
                raise TypeError(
                    f"term {name!r} declares outputs {list(term.outputs)} but returned "
                    f"{type(out).__name__}; return a dict with exactly those keys."
                )
            if set(out) != set(term.outputs):
                raise ValueError(
                    f"term {name!r} returned keys {sorted(out)}; its outputs are "
                    f"{sorted(term.outputs)}. Return exactly the declared outputs."
                )
            for o in term.outputs:
                values[f"{name}/{o}"] = self._check_value(out[o], f"{name}/{o}", num_envs)
        return jnp.stack([values[s.name] for s in self._ep_rows])

    def _term_names(self) -> list[str]:
        seen: list[str] = []
        for s in self._ep_defined:
            if s.term not in seen:
                seen.append(s.term)
        return seen

    def _check_value(self, v: Any, name: str, num_envs: int) -> jax.Array:
        a = _as_array(v, f"term {name!r}")
        if a.shape != (num_envs,):
            if a.ndim == 0:
                fix = "it returned a scalar; broadcast it with jnp.full((num_envs,), value)"
            elif a.ndim == 2 and a.shape[0] == num_envs and a.shape[1] == 1:
                fix = "drop the trailing axis with .squeeze(-1)"
            elif a.ndim >= 2 and a.shape[0] == num_envs:
                fix = "reduce the extra axes, e.g. .sum(-1) or jnp.linalg.norm(x, axis=-1)"
            else:
                fix = "return one value per env"
            raise ValueError(
                f"term {name!r} returned shape {a.shape}; expected (num_envs,)=({num_envs},): "
                f"{fix}."
            )
        return a.astype(self.dtype)

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
        done = _as_array(done, "update: done")
        if done.shape != (num_envs,):
            raise ValueError(
                f"update: done must be a bool array of shape (num_envs,)=({num_envs},), got "
                f"{done.dtype}{list(done.shape)}."
            )
        if jnp.issubdtype(done.dtype, jnp.floating):
            raise TypeError(
                f"update: done has dtype {done.dtype}; pass a bool array. A float done (0.1, "
                "NaN, -1) has no single meaning; Brax's State.done is 0.0/1.0: pass "
                "state.done.astype(bool)."
            )
        shards = state.ended.hi.shape[0]  # type: ignore[union-attr]
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
        done = done.astype(jnp.bool_) if done.dtype != jnp.bool_ else done
        x = like(self._evaluate(step_input, num_envs), state.running.steps, "the term values")
        done = like(done, state.running.steps[0], "done")
        prop = jnp.asarray(self._ep_propagate)[:, None]
        finite = jnp.isfinite(x)
        running, values, any_step = _episode.step(
            self._episode_plan, state.running, x, finite | prop, done
        )
        ended = done[None, :] & any_step
        ok = ended & (jnp.isfinite(values) | prop)
        bad = (~finite).astype(jnp.int32) + (ended & ~ok).astype(jnp.int32)
        group_ids = [
            like(i, state.running.steps[0], f"the group indices of {where}")
            for i, where in self._group_ids(step_input, num_envs)
        ]
        values, ok, bad = self._by_group(values, ok, bad, group_ids)
        # Materialized once (after the group split): without the barrier XLA recomputes
        # the episode values from the old accumulators inside each reduction, which makes
        # it copy them every step (H100, isolated update: 13.3 instead of 16.4 us/step for
        # the simple spec).
        values, ok, bad = jax.lax.optimization_barrier((values, ok, bad))

        def by_shard(a: jax.Array) -> jax.Array:
            # [M, E] -> [S, M, E/S]: shard s gets the s-th block of envs. With the env axis
            # split over devices in S blocks this is a local view, and everything below
            # reduces within a shard only.
            return jnp.moveaxis(a.reshape(a.shape[0], shards, num_envs // shards), 1, 0)

        plan = self._ep_plan
        assert plan is not None

        # Per shard (`_SHARD_COUNTERS`): env steps, episodes ended, and those whose group
        # index is out of range, counted in the fold's own reduction.
        shard_counts = [jnp.ones_like(done), done]
        if group_ids:
            out_of_range = [
                done & ((i < 0) | (i >= len(g.names))) for g, i in zip(self._groupings, group_ids)
            ]
            shard_counts.append(jnp.sum(jnp.stack(out_of_range), axis=0, dtype=jnp.int32))
        tally = jnp.stack([c.astype(jnp.int32) for c in shard_counts])

        def fold(st, v, m, n, t, e):
            return _stream.add_tallied(plan, st, v, m, n, t, e, fused=shards == 1)

        args = (
            state.finished,
            by_shard(values),
            by_shard(ok),
            by_shard(bad),
            by_shard(tally),
            state.ended,
        )
        if shards == 1:
            # One shard: the plain fold (a vmap of size 1 still batches its scatters).
            first = jax.tree.map(lambda a: a[0], args)
            finished, ended = jax.tree.map(lambda a: a[None], fold(*first))
        else:
            finished, ended = jax.vmap(fold)(*args)
        return state._replace(running=running, finished=finished, ended=ended)

    def _group_ids(self, step_input: Any, num_envs: int) -> list[tuple[jax.Array, str]]:
        """Each grouping's group index per env (`[num_envs]` int32), checked, with where
        it comes from (for messages)."""
        out = []
        for g, term in zip(self._groupings, self._grouping_terms):
            where = f"the groups {list(g.names)} of term {term!r}"
            v = g.fn(step_input, **g.params)
            host = None if isinstance(v, jax.Array | jax.core.Tracer) else np.asarray(v)
            if host is not None and host.dtype.kind in "iub":
                # Wide host ints: clipped to just out of range, so they stay out of it.
                a = jnp.asarray(np.clip(host, -1, len(g.names)).astype(np.int32))
            else:
                a = _as_array(v, where)
            if not (jnp.issubdtype(a.dtype, jnp.integer) or a.dtype == jnp.bool_):
                raise TypeError(
                    f"{where}: the group function returned dtype {a.dtype}; return each env's "
                    f"group index as an int array (0 for {g.names[0]!r}, ...)."
                )
            if a.shape != (num_envs,):
                raise ValueError(
                    f"{where}: the group function returned shape {a.shape}; expected one "
                    f"index per env, (num_envs,)=({num_envs},)."
                )
            if a.dtype != jnp.bool_ and jnp.iinfo(a.dtype).bits > 32:
                a = jnp.clip(a, -1, len(g.names))
            out.append((a.astype(jnp.int32), where))
        return out

    def _by_group(
        self, values: jax.Array, ok: jax.Array, bad: jax.Array, group_ids: list[jax.Array]
    ) -> tuple[jax.Array, jax.Array, jax.Array]:
        """Episode rows `[M, E]` as report rows: each metric over all envs, then (for a
        grouped metric) once per group, masked to the envs in that group. One compare
        per grouping; no work per group beyond the elementwise mask."""
        if not self._groupings:
            return values, ok, bad
        src, kind, group = self._report_rows
        # Row K of `ids` is 0 for every env: the overall rows match it as group 0.
        ids = jnp.concatenate([jnp.stack(group_ids), jnp.zeros_like(group_ids[0])[None]])
        match = jnp.take(ids, kind, axis=0) == jnp.asarray(group)[:, None]
        take = lambda a: jnp.take(a, src, axis=0)  # noqa: E731
        return take(values), take(ok) & match, take(bad) * match.astype(jnp.int32)

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
        unknown = sorted(set(values) - set(self._lg_index))
        if unknown:
            raise ValueError(
                f"log: unknown logged names {unknown}; declare them in "
                f"Metrics(logged=...). Known: {sorted(self._lg_index)}."
            )
        flat = {}
        for name, v in values.items():
            a = _as_array(v, f"log: {name!r}")
            if a.size:  # an empty array logs nothing
                flat[name] = a.reshape(-1).astype(self.dtype)
        if not flat:
            return state
        assert self._lg_plan is not None and state.logged is not None
        width = max(a.shape[0] for a in flat.values())
        rows = len(self._lg_plan.rows)
        v = jnp.zeros((rows, width), self.dtype)
        m = jnp.zeros((rows, width), jnp.bool_)
        for name, a in flat.items():
            i = self._lg_index[name]
            v = v.at[i, : a.shape[0]].set(a)
            m = m.at[i, : a.shape[0]].set(True)
        finite = jnp.isfinite(v)
        ok = m & (finite | jnp.asarray(self._lg_propagate)[:, None])
        bad = (m & ~finite).astype(jnp.int32)
        logged = _stream.add(self._lg_plan, state.logged, v, ok, bad)
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
        if name in self._shard_counters:
            raise ValueError(f"increment: {name!r} is counted by update; it cannot be incremented.")
        j = self._stored_counters.index(name)
        assert state.counters is not None
        return state._replace(counters=_count.add_at(state.counters, j, by))

    def reset_period(self, state: MetricsState) -> MetricsState:
        """Starts a new flush period: period statistics clear; windows, EMA, counters and
        running episodes carry on."""
        state = self._check_state(state, "reset_period")
        plan = self._ep_plan
        return state._replace(
            finished=jax.vmap(lambda st: _stream.reset_period(plan, st))(state.finished)
            if plan
            else None,
            logged=_stream.reset_period(self._lg_plan, state.logged) if self._lg_plan else None,
        )

    def merge(self, a: MetricsState, b: MetricsState) -> MetricsState:
        """Combines the states of disjoint workers (devices, hosts, seeds) that ran side by
        side, as one run over both env batches (`b`'s envs after `a`'s).

        Mean/std are count-weighted (Chan); sum, count, min, max, histograms and counters
        are exact; windows keep the newest `n` by arrival step (`b`'s values after `a`'s
        of the same step); the EMA folds both workers' values in that order, exact to
        2^-32 of the values' range for states made by a sharded `init` and the average
        of the workers' EMAs otherwise (see the README). Running episodes are
        concatenated along the env axis; env shards are concatenated when both states
        have the same envs per shard, else each state's shards are merged into one first.
        Associative, with `empty()` as identity.
        """
        a = self._check_state(a, "merge")
        b = self._check_state(b, "merge")
        finished, ended = None, None
        if self._ep_plan is not None:
            finished, ended = self._merge_shards(a, b)
        return MetricsState(
            running=None
            if a.running is None
            else jax.tree.map(lambda x, y: jnp.concatenate([x, y], axis=-1), a.running, b.running),
            finished=finished,
            ended=ended,
            logged=None
            if self._lg_plan is None
            else _stream.merge(self._lg_plan, a.logged, b.logged),
            counters=None if a.counters is None else _count.merge(a.counters, b.counters),
            spec=self._spec,
        )

    def _merge_shards(self, a: MetricsState, b: MetricsState) -> tuple[Any, Count]:
        plan = self._ep_plan
        assert plan is not None and a.ended is not None and b.ended is not None
        sa, sb = a.ended.hi.shape[0], b.ended.hi.shape[0]
        if sa == 0 or sb == 0:
            return (b.finished, b.ended) if sa == 0 else (a.finished, a.ended)
        per_a = a.running.steps.shape[-1] // sa  # type: ignore[union-attr]
        per_b = b.running.steps.shape[-1] // sb  # type: ignore[union-attr]
        fa, fb, ea, eb = a.finished, b.finished, a.ended, b.ended
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

    def compute(
        self, state: MetricsState, include_running: bool = False
    ) -> dict[str, jax.Array | Count]:
        """The report: tag -> small array (in-graph; O(metrics), not O(num_envs)).

        Counts (`/count`, `/nonfinite`, `/histogram`, counters) are exact `Count` pairs;
        `to_host` turns them into Python ints. Empty statistics are NaN.

        Args:
          state: the current state.
          include_running: also report `<metric>/running`, the mean over envs of the
            running (unfinished) episodes' current values.
        """
        state = self._check_state(state, "compute")
        out: dict[str, jax.Array | Count] = {}
        finished = None
        if self._ep_plan is not None:
            finished = _stream.combine(self._ep_plan, state.finished)  # type: ignore[arg-type]
        for group, plan, st in (
            ("episode", self._ep_plan, finished),
            ("logged", self._lg_plan, state.logged),
        ):
            if plan is None:
                continue
            rows = [
                row if spec.nonfinite == "propagate" else _count_overflow(row)
                for spec, row in zip(plan.rows, _stream.compute(plan, st))
            ]
            for i, spec in enumerate(plan.rows):
                for stat in _statistics.reported(spec.stats):
                    out[_tags.tag(self.prefixes[group], spec.name, stat)] = rows[i][stat]
        if include_running and state.running is not None:
            run = _episode.running(self._episode_plan, state.running)
            has = ~jnp.isnan(run)
            n = jnp.sum(has, axis=1)
            mean = jnp.sum(jnp.where(has, run, 0), axis=1) / jnp.maximum(n, 1).astype(self.dtype)
            mean = jnp.where(n > 0, mean, jnp.nan)
            for i, spec in enumerate(self._ep_rows):
                out[_tags.tag(self.prefixes["episode"], spec.name, "running")] = mean[i]
        shard_totals = _count.total(state.ended) if state.ended is not None else None
        for c in self.counter_names:
            if c in self._shard_counters:
                j = self._shard_counters.index(c)
                value = Count(shard_totals.hi[j], shard_totals.lo[j])  # type: ignore[union-attr]
            else:
                assert state.counters is not None
                j = self._stored_counters.index(c)
                value = Count(state.counters.hi[j], state.counters.lo[j])
            out[_tags.tag(self._counter_prefix, c, "total")] = value
        return out

    # ------------------------------------------------------------------ host side

    def to_host(self, report: Mapping[str, Any]) -> dict[str, Any]:
        """Host side: fetches a report; scalars become floats, counts exact Python ints,
        histograms and window values numpy arrays."""
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
        specs = {("episode", s.name): s for s in self._ep_defined}
        specs.update({("logged", s.name): s for s in (self._lg_plan.rows if self._lg_plan else ())})
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
