"""What a step hands a `Metrics` spec, checked: its term values, its group indices, and
the episode rows as report rows (each metric, then one row per group)."""

from collections.abc import Mapping
from typing import Any, NamedTuple

import jax
import jax.core  # jax.core.Tracer: imported by jax, named here for the type checker
import jax.numpy as jnp
import numpy as np

from ._rows import SpecRows
from ._stream import Selected


def _is_numeric(dtype) -> bool:
    return jnp.issubdtype(dtype, jnp.bool_) or (
        jnp.issubdtype(dtype, jnp.number) and not jnp.issubdtype(dtype, jnp.complexfloating)
    )


def as_array(v: Any, what: str) -> jax.Array:
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
        # Config options are attributes set at run time.
        if host.dtype.kind in "iuO" and not jax.config.jax_enable_x64:  # pyright: ignore[reportAttributeAccessIssue]
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


def done_flags(done: Any, num_envs: int) -> jax.Array:
    """`update`'s `done` as a bool array `[num_envs]`, or an error naming the fix."""
    done = as_array(done, "update: done")
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
    return done.astype(jnp.bool_) if done.dtype != jnp.bool_ else done


def term_values(rows: SpecRows, step_input: Any, num_envs: int) -> jax.Array:
    """Every episode row's value of this step, `[M, num_envs]` in the spec's dtype, or an
    error naming the term and the fix."""
    values: dict[str, jax.Array] = {}
    for name, term in zip(_term_names(rows), rows.terms):
        out = term.fn(step_input, **term.params)
        if term.outputs is None:
            if isinstance(out, Mapping):
                raise TypeError(
                    f"term {name!r} returned a dict with keys {sorted(out)} but declares "
                    f"no outputs; declare them: Term(fn, outputs={sorted(out)!r})."
                )
            values[name] = _check_value(rows.dtype, out, name, num_envs)
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
            values[f"{name}/{o}"] = _check_value(rows.dtype, out[o], f"{name}/{o}", num_envs)
    return jnp.stack([values[s.name] for s in rows.ep_rows])


def _term_names(rows: SpecRows) -> list[str]:
    seen: list[str] = []
    for s in rows.ep_defined:
        if s.term not in seen:
            seen.append(s.term)
    return seen


def _check_value(dtype: Any, v: Any, name: str, num_envs: int) -> jax.Array:
    a = as_array(v, f"term {name!r}")
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
            f"term {name!r} returned shape {a.shape}; expected (num_envs,)=({num_envs},): {fix}."
        )
    return a.astype(dtype)


def group_ids(rows: SpecRows, step_input: Any, num_envs: int) -> list[tuple[jax.Array, str]]:
    """Each grouping's group index per env (`[num_envs]` int32), checked, with where
    it comes from (for messages)."""
    out = []
    for g, term in zip(rows.groupings, rows.grouping_terms):
        where = f"the groups {list(g.names)} of term {term!r}"
        v = g.fn(step_input, **g.params)
        host = None if isinstance(v, jax.Array | jax.core.Tracer) else np.asarray(v)
        if host is not None and host.dtype.kind in "iub":
            # Wide host ints: clipped to just out of range, so they stay out of it.
            a = jnp.asarray(np.clip(host, -1, len(g.names)).astype(np.int32))
        else:
            a = as_array(v, where)
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


class Segments(NamedTuple):
    """The segment sources' batch (`[sources, E]`, `_stream.SegmentPlan`): their episode
    values, which to fold, their non-finite counts, and each env's group index."""

    values: jax.Array
    ok: jax.Array
    bad: jax.Array
    group: jax.Array


def by_group(
    rows: SpecRows,
    values: jax.Array,
    ok: jax.Array,
    bad: jax.Array,
    group_ids: list[jax.Array],
    segmented: bool,
) -> tuple[Selected, Segments | None]:
    """Episode rows `[M, E]` as the report rows folded as rows (`_stream.Selected`): each
    metric over all envs, then (for a grouped metric that has rows per group) once per
    group, masked to the envs in that group; and, where `segmented`, the segment
    sources' inputs (`Segments`; None without segment rows), whose group rows are then
    not among the rows. No copy of the batch per group: the rows select from it."""
    if not rows.groupings:
        return Selected.every(values, ok, bad), None
    segmented = segmented and bool(rows.segment_sources)
    src, kind, group = rows.report_rows if segmented else rows.every_row
    # Rows of every env (kind K) select no grouping.
    kind = np.where(kind == len(rows.groupings), -1, kind)
    ids = jnp.stack(group_ids)
    dense = Selected(values, ok, bad, ids, *(tuple(int(i) for i in a) for a in (src, kind, group)))
    if not segmented:
        return dense, None
    s_src, s_kind = (np.asarray(a, np.int32) for a in zip(*rows.segment_sources))
    pick = lambda a: jnp.take(a, s_src, axis=0)  # noqa: E731
    return dense, Segments(pick(values), pick(ok), pick(bad), jnp.take(ids, s_kind, axis=0))
