"""The benchmark suite at a tiny size: its output structure, and that what it times reports
the right numbers. No timing assertions (speed claims live in docs/benchmarks.md).

References: numpy float64 unrolled from the same random inputs (isolated scenario), the
hand-written floor and the host loggers against jaxmetrics on the same rollout (end to
end, on the CPU where separately compiled rollouts are deterministic).
"""

import contextlib
import copy
import io
import json
import math
import os

import numpy as np
import pytest

import benchmarks
from benchmarks import _brax_results, _isolated, _profile, _render
from benchmarks._report import Table

NUM_ENVS, STEPS = 64, 50
ROLLOUT_STEPS = 30
ARGS = [
    "--quick",
    "--num-envs", str(NUM_ENVS),
    "--steps", str(STEPS),
    "--repeats", "1",
    "--step-kernels", "4",
    "--loaded-features", "sum,full",
    "--loaded-terms", "1",
    "--loaded-envs", "32",
    "--scale-envs", "16,32",
    "--scale-terms", "1,3",
    "--scale-windows", "4,16",
    "--scale-steps", "10",
    "--scale-repeats", "1",
    "--group-counts", "4",
    "--flush-envs", "16,64",
    "--flush-repeats", "2",
    "--period-envs", "16",
    "--period-ends", "3",
    "--period-every", "2",
    "--env", "inverted_pendulum",
    # Brax's cheapest backend to compile: the checks compare what the loggers and layouts
    # report on one rollout, whatever its physics.
    "--backend", "spring",
    "--e2e-envs", "4",
    "--e2e-steps", str(ROLLOUT_STEPS),
    "--e2e-repeats", "1",
    "--host-steps", str(ROLLOUT_STEPS),
    "--host-repeats", "1",
    "--e2e-variants", "empty,floor,callback_numpy",
    "--sharded-per-device", "4",
    "--sharded-steps", "10",
    "--sharded-repeats", "1",
    "--sharded-devices", "1,2",
    "--sharded-processes", "2",
    "--profile",
]  # fmt: skip
SCENARIOS = {
    "isolated",
    "kernels",
    "loaded",
    "scaling_envs",
    "scaling_terms",
    "scaling_window",
    "groups",
    "group_kernels",
    "flush",
    "period_ends",
    "end_to_end",
    "alternatives",
    "sharded",
    "sharded_flush",
    "distributed",
    "targets",
}


@pytest.fixture(scope="module")
def out_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("bench")


@pytest.fixture(scope="module")
def result(out_dir):
    path = out_dir / "out.json"
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        tables = benchmarks.main([*ARGS, "--json", str(path), "--out-dir", str(out_dir / "sets")])
    with open(path) as f:
        doc = json.load(f)
    return doc, tables, printed.getvalue()


@pytest.mark.slow
def test_json_has_environment_and_every_scenario(result):
    doc, tables, _ = result
    env = doc["environment"]
    for key in ("date", "machine", "device", "versions", "command"):
        assert env[key], key
    assert env["device"]["backend"] == "cpu"
    assert env["versions"]["jax"] and env["versions"]["jaxmetrics"]
    assert doc["config"]["preset"] == "quick"
    assert doc["config"]["num_envs"] == NUM_ENVS
    assert set(doc["scenarios"]) == SCENARIOS
    assert [t.name for t in tables] == list(doc["scenarios"])
    for name, s in doc["scenarios"].items():
        assert s["rows"], name
        for row in s["rows"]:
            assert len(row) == len(s["columns"]), name


@pytest.mark.slow
def test_tables_are_printed_as_markdown(result):
    doc, _, printed = result
    for s in doc["scenarios"].values():
        assert f"### {s['title']}" in printed
        assert "| " + " | ".join(s["columns"]) + " |" in printed


@pytest.mark.slow
def test_rows_cover_the_requested_sizes(result):
    doc, _, _ = result
    sc = doc["scenarios"]
    assert [r[0] for r in sc["scaling_envs"]["rows"]] == [16, 32]
    assert [r[0] for r in sc["scaling_terms"]["rows"]] == [1, 3]
    assert [r[0] for r in sc["scaling_window"]["rows"]] == [4, 16]
    assert [r[0] for r in sc["flush"]["rows"]] == [16, 64]
    # State grows with num_envs and window size; what a flush moves does not.
    at = sc["scaling_envs"]["columns"].index("state bytes")
    state = [r[at] for r in sc["scaling_envs"]["rows"]]
    assert state[1] > state[0]
    # The simple statistics timed beside the full spec, at every size.
    simple = sc["scaling_envs"]["columns"].index("simple x floor")
    assert all(r[simple] > 0 for r in sc["scaling_envs"]["rows"])
    layout = sc["scaling_envs"]["columns"].index("layout x floor")
    assert all(r[layout] > 0 for r in sc["scaling_envs"]["rows"])
    wstate = [r[3] for r in sc["scaling_window"]["rows"]]
    # two windowed rows; a slot holds a float32 value and its uint32 arrival step
    assert wstate[1] - wstate[0] == 2 * (16 - 4) * (4 + 4)
    assert len({r[2] for r in sc["flush"]["rows"]}) == 1
    assert [r[:2] for r in sc["groups"]["rows"]] == [
        ["full", 0],
        ["full", 4],
        ["period stats", 0],
        ["period stats", 4],
    ]
    assert sc["groups"]["data"]["check"] == {"groups": 4, "group_counts_sum_to_total": True}
    gstate = [r[6] for r in sc["groups"]["rows"]]  # 1 + g report rows per metric
    assert gstate[0] < gstate[1] and gstate[2] < gstate[3]
    assert [r[0] for r in sc["period_ends"]["rows"]] == ["reset only", "emit", "history"]
    e2e = [r[0] for r in sc["end_to_end"]["rows"]]
    assert len(e2e) == 4 and e2e[0] == "bare rollout" and "empty spec" in e2e[1]
    alt = [r[0] for r in sc["alternatives"]["rows"]]
    assert len(alt) == 3 and "debug.callback" in alt[2]


def _episode_sums_f64(xs: np.ndarray, dones: np.ndarray, row: int) -> tuple[float, int]:
    """Sum over finished episodes of each episode's sum of row `row`, unrolled in float64."""
    running = np.zeros(xs.shape[2])
    total, episodes = 0.0, 0
    for t in range(xs.shape[0]):
        running += xs[t, row].astype(np.float64)
        for e in np.flatnonzero(dones[t]):
            total += running[e]
            running[e] = 0.0
            episodes += 1
    return total, episodes


@pytest.mark.slow
def test_isolated_floor_and_jaxmetrics_match_a_float64_reference(result):
    doc, _, _ = result
    check = doc["scenarios"]["isolated"]["data"]["check"]
    xs, dones = (np.asarray(a) for a in _isolated.inputs(NUM_ENVS, STEPS))
    want_episodes = int(dones.sum())
    assert want_episodes > 0
    assert check["episodes"] == want_episodes
    assert check["counts"] == [want_episodes] * 10 and check["counts_equal"]
    # Sum-reduced terms m0, m1 read rows 0, 1 of the inputs.
    assert set(check["jaxmetrics_sums"]) == {"m0", "m1"}
    for row, name in enumerate(("m0", "m1")):
        want, _ = _episode_sums_f64(xs, dones, row)
        np.testing.assert_allclose(check["jaxmetrics_sums"][name], want, rtol=1e-6)
        np.testing.assert_allclose(check["floor_totals"][name], want, rtol=1e-5)


def test_layout_floor_sums_the_finished_episodes_means():
    # The scaling table's layout floor does the work it stands for: per env a Welford
    # mean and M2 over the running episode's steps, and the finished episodes' means
    # summed per metric; against float64 numpy, step by step.
    import jax

    from benchmarks import _workload as wl

    xs, dones = (np.asarray(a, np.float64) for a in _isolated.inputs(NUM_ENVS, STEPS))
    state = wl.layout_floor_init(3, NUM_ENVS)
    update = jax.jit(wl.layout_floor_update)
    want = np.zeros(3)
    start = np.zeros(NUM_ENVS, int)
    checked = 0
    for t in range(STEPS):
        done = dones[t].astype(bool)
        state = update(state, xs[t, :3].astype(np.float32), done)
        for e in range(NUM_ENVS):
            seen = xs[start[e] : t + 1, :3, e]
            if done[e]:
                want += seen.mean(axis=0)
                start[e] = t + 1
            elif len(seen) > 1:
                got = np.asarray(state.m2)[:, e], np.asarray(state.mean)[:, e]
                np.testing.assert_allclose(got[0], ((seen - seen.mean(0)) ** 2).sum(0), rtol=1e-4)
                np.testing.assert_allclose(got[1], seen.mean(0), rtol=1e-5)
                checked += 1
    assert checked > 0 and int(state.episodes) == int(dones.sum()) > 0
    np.testing.assert_allclose(np.asarray(state.total), want, rtol=1e-5)
    # Past 4,096 envs it sums in parts (padded where they do not divide the envs).
    wide = np.random.default_rng(0).random((3, 5000)).astype(np.float32)
    np.testing.assert_allclose(wl._row_sums(wide), wide.sum(axis=1, dtype=np.float64), rtol=1e-6)


@pytest.mark.slow
def test_loaded_rows_time_each_variant_after_the_env_step(result):
    doc, _, _ = result
    t = doc["scenarios"]["loaded"]
    col = {c: i for i, c in enumerate(t["columns"])}
    sizes = [(r[col["envs"]], r[col["terms"]]) for r in t["rows"]]
    assert sizes == [(NUM_ENVS, 10), (NUM_ENVS, 10), (NUM_ENVS, 1), (32, 10)]
    for r in t["rows"]:
        step, floor, ours = (r[col[c]] for c in ("step", "step + floor", "step + ours"))
        assert r[col["floor overhead"]] == pytest.approx(floor - step)
        assert r[col["our overhead"]] == pytest.approx(ours - step)
        assert r[col["% of step"]] == pytest.approx(100 * (ours - step) / step)
    # The env step's values feed the update: the same episodes as the random dones.
    _, dones = _isolated.inputs(NUM_ENVS, STEPS)
    check = t["data"]["check"]
    assert check["episodes"] == int(np.asarray(dones).sum()) > 0
    assert check["counts_equal"] and check["max_rel_diff_sum"] < 1e-5
    assert t["data"]["step_kernels"] == 4


def test_env_step_values_are_in_the_unit_interval_and_follow_the_action():
    import jax.numpy as jnp

    from benchmarks import _loaded

    x = _loaded.env_init(8)
    action = jnp.linspace(0.0, 1.0, 80, dtype=jnp.float32).reshape(10, 8)
    a = np.asarray(_loaded.env_step(x, action, 3))
    b = np.asarray(_loaded.env_step(x, action * 0.5, 3))
    assert a.shape == (_loaded.FEATURES, 8) and a.dtype == np.float32
    assert (a >= 0).all() and (a <= 1).all()
    # One unfused kernel by hand, float64: 0.5 + 0.5 sin(3 x + i) from the action's rows.
    x64 = np.full((_loaded.FEATURES, 8), 0.5)
    x64[:10] += np.asarray(action, np.float64)
    for i in range(3):
        x64 = 0.5 + 0.5 * np.sin(3.0 * x64 + i)
    np.testing.assert_allclose(a, x64, rtol=1e-5, atol=1e-6)
    assert not np.allclose(a[:10], b[:10])


@pytest.mark.slow
def test_kernel_profile_names_the_ops_of_each_variant(result):
    doc, _, _ = result
    k = doc["scenarios"]["kernels"]
    col = {c: i for i, c in enumerate(k["columns"])}
    rows = k["rows"]
    assert {r[col["variant"]] for r in rows} == {"floor", "simple", "full"}
    for r in rows:
        # Each profiled event is an op of the compiled program, found in its HLO.
        assert r[col["shape"]] and r[col["fuses"]], r
        assert r[col["us/step"]] > 0 and r[col["launches/step"]] > 0, r
    # The full spec runs more kernels than the floor, and takes longer in them.
    count = {v: sum(r[col["variant"]] == v for r in rows) for v in ("floor", "full")}
    assert count["full"] > count["floor"]
    totals = k["data"]["total_us_per_step"]
    assert totals["full"] > totals["floor"] > 0
    # Some kernel ran for part of each step: at most the kernels' sum (overlaps count once).
    busy = k["data"]["busy_us_per_step"]
    assert all(0 < busy[v] <= totals[v] * (1 + 1e-9) for v in totals), (busy, totals)
    assert set(k["data"]["wall_us_per_step"]) == set(totals)


@pytest.mark.parametrize("seed", range(20))
def test_profile_busy_time_counts_overlapping_kernels_once(seed):
    rng = np.random.default_rng(seed)
    starts = rng.integers(0, 60, size=rng.integers(0, 9))
    intervals = [(int(a), int(a + rng.integers(0, 25))) for a in starts]
    # Reference: the nanoseconds covered by some interval, one by one.
    covered = {t for a, b in intervals for t in range(a, b)}
    assert _profile._union_ns(intervals) == len(covered)


@pytest.mark.slow
def test_rollout_loggers_report_the_same_episodes(result):
    doc, _, _ = result
    check = doc["scenarios"]["end_to_end"]["data"]["check"]
    alt = doc["scenarios"]["alternatives"]
    assert check["episodes"] > 0 and check["counts_equal"]
    assert check["empty_lowers_to_bare"] is True
    assert check["max_rel_diff_sum"] < 1e-5
    # Same rollout length for every logger: each saw the same episodes.
    assert {r[5] for r in alt["rows"]} == {check["episodes"]}
    numpy_totals = alt["data"]["host_numpy_totals"]
    for i, name in enumerate(("reward", "abs_reward")):
        np.testing.assert_allclose(numpy_totals[i], check["floor_totals"][name], rtol=1e-5)
        np.testing.assert_allclose(numpy_totals[i], check["jaxmetrics_sums"][name], rtol=1e-5)


@pytest.mark.slow
def test_targets_table_judges_what_ran(result):
    doc, _, _ = result
    rows = {r[0]: r for r in doc["scenarios"]["targets"]["rows"]}
    assert "isolated update <= 1.5x the floor" in rows
    assert "isolated update <= 1.5x the floor at every size" in rows
    assert "end-to-end overhead within 0.3 pp of the floor's (every statistic)" in rows
    assert rows["empty spec indistinguishable from bare"][2] is True
    assert rows["bytes to host flat in num_envs"][2] is True
    # The GPU's per-group bound is not judged on a CPU; the callback logger is no target.
    for spec in ("full", "period stats"):
        assert (
            rows[f"per-group statistics ({spec}), most groups <= 1.5x no groups (GPU)"][2] is None
        )
    assert not any("100x" in target for target in rows)


@pytest.mark.slow
def test_each_scenario_is_written_to_its_own_file_which_renders(result, out_dir):
    doc, tables, _ = result
    made = {t.scenario for t in tables if t.scenario}
    assert sorted(os.listdir(out_dir / "sets")) == sorted(f"cpu_{s}.json" for s in made)
    docs = _render.load(str(out_dir / "sets"))
    for name, d in docs.items():
        scenario = name.removeprefix("cpu_").removesuffix(".json")
        assert list(d["scenarios"]) == [t.name for t in tables if t.scenario == scenario]
        assert d["environment"] == doc["environment"]
    rendered = _render.render(
        "".join(f"<!-- bench: {n} -->\n<!-- /bench -->\n" for n in docs), docs
    )
    for t in tables[:-1]:  # every table but the targets, the profiles left in the files
        assert (f"#### {t.title}\n" in rendered) == (t.name not in _render.PROFILES), t.name
    # The document judges its targets on accelerators only.
    assert "cpu_" not in _render.targets_markdown(docs)


@pytest.mark.parametrize("flag", ["--scenarios", "--e2e-variants"])
def test_unknown_names_are_refused(capsys, flag):
    with pytest.raises(SystemExit):
        benchmarks.main([flag, "floor,nope"])
    assert f"unknown {flag[2:]} " in capsys.readouterr().err


@pytest.mark.slow
def test_sharded_rows_count_the_collectives_and_check_weak_scaling(result):
    doc, _, _ = result
    sc = doc["scenarios"]
    cols = {c: k for k, c in enumerate(sc["sharded"]["columns"])}
    rows = {(r[0], r[1]): r for r in sc["sharded"]["rows"]}
    full = "jaxmetrics, 10 terms, every statistic"
    assert {d for d, _ in rows} == {1, 2}
    for (d, label), r in rows.items():
        assert r[cols["collectives in step loop"]] == 0, (d, label)  # shard-local steps
        if label == "bare rollout":
            # each device count's bare rollout against one device's, from the same table
            ratio = r[cols["ms/step"]] / rows[(1, label)][cols["ms/step"]]
            assert r[cols["x 1-device bare"]] == pytest.approx(ratio)
    assert rows[(2, full)][cols["overhead %"]] is not None
    flush = {r[0]: r for r in sc["sharded_flush"]["rows"]}
    # what a flush copies does not grow with the devices (or the envs)
    assert len({r[2] for r in flush.values()}) == 1
    # one device's compute moves nothing; two devices' shards meet in one collective
    assert [flush[d][3] for d in (1, 2)] == [0, 1]
    # the targets judge the weak-scaling check: a 2-device row says what it is
    judged = {r[0]: r for r in sc["targets"]["rows"]}
    row = judged["overhead on 2 devices within 0.5 pp of 1 device's (full spec)"]
    invalid = rows[(2, "bare rollout")][cols["x 1-device bare"]] > 1.02
    assert row[1].startswith("invalid") == invalid
    if invalid:
        assert row[2] is False
    dist = {r[0]: r for r in sc["distributed"]["rows"]}
    assert dist["jaxmetrics, full 10-term spec"][3] == 0  # no collective per step
    assert 0 < dist["jaxmetrics, full 10-term spec"][4] < 4096  # O(metrics) bytes


def test_period_end_table_times_emit_and_history_on_the_same_records():
    from benchmarks import _flush_cost

    t = _flush_cost.period_ends(num_envs=8, periods=3, every=2, repeats=1)
    rows = {r[0]: r for r in t.rows}
    assert sorted(rows) == ["emit", "history", "reset only"]
    # emit and history each wrote 3 records per call, warm-up round included.
    assert t.data["records_written"] == 2 * 2 * 3
    # A record: F floats, 2K count words, 2 step words, 4 bytes each.
    assert rows["history"][5] % 4 == 0 and rows["history"][5] > 0
    assert rows["reset only"][3] is None and rows["history"][3] is not None


def test_timed_rounds_rotate_so_no_variant_always_runs_first():
    from benchmarks._timing import Variant, measure

    calls = []
    variants = [Variant(n, lambda n=n: calls.append(n) or n) for n in "abc"]
    timings, last = measure(variants, repeats=6, warmup=1)
    rounds = [calls[3 + 3 * r : 6 + 3 * r] for r in range(6)]
    assert calls[:3] == ["a", "b", "c"]  # the warm-up
    assert all(sorted(r) == ["a", "b", "c"] for r in rounds)
    # Every variant takes every place of a round equally often.
    for place in range(3):
        assert sorted(r[place] for r in rounds) == ["a", "a", "b", "b", "c", "c"]
    assert {t.repeats for t in timings.values()} == {6} and last == {n: n for n in "abc"}


def test_paired_rounds_time_no_call_that_follows_the_other_program():
    from benchmarks._live import paired_rounds
    from benchmarks._timing import Variant

    calls = []

    def run(name):
        def f():
            calls.append(name)

        return f

    pair = [Variant("a", run("a")), Variant("b", run("b"))]
    samples, switch = paired_rounds(pair, rounds=4)
    assert calls[:2] == ["b", "a"]  # the warm-up, ending with the first round's first
    # Rounds a b, b a, a b, b a: the second program of each follows the other one.
    assert calls[2:] == ["a", "b", "b", "b", "a", "a", "a", "b", "b", "b", "a", "a"]
    assert {k: len(v) for k, v in samples.items()} == {"a": 4, "b": 4} and len(switch) == 4


@pytest.mark.parametrize("n", [3, 5, 10, 20, 21, 40])
def test_median_interval_is_the_widest_order_statistics_with_95_percent_coverage(n):
    from benchmarks._live import median_interval

    # Reference: the coverage of (x_(k), x_(n+1-k)) for the median of any continuous
    # distribution is 1 - 2 P(Binomial(n, 1/2) < k); the narrowest k-interval still at 95%.
    def coverage(k):
        return 1 - 2 * sum(math.comb(n, j) for j in range(k)) / 2**n

    ks = [k for k in range(1, n // 2 + 1) if coverage(k) >= 0.95]
    k = max(ks) if ks else 1
    xs = list(np.random.default_rng(n).permutation(np.arange(n, dtype=float)))
    assert median_interval(xs) == (k - 1, n - k)  # x_(j) of 0..n-1 is j - 1


@pytest.mark.parametrize("seed", range(5))
def test_live_read_s_estimates_cancel_the_order_the_pair_ran_in(seed):
    from benchmarks._live import summarize

    # Rounds alternate which program runs first; the one second runs `slow` % slower.
    rng = np.random.default_rng(seed)
    cost, slow, rounds = rng.uniform(-0.2, 0.2), rng.uniform(0.1, 0.6), 2 * rng.integers(3, 12)
    noise = rng.normal(0, 0.01, rounds)
    pcts = [cost + (slow if r % 2 == 0 else -slow) + noise[r] for r in range(rounds)]
    s = summarize(pcts)
    pairs = [(pcts[2 * j] + pcts[2 * j + 1]) / 2 for j in range(rounds // 2)]
    assert s["pair_pct"] == pytest.approx(pairs)
    assert s["median_pct"] == pytest.approx(np.median(pairs))
    assert abs(s["median_pct"] - cost) < 0.03 and abs(s["order_pct"] - slow) < 0.03
    lo, hi = s["ci_pct"]
    assert lo <= s["median_pct"] <= hi and {lo, hi} <= set(pairs)
    with pytest.raises(ValueError, match="--e2e-live-rounds 2 or more"):
        summarize(pcts[:1])


def test_live_read_pairs_the_rounds_and_counts_what_the_read_adds():
    import jax
    import jax.numpy as jnp

    from benchmarks import _live
    from benchmarks._timing import Variant, blocking, compile_jit

    steps, x = 20, jnp.ones((64,), jnp.float32)

    def scan(extra):
        def body(c, t):
            c = c * 0.5 + t
            return (jnp.sort(jnp.cumsum(c)) if extra else c), None

        return lambda c: jax.lax.scan(body, c, jnp.arange(steps, dtype=jnp.float32))[0]

    trio, hlo = [], {}
    for name, extra in (("live_base", False), ("again", False), ("live", True)):
        compiled, _ = compile_jit(scan(extra), x)
        trio.append(Variant(name, blocking(compiled, x)))
        hlo[name] = compiled.as_text()
    t = _live.live_read(trio, hlo, steps, rounds=6)
    for s in (t.data, t.data["control"]):  # the read's estimates, the second load's
        assert len(s["paired_pct"]) == 6 and len(s["pair_pct"]) == 3
        lo, hi = s["ci_pct"]
        assert lo <= s["median_pct"] <= hi
        # Rounds a b, b a, a b, ...: a call after the other program's is run untimed
        # first, once a round.
        assert len(s["switch_pct"]) == 6
    (base, again, read) = t.rows
    assert [base[0], again[0], read[0]] == ["live_base", "again", "live"]
    assert read[2] > base[2] == again[2]  # the sort's kernels; the same program twice
    assert set(t.data["busy_us_per_step"]) == {"live_base", "again", "live"}
    # what the read adds, by kind of kernel: the sort it added is among them
    assert any("sort" in kind for kind, _, n in t.data["added_kernels"] if n > 0)
    judged = benchmarks._targets.targets([t], "cpu")
    assert [r[2] for r in judged.rows] == [None, None]  # a CPU run is left to the reader
    assert "second load" in judged.rows[1][1]


@pytest.mark.parametrize("busy_us, met", [(2.0, True), (3.5, False)])
def test_the_live_read_is_judged_on_the_device_time_it_adds(busy_us, met):
    # 0.1 pp of a 3 ms step is 3 us of device time; the wall clock is shown, not judged.
    t = Table("live_read", "", ["variant", "ms/step", "device busy us/step"])
    t.add("live_base", 3.0, 2900.0)
    t.add("live", 3.0, 2900.0 + busy_us)
    t.data = {"median_pct": 0.5, "ci_pct": [0.4, 0.6]}
    rows = benchmarks._targets.targets([t], "gpu").rows
    assert rows[0][2] is met and rows[0][1] == f"{busy_us / 3e3 * 100:+.3f}% of the step"
    assert rows[1][2] is None and rows[1][1] == "+0.500% [+0.400, +0.600]"


DOC = os.path.join(os.path.dirname(__file__), os.pardir, os.pardir, "docs", "benchmarks.md")


def _committed() -> tuple[str, dict]:
    with open(DOC) as f:
        return f.read(), _render.load(_render.results_dir(DOC))


def test_committed_tables_are_what_the_committed_results_files_render_to():
    text, docs = _committed()
    # On failure: `python -m benchmarks --render` rewrites the tables from the files.
    assert _render.render(text, docs) == text


def test_the_results_page_stays_a_page_of_summaries():
    # Issue 46: targets, how to run, one block per scenario; history stays in git.
    text, docs = _committed()
    assert text.count("\n") <= 500 and len(docs) <= 10
    assert all("runs" not in doc for doc in docs.values())  # no per-run dumps
    assert "/root/" not in text and "python -m jaxmetrics.bench" not in text


def test_every_committed_results_file_renders_each_of_its_tables():
    text, docs = _committed()
    assert docs
    for name, doc in docs.items():
        block = text.split(f"<!-- bench: {name} -->\n")[1].split("<!-- /bench -->")[0]
        assert block.startswith(f"`{name}`: "), name  # where and how it was measured
        its = _render.tables(doc)
        assert its, name
        for t in its:
            assert t.rows, (name, t.name)
            assert f"#### {t.title}\n" in block, (name, t.name)


def test_render_keeps_the_prose_and_refuses_what_it_cannot_place():
    _, docs = _committed()
    one = {"h200_groups.json": docs["h200_groups.json"]}
    text = "Before.\n<!-- bench: h200_groups.json -->\nstale\n<!-- /bench -->\nAfter.\n"
    out = _render.render(text, one)
    assert out.startswith(
        "Before.\n<!-- bench: h200_groups.json -->\n`h200_groups.json`: NVIDIA H200, "
    )
    assert out.endswith("<!-- /bench -->\nAfter.\n") and "stale" not in out
    assert _render.render(out, one) == out
    with pytest.raises(ValueError, match=r"no block shows \['h200_groups.json'\]"):
        _render.render("Prose only.\n", one)
    with pytest.raises(ValueError, match="'<!-- bench: gone.json -->' names no results file"):
        _render.render("<!-- bench: gone.json -->\n<!-- /bench -->\n", one)


def test_render_is_the_cli_s_render_step(tmp_path):
    text, docs = _committed()
    (tmp_path / "benchmarks").mkdir()
    for name in ("h100_flush.json", "h200_groups.json"):
        with open(tmp_path / "benchmarks" / name, "w") as f:
            json.dump(docs[name], f)
    stale = "<!-- bench: targets -->\n<!-- /bench -->\n" + "".join(
        f"<!-- bench: {n} -->\nSTALE\n<!-- /bench -->\n"
        for n in ("h100_flush.json", "h200_groups.json")
    )
    (tmp_path / "benchmarks.md").write_text(stale)
    assert benchmarks.main(["--render", str(tmp_path / "benchmarks.md")]) == []
    out = (tmp_path / "benchmarks.md").read_text()
    groups = docs["h200_groups.json"]["scenarios"]["groups"]
    col = groups["columns"].index("x no groups")
    full = max((r for r in groups["rows"] if r[0] == "full"), key=lambda r: r[1])
    assert "STALE" not in out  # the GPU file's target row, from its table:
    assert f"{full[col]:.2f}x at {full[1]} groups" in out
    assert out == _render.render(stale, _render.load(str(tmp_path / "benchmarks")))


def _ppo_run(call, variant, t_s, training_sps, reports=0):
    """A `_brax_train` run: 300 steps in three intervals, the first compiling."""
    from benchmarks._brax_train import _steady

    progress = [
        {"step": step, "t_s": t, "training_sps": sps, "eval_episode_reward": None}
        for step, t, sps in zip((0, 100, 200, 300), t_s, training_sps)
    ]
    run = {"variant": variant, "run": 1, "call": call, "progress": progress}
    run.update(_steady(progress, [(5.0, 1.0)]))  # a compile ends in the first interval
    run["settings"] = {"num_envs": 8, "num_timesteps": 300}
    if reports:
        run["records"] = reports
        run["arrivals"] = [{"step": 101 + i % 200} for i in range(reports)]
    return run


def test_ppo_train_runs_are_compared_within_their_call_and_costed_per_report():
    brax = _ppo_run("c", "brax", (0, 10, 11, 12), (None, 50, 100, 100))
    # 1 s more than Brax's 2 s over the kept intervals; epochs at 80 instead of 100 sps
    slow = _ppo_run("c", "report_full", (0, 10, 11.5, 13), (None, 50, 80, 80), reports=100)
    alone = _ppo_run("d", "report_full", (0, 10, 11.5, 13), (None, 50, 80, 80), reports=100)
    doc = {"calls": {k: {"commit": "abc1234", "commands": ["cmd"], "notes": []} for k in "cd"}}
    doc["runs"] = [brax, slow, alone]
    c, d = _brax_results.call_tables(doc)
    assert c.rows[0][:7] == ["brax", 1, None, 100, 100, 0.0, 0.0]
    variant, _, records, steady, training, *over = c.rows[1]
    assert (variant, records, steady, training) == ("report_full", 100, 67, 80)
    # % more time per step; ms per report: 1 s / 100, and 2 x 100 steps x (1/80 - 1/100) / 100
    np.testing.assert_allclose(over, [50.0, 25.0, 10.0, 5.0])
    assert d.rows[0][5:] == [None] * 4  # no Brax run in its call: nothing to compare with
    fewer = _ppo_run("c", "report_full", (0, 10, 11.5, 13), (None, 50, 80, 80), reports=99)
    assert _brax_results.report_cost(fewer, {"steady": 100, "training": 100}) == (None, None)
    summary = _brax_results.summarize(doc["runs"])
    assert summary["c"]["report_full"]["overhead_steady_pct"] == pytest.approx(50.0)
    assert summary["d"]["report_full"]["overhead_steady_pct"] is None


def test_ppo_train_outputs_merge_by_call():
    from benchmarks import _brax_train

    def output(call, commit, command, variant):
        run = _ppo_run(call, variant, (0, 10, 11, 12), (None, 50, 100, 100))
        meta = {"commit": commit, "commands": [command], "notes": []}
        return {"benchmark": "brax_ppo_train", "calls": {call: meta}, "runs": [run]}

    a, b = output("c", "t1", "cmd a", "brax"), output("c", "t1", "cmd b", "fold_full")
    merged = _brax_train.merge([a, b, output("d", "t2", "cmd c", "brax")])
    assert merged["calls"]["c"]["commands"] == ["cmd a", "cmd b"]
    assert [r["variant"] for r in merged["runs"]] == ["brax", "fold_full", "brax"]
    assert set(merged["summary"]) == {"c", "d"}
    with pytest.raises(ValueError, match="give each tree its own --call"):
        _brax_train.merge(
            [a, copy.deepcopy(b) | {"calls": {"c": b["calls"]["c"] | {"commit": "t3"}}}]
        )


def test_ppo_train_variant_names():
    from benchmarks._brax_train import OFTEN_REPORT_EVERY, RARE_REPORT_EVERY, parse_variant

    assert parse_variant("brax") == ("brax", None, None, "tensorboard")
    assert parse_variant("report_full_often") == (
        "report",
        "full",
        OFTEN_REPORT_EVERY,
        "tensorboard",
    )
    assert parse_variant("fold_mean_rare") == ("fold", "mean", RARE_REPORT_EVERY, "tensorboard")
    assert parse_variant("report_full_mem") == ("report", "full", None, "memory")
    with pytest.raises(ValueError, match="unknown variant 'report_full_sometimes'"):
        parse_variant("report_full_sometimes")


def test_ppo_train_summary_keeps_each_call_s_means_and_not_its_runs():
    brax = _ppo_run("c", "brax", (0, 10, 11, 12), (None, 50, 100, 100))
    often = _ppo_run("c", "report_full", (0, 10, 11.5, 13), (None, 50, 80, 80), reports=100)
    meta = {"commit": "abc1234", "commands": ["cmd"], "notes": []}
    env = {"device": "cpu", "device_count": 1, "jax": "0", "host": "machine"}
    doc = {"environment": env, "calls": {"c": meta}, "runs": [brax, often]}
    doc["summary"] = _brax_results.summarize(doc["runs"])
    summary = _brax_results.summary_doc(doc)
    assert "runs" not in summary and "host" not in summary["environment"]
    assert summary["calls"]["c"] | meta == summary["calls"]["c"]
    assert (summary["calls"]["c"]["num_envs"], summary["calls"]["c"]["num_timesteps"]) == (8, 300)
    # The summary renders the output's table, the cost per report included.
    table = _brax_results.summary_table(summary)
    assert table.rows == _brax_results.summary_table(doc).rows
    assert table.rows[1][:6] == ["c", "abc1234", "8, 0.0003M", "report_full", 1, 100]
    np.testing.assert_allclose(table.rows[1][8:], [50.0, 25.0, 10.0, 5.0])
    assert _render.tables(summary | {"benchmark": "brax_ppo_train"})[0].rows == table.rows


def test_brax_trainers_get_the_name_docs_brax_md_restores(monkeypatch):
    import jax
    import jax._src.api

    from benchmarks._brax_train import restore_device_put_replicated

    monkeypatch.setattr(jax, "device_put_replicated", None, raising=False)
    monkeypatch.delattr(jax, "device_put_replicated")
    restore_device_put_replicated()
    assert jax.device_put_replicated is jax._src.api.device_put_replicated
    theirs = object()  # a JAX that has the name keeps its own
    monkeypatch.setattr(jax, "device_put_replicated", theirs)
    restore_device_put_replicated()
    assert jax.device_put_replicated is theirs


def test_one_command_line_runs_the_trainer_benchmarks_too(tmp_path, capsys):
    with pytest.raises(SystemExit):
        benchmarks.main(["--help"])
    usage = capsys.readouterr().out
    assert usage.startswith("usage: python -m benchmarks")
    for name in ("brax-train", "playground-train", "in-trainer", "channel"):
        assert f"\n  {name} " in usage
    with pytest.raises(SystemExit):
        benchmarks.main(["brax-train", "--help"])
    assert capsys.readouterr().out.startswith("usage: python -m benchmarks brax-train")
    # A command runs its own main with the rest of the line: an empty in-trainer summary.
    out = tmp_path / "in_trainer.json"
    assert benchmarks.main(["in-trainer", "--commit", "abc", "--out", str(out)]) == []
    with open(out) as f:
        assert json.load(f) == {
            "benchmark": "in_trainer",
            "cases": [],
            "device": None,
            "jax": None,
            "commit": "abc",
        }


def test_the_benchmarks_examples_run():
    # pytest collects the package's doctests only (testpaths); the benchmarks' run here.
    import doctest
    import importlib
    import pkgutil

    names = [m.name for m in pkgutil.iter_modules(benchmarks.__path__) if m.name != "__main__"]
    assert "_report" in names and "_cond_sync" not in names
    tried = 0
    for name in names:
        result = doctest.testmod(importlib.import_module(f"benchmarks.{name}"))
        assert result.failed == 0, name
        tried += result.attempted
    assert tried > 0
