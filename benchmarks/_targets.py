"""The targets the project holds itself to, judged on the tables of a run.

A per-step host callback logger is a reference row of the alternatives, not a target:
the hand-written floor itself is less than 100x cheaper than that logger, so a ratio to
it measured the rollout's noise, not jaxmetrics (45x to 78x in two runs of one tree on an
H100, `h100_e2e.json` the first).
"""

from collections.abc import Callable, Sequence

from . import _live, _rollout, _sharded
from ._report import Table

NOTE = "met '-': judged by reading the numbers (noise-limited), not a threshold."

FLOOR_RATIO = 1.5
"""The isolated update's bound, in multiples of the hand-written floor, at every size; and
the per-group update's, in multiples of the ungrouped one (GPU)."""

E2E_POINTS = 0.3
"""The end-to-end bound: percentage points of overhead above the floor's, same run."""

LIVE_POINTS = 0.1
"""The live-read bound: percentage points of the rollout's step that a curriculum's
every-step read adds to the device's busy time (`_live`). Its wall clock is shown beside,
not judged: two loads of one program ran 0.29% apart on an H200, steadily."""

DEVICES_POINTS = 0.5
"""The many-device bound: percentage points of overhead above one device's, same run."""


def _find(tables: Sequence[Table], name: str) -> Table | None:
    return next((t for t in tables if t.name == name), None)


def _isolated(t: Table, iso: Table, tables: Sequence[Table], backend: str) -> None:
    ratio = next(r[2] for r in iso.rows if r[0].startswith("jaxmetrics: full"))
    t.add(f"isolated update <= {FLOOR_RATIO}x the floor", f"{ratio:.2f}x", ratio <= FLOOR_RATIO)


def _scaling(t: Table, envs: Table, tables: Sequence[Table], backend: str) -> None:
    terms = _find(tables, "scaling_terms")
    sizes = [(f"{r[0]:,} envs", r[3]) for r in envs.rows]
    if "simple x floor" in envs.columns:
        at = envs.columns.index("simple x floor")
        sizes += [(f"{r[0]:,} envs (simple stats)", r[at]) for r in envs.rows]
    sizes += [(f"{r[0]:,} terms", r[3]) for r in (terms.rows if terms else [])]
    where, worst = max(sizes, key=lambda s: s[1])
    t.add(
        f"isolated update <= {FLOOR_RATIO}x the floor at every size",
        f"{worst:.2f}x at {where} (the worst of {len(sizes)})",
        worst <= FLOOR_RATIO,
    )


def _groups(t: Table, gr: Table, tables: Sequence[Table], backend: str) -> None:
    col = {c: k for k, c in enumerate(gr.columns)}
    by_spec: dict[str, list[list]] = {}
    for r in gr.rows:
        by_spec.setdefault(r[col["spec"]] if "spec" in col else "full", []).append(r)
    for spec, rows in by_spec.items():
        most = max(rows, key=lambda r: r[col["groups"]])
        ratio, groups = most[col["x no groups"]], most[col["groups"]]
        t.add(
            f"per-group statistics ({spec}), most groups <= {FLOOR_RATIO}x no groups (GPU)",
            f"{ratio:.2f}x at {groups} groups",
            ratio <= FLOOR_RATIO if backend != "cpu" else None,
        )


def _end_to_end(t: Table, e2e: Table, tables: Sequence[Table], backend: str) -> None:
    pct = {r[0]: r[3] for r in e2e.rows}
    full = pct[_rollout.LABELS["jaxmetrics"]]
    floor = pct.get(_rollout.LABELS["floor"])
    if floor is not None:
        t.add(
            f"end-to-end overhead within {E2E_POINTS} pp of the floor's (every statistic)",
            f"{full:.2f}% vs {floor:.2f}%",
            full - floor <= E2E_POINTS,
        )
    empty = pct.get(_rollout.LABELS["empty"])
    if empty is not None:
        same = e2e.data["check"]["empty_lowers_to_bare"]
        t.add("empty spec indistinguishable from bare", f"{empty:.2f}%, same program: {same}", same)


def _live_read(t: Table, lr: Table, tables: Sequence[Table], backend: str) -> None:
    col = {c: k for k, c in enumerate(lr.columns)}
    rows = {r[0]: r for r in lr.rows}
    base, live = rows["live_base"], rows["live"]
    busy = col["device busy us/step"]
    if base[busy] is not None:
        step = base[col["ms/step"]] * 1e3
        d = (live[busy] - base[busy]) / step * 100
        said = f"{d:+.3f}% of the step"
        again = rows.get(_rollout.LIVE_AGAIN)
        if again is not None and again[busy] is not None:
            d0 = (again[busy] - base[busy]) / step * 100
            said += f" (a second load of the program without it: {d0:+.3f}%)"
        t.add(
            f"a live read every step adds within {LIVE_POINTS} pp of device time end to end",
            said,
            d <= LIVE_POINTS if backend != "cpu" else None,
        )
    said = _live.interval(lr.data)
    control = lr.data.get("control")
    if control is not None:
        said += f" vs {_live.interval(control)} for a second load of the program without it"
    t.add("a live read every step, wall clock end to end (95% interval)", said, None)


def _many_devices(t: Table, sh: Table, tables: Sequence[Table], backend: str) -> None:
    col = {c: k for k, c in enumerate(sh.columns)}
    # From ms/step, which every results file has (files older than the weak-scaling check
    # are judged by it too).
    bare = {r[0]: r[col["ms/step"]] for r in sh.rows if r[1] == _sharded.BARE}
    over = {r[0]: r[col["overhead %"]] for r in sh.rows if r[1] == _sharded.SPECS["full"]}
    one = over.get(1)
    for d, pct in over.items():
        if d == 1 or one is None:
            continue
        name = f"overhead on {d} devices within {DEVICES_POINTS} pp of 1 device's (full spec)"
        x = bare[d] / bare[1]
        if x > _sharded.WEAK_SCALING:
            # A bare rollout that does not weak-scale hides or adds cost of its own.
            t.add(
                name,
                f"invalid: bare rollout {x:.3f}x 1 device's (over {_sharded.WEAK_SCALING}x); "
                f"{pct:.2f}% vs {one:.2f}%",
                False,
            )
        else:
            t.add(name, f"{pct:.2f}% vs {one:.2f}% (bare {x:.3f}x)", pct - one <= DEVICES_POINTS)
    shown = (_sharded.BARE, *_sharded.SPECS.values())  # not an older file's unsharded state
    left = sum(r[col["collectives in step loop"]] for r in sh.rows if r[1] in shown)
    t.add("no collective in the step loop (sharded state)", f"{left} ops", left == 0)
    fl = _find(tables, "sharded_flush")
    if fl is not None:
        fc = {c: k for k, c in enumerate(fl.columns)}
        for r in fl.rows:
            if r[fc["devices"]] > 1:
                ms = r[fc["Logger.flush ms"]]
                t.add(
                    f"Logger.flush of a {r[fc['devices']]}-device sharded state under 1 ms",
                    f"{ms:.3f} ms",
                    ms < 1.0,
                )


def _distributed(t: Table, dist: Table, tables: Sequence[Table], backend: str) -> None:
    ratio = next(r[2] for r in dist.rows if r[0].startswith("jaxmetrics"))
    t.add(
        f"isolated update under jax.distributed <= {FLOOR_RATIO}x the floor",
        f"{ratio:.2f}x",
        ratio <= FLOOR_RATIO,
    )


def _flush(t: Table, fl: Table, tables: Sequence[Table], backend: str) -> None:
    col = {c: k for k, c in enumerate(fl.columns)}
    ms = [r[col["Logger.flush ms"]] for r in fl.rows]
    t.add("Logger.flush returns in under 1 ms", f"{max(ms):.3f} ms at most", max(ms) < 1.0)
    t.add("Logger.flush flat in num_envs", f"max/min over num_envs {max(ms) / min(ms):.2f}", None)
    sizes = sorted({r[col["bytes to host"]] for r in fl.rows})
    t.add("bytes to host flat in num_envs", f"{sizes}", len(sizes) == 1)


Judge = Callable[[Table, Table, Sequence[Table], str], None]

JUDGES: tuple[tuple[str, Judge], ...] = (
    ("isolated", _isolated),
    ("scaling_envs", _scaling),
    ("groups", _groups),
    ("end_to_end", _end_to_end),
    ("live_read", _live_read),
    ("sharded", _many_devices),
    ("distributed", _distributed),
    ("flush", _flush),
)
"""Per table that a target is judged on, the judge that adds its rows, in the order the
targets are listed."""


def targets(tables: Sequence[Table], backend: str) -> Table:
    """The project's targets, against what was measured in `tables` on `backend` (the
    per-group bound is a GPU's: on a CPU its row is left to the reader)."""
    t = Table("targets", "Targets", ["target", "measured", "met"])
    for name, judge in JUDGES:
        table = _find(tables, name)
        if table is not None and table.rows:
            judge(t, table, tables, backend)
    t.notes.append(NOTE)
    return t


def order(tables: Sequence[Table]) -> int:
    """Where the targets of `tables` come in the list (to list those of several runs)."""
    names = {t.name for t in tables}
    return next((i for i, (name, _) in enumerate(JUDGES) if name in names), len(JUDGES))
