"""A `Metrics` spec's static side: its arguments checked and flattened into report rows,
stream plans, tags and the spec's identity (`SpecRows`), built once per spec."""

import dataclasses
import hashlib
from collections.abc import Callable, Mapping, Sequence
from typing import Any, NamedTuple, cast

import jax.numpy as jnp
import numpy as np

from . import _episode, _reductions, _stream, _tags
from ._metrics_state import spec_id
from ._spec import Groups, Logged, MetricSpec, Term, check_name, check_policy, parse_stats, reported
from ._tags import TagInfo

BUILTIN_COUNTERS = ("env_steps", "episodes")
GROUP_COUNTER = "ungrouped"
# Counted per env shard in `MetricsState.shard_counts`, one column each, in this order (the
# last only with groups): a step updates them in one kernel, with no cross-device reduction.
SHARD_COUNTERS = ("env_steps", "episodes", GROUP_COUNTER)

# The version of the MetricsState's array format, part of the spec's identity: a checkpoint
# of another format is refused as another spec's instead of being misread. Raise it with
# any change to the state's fields, shapes or meaning.
STATE_FORMAT = 6


@dataclasses.dataclass(frozen=True)
class SpecRows:
    """Everything static about a spec. Episode rows are sorted by reduction (`_episode.ORDER`);
    report rows are each episode metric followed by its groups."""

    terms: tuple[Term, ...]
    groupings: tuple[Groups, ...]  # distinct groupings, each evaluated once per step
    grouping_terms: tuple[str, ...]  # per grouping, the first term that uses it
    counter_names: tuple[str, ...]
    shard_counters: tuple[str, ...]  # counted per env shard (`SHARD_COUNTERS`)
    stored_counters: tuple[str, ...]  # kept in `MetricsState.counters`
    prefixes: dict[str, str]  # "episode" and "logged" tag prefixes
    counter_prefix: str
    dtype: jnp.dtype
    ep_rows: tuple[MetricSpec, ...]
    ep_row_groups: tuple[int | None, ...]  # per episode row, its grouping (None: none)
    ep_defined: tuple[MetricSpec, ...]  # report rows in definition order (the tag table's)
    # Per report row: its episode row, its grouping (len(groupings): none) and group.
    every_row: tuple[np.ndarray, np.ndarray, np.ndarray]
    # The same for the rows folded as rows where segment rows are (every row but those).
    report_rows: tuple[np.ndarray, np.ndarray, np.ndarray]
    # Per segment source (`_stream.SegmentPlan`): its episode row and its grouping.
    segment_sources: tuple[tuple[int, int], ...]
    ep_segments: _stream.SegmentPlan | None  # None: every report row is folded as a row
    episode_plan: _episode.EpisodePlan
    ep_plan: _stream.StreamPlan | None
    lg_plan: _stream.StreamPlan | None
    lg_index: dict[str, int]
    ep_propagate: np.ndarray  # per episode row: its nonfinite policy is "propagate"
    lg_propagate: np.ndarray
    tags: tuple[TagInfo, ...]
    identity: NamedTuple  # `spec_id` of the configuration


def build(
    terms: Mapping[str, Term | Callable[..., Any]] | None,
    logged: Mapping[str, Logged] | Sequence[str] | None,
    counters: Sequence[str],
    nonfinite: str,
    episode_prefix: str,
    logged_prefix: str,
    counter_prefix: str,
    groups: Groups | None,
    dtype: Any,
) -> SpecRows:
    """The `SpecRows` of `Metrics(...)`'s arguments (see `Metrics`), or an error naming the
    argument and the fix."""
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
        raise TypeError(f"Metrics(groups=...) takes jaxmetrics.groups(fn, names), got {groups!r}.")
    flat_terms, ep_specs, ep_groupings = _flatten_terms(terms or {}, nonfinite, groups)
    # Distinct groupings (each evaluated once per step), with the first term using it.
    groupings: tuple[Groups, ...] = ()
    grouping_terms: tuple[str, ...] = ()
    for spec, g in zip(ep_specs, ep_groupings):
        if g is not None and g not in groupings:
            groupings += (g,)
            grouping_terms += (spec.term,)
    lg_specs = _flatten_logged(logged or {}, nonfinite)
    if isinstance(counters, str):
        raise TypeError(f"counters must be a list of names, got the string {counters!r}.")
    user_counters = tuple(check_name(c, "counter") for c in counters)
    builtin = BUILTIN_COUNTERS if ep_specs else ()
    builtin += (GROUP_COUNTER,) if groupings else ()
    clash = set(user_counters) & set(builtin)
    if clash:
        raise ValueError(f"counters {sorted(clash)} are built in; choose other names.")
    if len(set(user_counters)) != len(user_counters):
        raise ValueError(f"duplicate counter names in {list(user_counters)}.")
    counter_names = builtin + user_counters
    shard_counters = tuple(c for c in SHARD_COUNTERS if c in builtin)
    stored_counters = tuple(c for c in counter_names if c not in SHARD_COUNTERS)
    for arg, prefix in (
        ("episode_prefix", episode_prefix),
        ("logged_prefix", logged_prefix),
        ("counter_prefix", counter_prefix),
    ):
        check_name(prefix, f"Metrics({arg}=...)")
    prefixes = {"episode": episode_prefix, "logged": logged_prefix}

    # Episode rows sorted by reduction (stable): each reduction is one block.
    order = sorted(
        range(len(ep_specs)),
        # An episode metric's reduce is set (None only for logged values).
        key=lambda i: _episode.ORDER.index(
            _reductions.name(cast(str | _reductions.Discounted, ep_specs[i].reduce))
        ),
    )
    ep_rows = tuple(ep_specs[i] for i in order)
    # Per episode row, the index of its grouping in groupings (None: ungrouped).
    ep_row_groups = tuple(
        None if ep_groupings[i] is None else groupings.index(ep_groupings[i]) for i in order
    )
    # Report rows: each metric, then its groups; in definition order for the tag table.
    ep_defined = tuple(r for spec, g in zip(ep_specs, ep_groupings) for r in with_groups(spec, g))
    stream_rows = [r for i in order for r in with_groups(ep_specs[i], ep_groupings[i])]
    # Per report row: its episode row, its grouping (len(groupings): none) and group; for
    # every row, and for the rows folded as rows where the group rows of a metric with
    # period statistics only are segment rows instead: folded by segment reductions over
    # the group index (`_stream.SegmentPlan`).
    every: tuple[list[int], list[int], list[int]] = ([], [], [])
    as_rows: tuple[list[int], list[int], list[int]] = ([], [], [])
    sources: list[tuple[int, int]] = []
    blocks: list[tuple[int, int]] = []
    row = 0
    for r, k in enumerate(ep_row_groups):
        names = () if k is None else groupings[k].names
        segmented = k is not None and _period_only(ep_rows[r])
        if segmented:
            assert k is not None
            sources.append((r, k))
            blocks.append((row + 1, len(names)))
        for (src, kind, group), n in (
            (every, len(names)),
            (as_rows, 0 if segmented else len(names)),
        ):
            src += [r] * (1 + n)
            kind += [len(groupings)] + [k] * n  # type: ignore[list-item]
            group += [0, *range(n)]
        row += 1 + len(names)
    every_row = tuple(np.asarray(a, np.int32) for a in every)
    report_rows = tuple(np.asarray(a, np.int32) for a in as_rows)
    assert len(every_row) == 3 and len(report_rows) == 3
    # An episode metric's reduce is set (None only for logged values).
    reductions = [cast(str | _reductions.Discounted, s.reduce) for s in ep_rows]
    episode_plan = _episode.EpisodePlan.build(reductions, dt)
    ep_plan = _stream.StreamPlan.build(stream_rows, dt) if ep_specs else None
    ep_segments = None
    if blocks:
        assert ep_plan is not None
        ep_segments = _stream.SegmentPlan.build(ep_plan, tuple(blocks))
    lg_plan = _stream.StreamPlan.build(lg_specs, dt) if lg_specs else None
    lg_index = {s.name: i for i, s in enumerate(lg_specs)}
    ep_propagate = np.array([s.nonfinite == "propagate" for s in ep_rows], bool)
    lg_propagate = np.array([s.nonfinite == "propagate" for s in lg_specs], bool)

    infos: list[TagInfo] = []
    for group, specs in (("episode", ep_defined), ("logged", lg_specs)):
        for s in specs:
            for stat in reported(s.stats):
                infos.append(_tags.info(prefixes[group], group, s.name, stat))
    for c in counter_names:
        infos.append(_tags.info(counter_prefix, "counter", c, "total"))
    _tags.check_unique((i.tag, _tags.origin(i)) for i in infos)
    tags = tuple(infos)
    config = (ep_defined, lg_specs, counter_names, prefixes, counter_prefix)
    canon = repr(_canonical((config, dt.name, STATE_FORMAT))).encode()
    spec = spec_id(hashlib.sha256(canon).hexdigest())
    return SpecRows(
        terms=tuple(flat_terms),
        groupings=groupings,
        grouping_terms=grouping_terms,
        counter_names=counter_names,
        shard_counters=shard_counters,
        stored_counters=stored_counters,
        prefixes=prefixes,
        counter_prefix=counter_prefix,
        dtype=dt,
        ep_rows=ep_rows,
        ep_row_groups=ep_row_groups,
        ep_defined=ep_defined,
        every_row=every_row,
        report_rows=report_rows,
        segment_sources=tuple(sources),
        ep_segments=ep_segments,
        episode_plan=episode_plan,
        ep_plan=ep_plan,
        lg_plan=lg_plan,
        lg_index=lg_index,
        ep_propagate=ep_propagate,
        lg_propagate=lg_propagate,
        tags=tags,
        identity=spec,
    )


def _period_only(spec: MetricSpec) -> bool:
    """Whether a metric's report statistics are period statistics only: its group rows
    need no ordered data per row (no EMA, window, histogram or sketch)."""
    st = spec.stats
    return st.ema is None and st.window is None and st.histogram is None and st.quantiles is None


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
            # `outputs` are the names here (`t.outputs` is set).
            reduces = {o: t.reduce.get(cast(str, o), "mean") for o in outputs}
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


def with_groups(spec: MetricSpec, grouping: Groups | None) -> list[MetricSpec]:
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
