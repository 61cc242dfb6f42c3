"""The `Metrics` spec: static configuration plus the pure functions over `MetricsState`."""

from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import _count, _episode, _reductions, _statistics, _stream, _tags
from ._count import Count
from ._spec import Logged, MetricSpec, Term, check_name, check_policy, parse_stats
from ._state import MetricsState
from ._tags import TagInfo

BUILTIN_COUNTERS = ("env_steps", "episodes")


def _is_numeric(dtype) -> bool:
    return jnp.issubdtype(dtype, jnp.bool_) or (
        jnp.issubdtype(dtype, jnp.number) and not jnp.issubdtype(dtype, jnp.complexfloating)
    )


def _like(x: jax.Array, ref: jax.Array) -> jax.Array:
    """`x` laid out like the state's `ref` over an explicit mesh (a no-op otherwise).

    Under explicit sharding JAX refuses to mix differently sharded operands; the state's
    layout wins, so a scan carry keeps its type: a replicated state gathers the inputs, a
    state sharded over envs keeps them sharded.
    """
    want = getattr(jax.typeof(ref).sharding, "spec", None)
    have = getattr(jax.typeof(x).sharding, "spec", None)
    if want is None or have is None or tuple(want) == tuple(have):
        return x
    if all(p is None for p in want) and all(p is None for p in have):
        return x
    return jax.sharding.reshard(x, want)


def _flatten_terms(terms: Mapping[str, Any], policy: str) -> tuple[list[Term], list[MetricSpec]]:
    if not isinstance(terms, Mapping):
        raise TypeError(
            f"terms must be a dict of name -> jaxmetrics.Term (or function), got "
            f"{type(terms).__name__}."
        )
    out_terms, specs = [], []
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
        for r in reduces.values():
            _reductions.check(r, where)
        stats = parse_stats(t.stats, where)
        nonfinite = check_policy(t.nonfinite if t.nonfinite is not None else policy, where)
        for o in outputs:
            metric = name if o is None else f"{name}/{o}"
            specs.append(MetricSpec(metric, name, reduces[o], stats, nonfinite))
        out_terms.append(t)
    return out_terms, specs


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
      dtype: float dtype of the state.

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
        dtype: Any = jnp.float32,
    ):
        check_policy(nonfinite, "Metrics(nonfinite=...)")
        dt = jnp.dtype(dtype)
        if not jnp.issubdtype(dt, jnp.floating):
            raise TypeError(f"Metrics(dtype=...) must be a float dtype, got {dt}.")
        self._terms, ep_specs = _flatten_terms(terms or {}, nonfinite)
        lg_specs = _flatten_logged(logged or {}, nonfinite)
        if isinstance(counters, str):
            raise TypeError(f"counters must be a list of names, got the string {counters!r}.")
        user_counters = tuple(check_name(c, "counter") for c in counters)
        builtin = BUILTIN_COUNTERS if ep_specs else ()
        clash = set(user_counters) & set(builtin)
        if clash:
            raise ValueError(f"counters {sorted(clash)} are built in; choose other names.")
        if len(set(user_counters)) != len(user_counters):
            raise ValueError(f"duplicate counter names in {list(user_counters)}.")
        self.counter_names = builtin + user_counters
        self.prefixes = {"episode": episode_prefix, "logged": logged_prefix}
        self._counter_prefix = counter_prefix
        self.dtype = dt

        # Episode rows sorted by reduction (stable): each reduction is one block.
        order = sorted(range(len(ep_specs)), key=lambda i: _episode.ORDER.index(ep_specs[i].reduce))
        self._ep_rows = tuple(ep_specs[i] for i in order)
        self._ep_defined = tuple(ep_specs)  # definition order, for the tag table
        self._episode_plan = _episode.EpisodePlan.build([s.reduce for s in self._ep_rows], dt)
        self._ep_plan = _stream.StreamPlan.build(self._ep_rows, dt) if ep_specs else None
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

    def init(self, num_envs: int) -> MetricsState:
        """A fresh state for `num_envs` envs (0 gives the identity element of `merge`)."""
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)):
            raise TypeError(f"num_envs must be an int, got {num_envs!r}.")
        if num_envs < 0:
            raise ValueError(f"num_envs must be >= 0, got {num_envs}.")
        has_ep = self._ep_plan is not None
        return MetricsState(
            episode=_episode.init(self._episode_plan, int(num_envs)) if has_ep else None,
            episodes=_stream.init(self._ep_plan) if has_ep else None,
            logged=_stream.init(self._lg_plan) if self._lg_plan else None,
            counters=_count.zeros((len(self.counter_names),)) if self.counter_names else None,
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
        ok = (state.episode is None) == (self._ep_plan is None)
        ok &= (state.logged is None) == (self._lg_plan is None)
        if ok and state.episode is not None:
            ok = state.episode.steps.shape[-2] == self._episode_plan.rows
        if ok and state.logged is not None and self._lg_plan is not None:
            ok = state.logged.mean.shape[-1] == len(self._lg_plan.rows)
        if not ok:
            raise ValueError(
                f"{fn}: this state was built by a different Metrics spec; call init() on "
                "the spec that updates it."
            )
        return state

    def _evaluate(self, step_input: Any, num_envs: int) -> jax.Array:
        values: dict[str, jax.Array] = {}
        for name, term in zip(self._term_names(), self._terms):
            out = term.fn(step_input, **term.params)
            if term.outputs is None:
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
        try:
            a = jnp.asarray(v)
        except TypeError as e:
            raise TypeError(
                f"term {name!r} returned {type(v).__name__}, not an array: {e}. Return a "
                f"float/int/bool array of shape (num_envs,)=({num_envs},)."
            ) from None
        if not _is_numeric(a.dtype):
            raise TypeError(
                f"term {name!r} returned dtype {a.dtype}; terms must return float, int or "
                "bool values."
            )
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

        Args:
          state: the current state.
          step_input: anything the term functions take (e.g. a Brax `State`).
          done: `[num_envs]` bool (or 0/1): whether each env's episode ends on this step.
            The step is part of the episode it ends.

        Returns:
          The new state.
        """
        state = self._check_state(state, "update")
        if state.episode is None:
            return state
        num_envs = state.episode.steps.shape[-1]
        done = jnp.asarray(done)
        if done.shape != (num_envs,) or not _is_numeric(done.dtype):
            raise ValueError(
                f"done must be a bool array of shape (num_envs,)=({num_envs},), got "
                f"{done.dtype}{list(done.shape)}."
            )
        done = done.astype(jnp.bool_) if done.dtype != jnp.bool_ else done
        x = _like(self._evaluate(step_input, num_envs), state.episode.steps)
        done = _like(done, state.episode.steps[0])
        prop = jnp.asarray(self._ep_propagate)[:, None]
        finite = jnp.isfinite(x)
        episode, values, any_step = _episode.step(
            self._episode_plan, state.episode, x, finite | prop, done
        )
        ended = done[None, :] & any_step
        ok = ended & (jnp.isfinite(values) | prop)
        bad = jnp.sum(~finite, axis=1, dtype=jnp.int32) + jnp.sum(
            ended & ~ok, axis=1, dtype=jnp.int32
        )
        assert self._ep_plan is not None
        episodes = _stream.add(self._ep_plan, state.episodes, values, ok)
        episodes = _stream.add_nonfinite(episodes, bad)
        counters = state.counters
        inc = jnp.zeros((len(self.counter_names),), jnp.int32)
        inc = inc.at[0].set(num_envs).at[1].set(jnp.sum(done, dtype=jnp.int32))
        counters = _count.add(counters, inc)
        return state._replace(episode=episode, episodes=episodes, counters=counters)

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
        if not values:
            return state
        assert self._lg_plan is not None and state.logged is not None
        flat = {}
        for name, v in values.items():
            a = jnp.asarray(v)
            if not _is_numeric(a.dtype):
                raise TypeError(
                    f"log: {name!r} has dtype {a.dtype}; log float, int or bool values."
                )
            flat[name] = a.reshape(-1).astype(self.dtype)
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
        logged = _stream.add(self._lg_plan, state.logged, v, ok)
        logged = _stream.add_nonfinite(logged, jnp.sum(m & ~finite, axis=1, dtype=jnp.int32))
        return state._replace(logged=logged)

    def increment(self, state: MetricsState, name: str, by: Any = 1) -> MetricsState:
        """Adds `by` (a non-negative int below 2^32) to the lifetime counter `name`."""
        state = self._check_state(state, "increment")
        if name not in self.counter_names:
            raise ValueError(
                f"increment: unknown counter {name!r}; declare it in Metrics(counters=...). "
                f"Known: {list(self.counter_names)}."
            )
        assert state.counters is not None
        if isinstance(by, (int, np.integer)) and not isinstance(by, bool):
            if not 0 <= by < 2**32:
                raise ValueError(f"increment: `by` must be in [0, 2^32), got {by}.")
            by = np.uint32(by)  # a Python int >= 2^31 does not fit the default int32
        by = jnp.asarray(by)
        if not jnp.issubdtype(by.dtype, jnp.integer) or by.shape != ():
            raise TypeError(
                f"increment: `by` must be a scalar int, got {by.dtype}{list(by.shape)}."
            )
        inc = jnp.zeros((len(self.counter_names),), jnp.uint32)
        inc = inc.at[self.counter_names.index(name)].set(by.astype(jnp.uint32))
        return state._replace(counters=_count.add(state.counters, inc))

    def reset_period(self, state: MetricsState) -> MetricsState:
        """Starts a new flush period: period statistics clear; windows, EMA, counters and
        running episodes carry on."""
        state = self._check_state(state, "reset_period")
        return state._replace(
            episodes=_stream.reset_period(self._ep_plan, state.episodes) if self._ep_plan else None,
            logged=_stream.reset_period(self._lg_plan, state.logged) if self._lg_plan else None,
        )

    def merge(self, a: MetricsState, b: MetricsState) -> MetricsState:
        """Combines the states of disjoint workers (devices, hosts, seeds).

        Mean/std are count-weighted (Chan); sum, count, min, max, histograms and counters
        are exact; windows keep the newest `n` with `b`'s values after `a`'s; EMA is the
        average of the workers' EMAs (each seeded worker weighs 1). Running episodes are
        concatenated along the env axis. Associative, with `empty()` as identity.
        """
        a = self._check_state(a, "merge")
        b = self._check_state(b, "merge")
        return MetricsState(
            episode=None
            if a.episode is None
            else jax.tree.map(lambda x, y: jnp.concatenate([x, y], axis=-1), a.episode, b.episode),
            episodes=None
            if self._ep_plan is None
            else _stream.merge(self._ep_plan, a.episodes, b.episodes),
            logged=None
            if self._lg_plan is None
            else _stream.merge(self._lg_plan, a.logged, b.logged),
            counters=None if a.counters is None else _count.merge(a.counters, b.counters),
        )

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
        for group, plan, st in (
            ("episode", self._ep_plan, state.episodes),
            ("logged", self._lg_plan, state.logged),
        ):
            if plan is None:
                continue
            rows = _stream.compute(plan, st)
            for i, spec in enumerate(plan.rows):
                for stat in _statistics.reported(spec.stats):
                    out[_tags.tag(self.prefixes[group], spec.name, stat)] = rows[i][stat]
        if include_running and state.episode is not None:
            run = _episode.running(self._episode_plan, state.episode)
            has = ~jnp.isnan(run)
            n = jnp.sum(has, axis=1)
            mean = jnp.sum(jnp.where(has, run, 0), axis=1) / jnp.maximum(n, 1).astype(self.dtype)
            mean = jnp.where(n > 0, mean, jnp.nan)
            for i, spec in enumerate(self._ep_rows):
                out[_tags.tag(self.prefixes["episode"], spec.name, "running")] = mean[i]
        if state.counters is not None:
            for j, c in enumerate(self.counter_names):
                out[_tags.tag(self._counter_prefix, c, "total")] = Count(
                    state.counters.hi[j], state.counters.lo[j]
                )
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
