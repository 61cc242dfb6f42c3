"""The notebooks run top to bottom and show what their text says.

Each notebook is executed by nbclient in a fresh `python3` kernel (a separate process: the
strict JAX settings of conftest do not reach it), with this checkout on its PYTHONPATH and
the suite's persistent compilation cache. Committed notebooks carry no outputs, so they can
never be stale: the outputs checked here are always fresh. After the notebook's own cells
the test appends one probe cell that prints, as JSON, values the checks need from the
kernel; everything visible (printed lines, tables, figures) is read from the outputs.
"""

import json
import math
import os
import re
import shutil
from pathlib import Path
from typing import Any, NamedTuple

import nbformat
import numpy as np
import pytest
from nbclient import NotebookClient
from nbformat.v4 import new_code_cell
from tensorboard.backend.event_processing import event_accumulator

ROOT = Path(__file__).resolve().parents[2]
NOTEBOOKS = ROOT / "notebooks"
NAMES = ("custom_terms", "quickstart", "training")
SKIP_TAG = "skip-execution"  # cells the tests leave out (the TensorBoard launch)
PROBE_MARK = "PROBE:"
CELL_TIMEOUT_S = 600  # per cell; a cold MJX compile on a busy 2-core CPU takes ~30 s


class Executed(NamedTuple):
    nb: Any  # the executed notebook (outputs filled in)
    skipped: list[Any]  # cells tagged SKIP_TAG, left out
    probe: dict[str, Any]  # what the probe cell printed


def read(name: str) -> Any:
    return nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)


def cell(nb: Any, cell_id: str) -> Any:
    (found,) = [c for c in nb.cells if c.get("id") == cell_id]
    return found


def stream(c: Any, name: str = "stdout") -> str:
    return "".join(o.text for o in c.outputs if o.output_type == "stream" and o.name == name)


def images(c: Any) -> int:
    return sum(1 for o in c.outputs if "image/png" in o.get("data", {}))


def execute(name: str, workdir: Path, probe: str) -> Executed:
    nb = read(name)
    skipped = [c for c in nb.cells if SKIP_TAG in c.metadata.get("tags", [])]
    nb.cells = [c for c in nb.cells if SKIP_TAG not in c.metadata.get("tags", [])]
    nb.cells.append(new_code_cell(f"import json\nprint({PROBE_MARK!r} + json.dumps({probe}))"))
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), env.get("PYTHONPATH")) if p)
    # The inline backend renders figures to PNG without a display (what notebook users
    # get), so that every plot is drawn and its image can be checked.
    env["MPLBACKEND"] = "module://matplotlib_inline.backend_inline"
    # Same persistent compilation cache as conftest: reruns skip the MJX compiles.
    env["JAX_COMPILATION_CACHE_DIR"] = os.environ.get(
        "JAXMETRICS_TEST_CACHE", str(ROOT / ".jax_cache")
    )
    env["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"] = "1.0"
    client = NotebookClient(
        nb,
        timeout=CELL_TIMEOUT_S,
        kernel_name="python3",
        resources={"metadata": {"path": str(workdir)}},
    )
    client.execute(env=env)  # raises CellExecutionError on the first failing cell
    out = stream(nb.cells[-1])
    assert out.startswith(PROBE_MARK), out
    return Executed(nb, skipped, json.loads(out[len(PROBE_MARK) :]))


@pytest.fixture(scope="module")
def quickstart(tmp_path_factory):
    return execute(
        "quickstart",
        tmp_path_factory.mktemp("quickstart"),
        """{
            "stat_table": stat_table.to_dict(),
            "reduction_table": reduction_table.to_dict(),
            "tags": sorted(set(df.tag)),
            "steps": wide.index.tolist(),
            "counts": wide["Episode_Metrics/return/count"].tolist(),
            "episodes": wide["Counters/episodes"].tolist(),
            "env_steps": wide["Counters/env_steps"].tolist(),
            "window": window.tolist(),
            "pcts": {str(p): v for p, v in pcts.items()},
            "num_envs": NUM_ENVS, "chunk": CHUNK, "chunks": CHUNKS,
        }""",
    )


@pytest.fixture(scope="module")
def training(tmp_path_factory):
    executed = execute(
        "training",
        tmp_path_factory.mktemp("training"),
        """{
            "log_dir": log_dir,
            "spi": config.steps_per_iteration,
            "iterations": config.num_iterations,
            "learner": list(ppo.LEARNER_METRICS),
            "memory_return": memory.dataframe().query(
                "tag == 'Episode_Metrics/episode_return/window_mean'"
            ).set_index("step").value.to_dict(),
        }""",
    )
    yield executed
    # The notebook writes its run to a fresh temporary directory (for users to open in
    # TensorBoard); the test's copy is not needed once read.
    shutil.rmtree(executed.probe["log_dir"])


@pytest.fixture(scope="module")
def custom_terms(tmp_path_factory):
    return execute(
        "custom_terms",
        tmp_path_factory.mktemp("custom_terms"),
        """{
            "report": {k: v for k, v in report.items() if not hasattr(v, "shape")},
            "nan_report": {k: v for k, v in nan_report.items() if not hasattr(v, "shape")},
            "check": check.to_dict(),
            "dq_check": dq_check.to_dict(),
            "group_check": group_check.to_dict(),
        }""",
    )


# --------------------------------------------------------------------- committed files


def test_committed_notebooks_carry_no_outputs_and_state_their_run_time():
    assert sorted(p.stem for p in NOTEBOOKS.glob("*.ipynb")) == list(NAMES)
    for name in NAMES:
        nb = read(name)
        nbformat.validate(nb)
        assert nb.metadata.kernelspec.name == "python3", name
        for c in nb.cells:
            if c.cell_type == "code":
                assert c.outputs == [] and c.execution_count is None, (name, c.id)
        first = nb.cells[0]
        assert first.cell_type == "markdown", name
        assert re.search(
            r"\*\*Run time:\*\* about \d+ s on this machine \(2-core CPU", first.source
        ), name


def test_only_the_tensorboard_launch_is_left_out():
    for name in NAMES:
        tagged = [c for c in read(name).cells if SKIP_TAG in c.metadata.get("tags", [])]
        if name == "training":
            assert len(tagged) == 1 and "%tensorboard --logdir" in tagged[0].source
        else:
            assert tagged == [], name


# --------------------------------------------------------------------- quickstart


def assert_no_upstream_noise(executed: Executed) -> None:
    # `jmb.quiet_upstream()` around the imports and env builds keeps MuJoCo's warp lines
    # and Brax's maintenance warning out of every cell.
    for c in executed.nb.cells:
        if c.cell_type == "code":
            shown = stream(c) + stream(c, "stderr")
            assert "Failed to import" not in shown, c.get("id")
            assert "not actively being maintained" not in shown, c.get("id")


# One test per notebook, each naming its fixture: the tests of a notebook share its run
# on one xdist worker (tests/conftest.py groups them by the fixture).
@pytest.mark.slow
def test_custom_terms_shows_no_upstream_noise(custom_terms):
    assert_no_upstream_noise(custom_terms)


@pytest.mark.slow
def test_quickstart_shows_no_upstream_noise(quickstart):
    assert_no_upstream_noise(quickstart)


@pytest.mark.slow
def test_training_shows_no_upstream_noise(training):
    assert_no_upstream_noise(training)


@pytest.mark.slow
def test_quickstart_contrasts_per_episode_mean_with_mean_of_batch_means(quickstart):
    out = stream(cell(quickstart.nb, "mean-vs-batch-means"))
    assert re.search(r"^finished episodes: 4$", out, re.M), out
    assert re.search(r"^success rate, each episode weighs 1: 0\.25$", out, re.M), out
    assert re.search(r"^per-step batch means: \[0\.0, 1\.0\]$", out, re.M), out
    assert re.search(r"^mean of per-step batch means: 0\.5$", out, re.M), out


@pytest.mark.slow
def test_quickstart_statistics_tables_agree_with_numpy(quickstart):
    for table in ("stat_table", "reduction_table"):
        t = quickstart.probe[table]
        assert t["jaxmetrics"].keys() == t["numpy"].keys()
        for stat, want in t["numpy"].items():
            assert t["jaxmetrics"][stat] == pytest.approx(want, rel=1e-6), (table, stat)
    stat_rows = set(quickstart.probe["stat_table"]["numpy"])
    assert {"mean", "std", "count", "ema(0.5)", "window_p90"} <= stat_rows
    assert set(quickstart.probe["reduction_table"]["numpy"]) == {
        "mean",
        "sum",
        "max",
        "min",
        "last",
        "std",
    }
    # The histogram line: [underflow, bins..., overflow] around numpy's in-range counts.
    out = stream(cell(quickstart.nb, "report-stats"))
    ours, numpys = ([int(v) for v in m.split()] for m in re.findall(r"\[([\d ]+)\]", out))
    assert ours == [0, *numpys, 0]
    assert numpys == np.histogram([3, 1, 4, 1, 5, 9, 2, 6], bins=5, range=(0, 10))[0].tolist()


@pytest.mark.slow
def test_quickstart_dataframe_has_the_tags_of_the_spec(quickstart):
    tags = set(quickstart.probe["tags"])
    ret = "Episode_Metrics/return"
    assert {ret + s for s in ("", "/std", "/min", "/max", "/count")} <= tags
    assert {f"{ret}/window_{s}" for s in ("mean", "std", "min", "max", "p10", "p50", "p90")} <= tags
    for term in ("truncated", "joint_vel", "max_tilt"):
        assert f"Episode_Metrics/{term}" in tags
    assert {"Counters/env_steps", "Counters/episodes", "Counters/env_steps/per_sec"} <= tags
    printed = stream(cell(quickstart.nb, "tags")).splitlines()[1:]
    assert printed == sorted(t for t in tags if t.startswith(ret))


@pytest.mark.slow
def test_quickstart_reports_every_episode_once(quickstart):
    p = quickstart.probe
    per_report = p["chunk"] * p["num_envs"]
    assert p["steps"] == [per_report * (i + 1) for i in range(p["chunks"])]
    assert p["env_steps"] == p["steps"]
    # Period counts partition the lifetime episode counter.
    assert np.cumsum(p["counts"]).tolist() == p["episodes"]
    out = stream(cell(quickstart.nb, "count-sum"))
    assert re.findall(r"(\d+)$", out, re.M) == [str(int(p["episodes"][-1]))] * 2


@pytest.mark.slow
def test_quickstart_window_percentiles_match_numpy_and_every_plot_is_drawn(quickstart):
    window = np.asarray(quickstart.probe["window"], np.float64)
    assert window.shape == (100,)
    for p, v in quickstart.probe["pcts"].items():
        assert v == pytest.approx(np.percentile(window, float(p)), rel=1e-5), p
    for cell_id in ("histogram", "window", "over-time"):
        assert images(cell(quickstart.nb, cell_id)) == 1, cell_id


# --------------------------------------------------------------------- training


@pytest.mark.slow
def test_training_writes_every_iteration_to_tensorboard(training):
    p = training.probe
    steps = [p["spi"] * (i + 1) for i in range(p["iterations"])]
    assert stream(cell(training.nb, "train")).strip() == f"TensorBoard run: {p['log_dir']}"
    acc = event_accumulator.EventAccumulator(
        p["log_dir"], size_guidance={event_accumulator.SCALARS: 0}
    )
    acc.Reload()
    scalars = set(acc.Tags()["scalars"])
    for tag in [f"Train/{n}" for n in p["learner"]] + [
        "Episode_Metrics/episode_return/window_mean",
        "Counters/env_steps",
        "Timers/iteration",
    ]:
        assert tag in scalars, tag
        assert [e.step for e in acc.Scalars(tag)] == steps, tag
    # The live view and TensorBoard saw the same records (TensorBoard stores float32).
    ret = {e.step: e.value for e in acc.Scalars("Episode_Metrics/episode_return/window_mean")}
    memory = {int(k): v for k, v in p["memory_return"].items()}
    assert sorted(memory) == steps
    for step in steps:
        assert ret[step] == pytest.approx(memory[step], rel=1e-6), step
    # What the notebook's text claims: the pole stays up much longer at the end.
    assert ret[steps[-1]] > 3 * ret[steps[0]], (ret[steps[0]], ret[steps[-1]])


@pytest.mark.slow
def test_training_live_view_ends_on_the_last_iteration(training):
    outputs = cell(training.nb, "train").outputs
    shown = [o for o in outputs if o.output_type == "display_data"]
    assert len(shown) == 2  # the table and the plot, updated in place
    table, plot = shown
    assert "text/html" in table.data
    rows = re.findall(r"^(\d+)\s", table.data["text/plain"], re.M)
    assert rows[-1] == str(training.probe["iterations"])
    assert "image/png" in plot.data
    assert "%tensorboard" not in "".join(c.source for c in training.nb.cells)
    assert len(training.skipped) == 1


# --------------------------------------------------------------------- custom_terms


@pytest.mark.slow
def test_custom_terms_reward_components_add_up_to_the_return(custom_terms):
    r = custom_terms.probe["report"]
    ep = "Episode_Metrics/"
    counts = {r[k] for k in r if k.endswith("/count")}
    assert len(counts) == 1 and counts.pop() > 0  # every metric saw the same episodes
    parts = sum(r[f"{ep}reward_{c}"] for c in ("alive", "angle", "ctrl"))
    assert r[f"{ep}return"] == pytest.approx(parts, rel=1e-5)
    assert r[f"{ep}reward_alive"] > 0 > r[f"{ep}reward_angle"]
    # Multi-output term: per episode, max >= mean of the same |angle|; upright is a fraction.
    assert r[f"{ep}pole/max_angle/min"] >= r[f"{ep}pole/mean_angle/min"]
    assert r[f"{ep}pole/max_angle"] >= r[f"{ep}pole/mean_angle"]
    assert 0.0 <= r[f"{ep}pole/upright/min"] <= r[f"{ep}pole/upright/max"] <= 1.0
    out = stream(cell(custom_terms.nb, "components-sum"))
    mean_return, summed = re.findall(r"(-?\d+\.\d+)$", out, re.M)
    assert mean_return == summed


@pytest.mark.slow
def test_custom_terms_nan_handling_is_visible(custom_terms):
    c = cell(custom_terms.nb, "nan-report")
    warning = stream(c, "stderr")
    assert "RuntimeWarning: step 0, run 0: term 'skip': 2 non-finite value(s) left out" in warning
    assert "'propagate'" not in warning  # only "skip" warns
    r = custom_terms.probe["nan_report"]
    # Reference by hand: env episodes under "skip" are 1, 2, 3 (NaN and inf steps left out).
    assert r["Episode_Metrics/skip"] == 2.0
    assert r["Episode_Metrics/skip/window_mean"] == 2.0
    assert r["Episode_Metrics/skip/count"] == 3
    assert r["Episode_Metrics/skip/nonfinite"] == 2
    assert math.isnan(r["Episode_Metrics/propagate"])
    assert r["Episode_Metrics/propagate/nonfinite"] == 2
    table = next(o for o in c.outputs if o.output_type == "execute_result").data["text/plain"]
    assert "not written" in table
    raised = stream(cell(custom_terms.nb, "nan-raise"))
    assert raised.startswith("NonFiniteError: ") and "'speed'" in raised


@pytest.mark.slow
def test_custom_terms_smoothing_matches_numpy(custom_terms):
    t = custom_terms.probe["check"]
    assert set(t["numpy"]) == {
        "period mean",
        "period count",
        "window(100) mean",
        "ema(0.01)",
        "ema(0.1)",
    }
    for stat, want in t["numpy"].items():
        assert t["jaxmetrics"][stat] == pytest.approx(want, rel=1e-5), stat
    assert images(cell(custom_terms.nb, "smoothing")) == 1


@pytest.mark.slow
def test_custom_terms_discounted_returns_and_quantiles_match_numpy(custom_terms):
    t = custom_terms.probe["dq_check"]
    got, want = t["jaxmetrics"], t["numpy"]
    assert got["episodes"] == want["episodes"] > 100
    assert got["mean discounted return"] == pytest.approx(want["mean discounted return"], 1e-5)
    for q in ("q10", "q50", "q90"):
        assert abs(got[q] - want[q]) <= 0.01 * abs(want[q]), q
    assert want["q10"] < 0 < want["q90"]  # both signs


@pytest.mark.slow
def test_custom_terms_groups_match_a_pandas_groupby(custom_terms):
    t = custom_terms.probe["group_check"]
    assert set(t["by hand count"]) == {"flat", "rough", "stairs"}  # every level has episodes
    for level, want in t["by hand mean"].items():
        assert t["jaxmetrics mean"][level] == pytest.approx(want, rel=1e-5), level
        assert t["jaxmetrics count"][level] == t["by hand count"][level], level
    assert all(t["match"].values())
