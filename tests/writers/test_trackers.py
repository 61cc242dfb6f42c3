"""Experiment trackers: what lands in Weights & Biases (offline runs, read back from their
`.wandb` files) and MLflow (a local SQLite store, read back with `MlflowClient`), checked
against the float64 numpy reference of test_writers. No network."""

import glob
import os
import struct
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_writers import BINS, FLOAT_TAGS, RANGE, STEPS, WINDOW, _periods, _reference

import jaxmetrics as jm

RUNS = 2
BIG = 2**32 - 1  # counters pass 2^32 (exact in W&B, float64 in MLflow)
HPARAMS = {"lr": 0.001, "algo": "ppo", "epochs": 4}


def _log_runs(writers):
    """Two vmapped seeds: seed r logs test_writers' periods + r; its counter grows by
    BIG - r per flush. `writers` is a `per_seed` factory; its `seeds_summary()` writes
    the cross-seed summary."""
    stats = ("mean", "std", "min", "max", "sum", "count", jm.ema(0.5))
    stats += (jm.window(WINDOW, percentiles=(50,)), jm.histogram(BINS, RANGE))
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=stats)}, counters=["samples"])
    state = jax.vmap(lambda _: metrics.init(1))(jnp.arange(RUNS))
    log = jax.vmap(lambda s, v: metrics.log(s, {"x": v}))
    inc = jax.vmap(lambda s, b: metrics.increment(s, "samples", b))
    with jm.Logger(metrics, writers, runs=RUNS, seeds_summary=writers.seeds_summary()) as logger:
        for step, vals in zip(STEPS, _periods()):
            if len(vals):
                shifted = np.stack([vals + r for r in range(RUNS)]).astype(np.float32)
                state = log(state, jnp.asarray(shifted))
            state = inc(state, jnp.array([BIG - r for r in range(RUNS)], jnp.uint32))
            state = logger.flush(state, step)


def _references():
    return [_reference([p + r for p in _periods()]) for r in range(RUNS)]


def _summary_reference():
    """Per step, tag -> (mean, sample std, count) of the seeds' float64 reference values
    of the tags both seeds have (the seeds' empty periods coincide)."""
    refs = _references()
    out = []
    for i in range(len(STEPS)):
        row = {}
        for tag in [*FLOAT_TAGS, "Train/x/count"]:
            if tag in refs[0][i]:
                v = np.array([float(ref[i][tag]) for ref in refs], np.float64)
                row[tag] = (v.mean(), v.std(ddof=1), v.size)
        out.append(row)
    return out


# ---------------------------------------------------------------- Weights & Biases


def _wait_for_wandb():
    """W&B's service writes a finished run's file in the background; its teardown waits
    for that (as it does at interpreter exit)."""
    import wandb

    wandb.teardown()


def _wandb_records(path):
    """The protobuf records of an offline run's `.wandb` file: W&B's LevelDB-style log
    (a 7-byte file header, 32 KiB blocks, records split into FULL/FIRST/MIDDLE/LAST
    chunks behind a 7-byte header: crc32, length, type)."""
    from wandb.proto import wandb_internal_pb2

    with open(path, "rb") as f:
        data = f.read()
    assert data[:4] == b":W&B" and struct.unpack("<H", data[4:6]) == (0xBEE1,)
    pos, chunks, out = 7, b"", []
    while pos + 7 <= len(data):
        if 32768 - pos % 32768 < 7:  # a block's tail too short for a header is padding
            pos += 32768 - pos % 32768
            continue
        _, n, kind = struct.unpack("<IHB", data[pos : pos + 7])
        chunks += data[pos + 7 : pos + 7 + n]
        pos += 7 + n
        if kind in (1, 4):  # FULL, LAST
            record = wandb_internal_pb2.Record()
            record.ParseFromString(chunks)
            out.append(record)
            chunks = b""
    return out


def _wandb_run(path):
    """run proto, config, history rows (step -> key -> JSON text), last summary values."""
    import json

    run, config, history, summary = None, {}, {}, {}
    for r in _wandb_records(path):
        kind = r.WhichOneof("record_type")
        if kind == "run":
            run = r.run
            config.update({i.key: json.loads(i.value_json) for i in r.run.config.update})
        elif kind == "config":
            config.update({i.key: json.loads(i.value_json) for i in r.config.update})
        elif kind == "history":
            row = {i.key or "/".join(i.nested_key): i.value_json for i in r.history.item}
            history[int(row["_step"])] = row
        elif kind == "summary":
            summary.update(
                {i.key or "/".join(i.nested_key): i.value_json for i in r.summary.update}
            )
    return run, config, history, summary


@pytest.fixture(scope="module")
def wandb_runs(tmp_path_factory):
    root = tmp_path_factory.mktemp("wandb")
    _log_runs(
        jm.WandbWriter.per_seed(
            "jaxmetrics-test", group="exp", mode="offline", dir=root, hparams=HPARAMS
        )
    )
    _wait_for_wandb()
    runs = [_wandb_run(p) for p in glob.glob(str(root / "wandb" / "offline-run-*" / "*.wandb"))]
    return {
        run.display_name: (run, config, history, summary) for run, config, history, summary in runs
    }


def test_wandb_one_run_per_seed_in_one_group_with_hparams_as_config(wandb_runs):
    assert sorted(wandb_runs) == ["exp/seed_0", "exp/seed_1", "exp/seeds_summary"]
    for run, config, _, _ in wandb_runs.values():
        assert (run.project, run.run_group) == ("jaxmetrics-test", "exp")
        assert {k: config[k] for k in HPARAMS} == HPARAMS


def test_wandb_history_matches_float64_reference_and_skips_empty(wandb_runs):
    import json

    for r, ref in enumerate(_references()):
        _, _, history, _ = wandb_runs[f"exp/seed_{r}"]
        assert sorted(history) == STEPS
        for tag in FLOAT_TAGS:
            got = {s: json.loads(row[tag]) for s, row in history.items() if tag in row}
            want = {s: x[tag] for s, x in zip(STEPS, ref) if tag in x}
            assert sorted(got) == sorted(want), tag  # the empty period is a gap
            for s, v in want.items():
                np.testing.assert_allclose(got[s], v, rtol=1e-5, atol=1e-6, err_msg=f"{tag}@{s}")
        counts = {s: json.loads(row["Train/x/count"]) for s, row in history.items()}
        assert counts == {s: x["Train/x/count"] for s, x in zip(STEPS, ref)}


def test_wandb_seeds_summary_run_holds_the_mean_and_std_across_seeds(wandb_runs):
    import json

    _, _, history, _ = wandb_runs["exp/seeds_summary"]
    assert sorted(history) == STEPS
    for s, want in zip(STEPS, _summary_reference()):
        row = history[s]
        counted = {t for t in row if t.endswith("/seeds_count")}
        counters = ["Counters/samples"] + (["Counters/samples/per_sec"] if s > STEPS[0] else [])
        assert counted == {f"{t}/seeds_count" for t in [*want, *counters]}
        for tag, (mean, std, n) in want.items():
            np.testing.assert_allclose(json.loads(row[tag]), mean, rtol=1e-5, atol=1e-6)
            np.testing.assert_allclose(json.loads(row[f"{tag}/seeds_std"]), std, atol=1e-5)
            assert json.loads(row[f"{tag}/seeds_count"]) == n


def test_wandb_counters_are_exact_in_history_and_summary(wandb_runs):
    for r in range(RUNS):
        _, _, history, summary = wandb_runs[f"exp/seed_{r}"]
        totals = [(i + 1) * (BIG - r) for i in range(len(STEPS))]
        assert [history[s]["Counters/samples"] for s in STEPS] == [str(t) for t in totals]
        assert summary["Counters/samples"] == str(totals[-1])


def test_wandb_histograms_have_spec_edges_and_window_histograms_numpy_counts(wandb_runs):
    import json

    edges = np.linspace(*RANGE, BINS + 1)
    for r, ref in enumerate(_references()):
        _, _, history, _ = wandb_runs[f"exp/seed_{r}"]
        for s, x in zip(STEPS, ref):
            row = history[s]
            if x["Train/x/count"]:  # written when the period has values, in range or not
                assert json.loads(row["Train/x/histogram/_type"]) == "histogram"
                np.testing.assert_array_equal(
                    json.loads(row["Train/x/histogram/values"]), x["Train/x/histogram"]
                )
                np.testing.assert_allclose(json.loads(row["Train/x/histogram/bins"]), edges)
            else:
                assert "Train/x/histogram/values" not in row
            counts, window_edges = np.histogram(x["window"], bins=30)
            np.testing.assert_array_equal(json.loads(row["Train/x/window_values/values"]), counts)
            np.testing.assert_allclose(
                json.loads(row["Train/x/window_values/bins"]), window_edges, rtol=1e-12
            )


def test_wandb_histograms_past_512_bins_are_coarsened_exactly(tmp_path):
    import json

    rng = np.random.default_rng(1)
    counts = rng.integers(0, 9, size=1030)
    edges = np.linspace(-1.0, 1.0, 1031)
    writer = jm.WandbWriter("p", mode="offline", dir=tmp_path)
    writer.open([])
    hist = jm.HistogramData(edges, counts, 0, 0)
    writer.write(jm.Record(1, 0.0, {"Counters/n": 2**53 + 1}, {"h/histogram": hist}, {}))
    writer.close()
    _wait_for_wandb()
    (path,) = glob.glob(str(tmp_path / "wandb" / "offline-run-*" / "*.wandb"))
    _, _, history, summary = _wandb_run(path)
    # 1030 bins in runs of ceil(1030 / 512) = 3: 343 runs of 3, one of 1.
    want = [counts[i : i + 3].sum() for i in range(0, 1030, 3)]
    assert json.loads(history[1]["h/histogram/values"]) == want
    np.testing.assert_array_equal(
        json.loads(history[1]["h/histogram/bins"]), [*edges[0:1030:3], edges[-1]]
    )
    assert summary["Counters/n"] == str(2**53 + 1)  # a float64 would round it


def test_wandb_writer_rejects_bad_options_at_creation(tmp_path):
    with pytest.raises(ValueError, match="mode must be one of"):
        jm.WandbWriter("p", mode="ofline")
    with pytest.raises(ValueError, match=r"window_bins must be an int in \[1, 512\]"):
        jm.WandbWriter("p", window_bins=513)
    with pytest.raises(ValueError, match=r"pass \['config'\] as WandbWriter's own arguments"):
        jm.WandbWriter("p", init_kwargs={"config": {}})
    with pytest.raises(TypeError, match="project must be a non-empty string"):
        jm.WandbWriter("")
    with pytest.raises(TypeError, match="group must be a non-empty string"):
        jm.WandbWriter.per_seed("p", group=None)
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ValueError, match="cannot create dir"):
        jm.WandbWriter("p", dir=blocker / "sub")


# ---------------------------------------------------------------- MLflow


@pytest.fixture(scope="module")
def mlflow_uri(tmp_path_factory):
    """One SQLite store for the module (creating one takes seconds)."""
    return f"sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"


@pytest.fixture(scope="module")
def mlflow_runs(mlflow_uri):
    from mlflow.tracking import MlflowClient

    uri = mlflow_uri
    _log_runs(
        jm.MLflowWriter.per_seed(
            "exp", run_name="ppo", tracking_uri=uri, hparams=HPARAMS, tags={"team": "rl"}
        )
    )
    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("exp").experiment_id])
    return client, {r.info.run_name: r for r in runs}


def test_mlflow_seeds_are_child_runs_of_one_finished_parent_with_params(mlflow_runs):
    _, runs = mlflow_runs
    assert sorted(runs) == ["ppo", "ppo/seed_0", "ppo/seed_1"]
    parent = runs["ppo"].info.run_id
    want = {k: str(v) for k, v in HPARAMS.items()}
    for name, run in runs.items():
        assert run.info.status == "FINISHED"
        assert run.data.params == want
        assert run.data.tags["team"] == "rl"
        assert run.data.tags.get("mlflow.parentRunId") == (None if name == "ppo" else parent)


def test_mlflow_metric_history_matches_float64_reference(mlflow_runs):
    client, runs = mlflow_runs
    for r, ref in enumerate(_references()):
        run_id = runs[f"ppo/seed_{r}"].info.run_id
        for tag in [*FLOAT_TAGS, "Train/x/count"]:
            got = {m.step: m.value for m in client.get_metric_history(run_id, tag)}
            want = {s: x[tag] for s, x in zip(STEPS, ref) if tag in x}
            assert sorted(got) == sorted(want), tag  # the empty period is a gap
            for s, v in want.items():
                np.testing.assert_allclose(got[s], v, rtol=1e-5, atol=1e-6, err_msg=f"{tag}@{s}")
        counters = client.get_metric_history(run_id, "Counters/samples")
        assert [(m.step, m.value) for m in counters] == [
            (s, float((i + 1) * (BIG - r))) for i, s in enumerate(STEPS)
        ]


def test_mlflow_seeds_summary_goes_into_the_parent_run(mlflow_runs):
    client, runs = mlflow_runs
    run_id = runs["ppo"].info.run_id
    want = _summary_reference()
    for tag in [*FLOAT_TAGS, "Train/x/count"]:
        for stat, k in (("", 0), ("/seeds_std", 1), ("/seeds_count", 2)):
            got = {m.step: m.value for m in client.get_metric_history(run_id, tag + stat)}
            ref = {s: w[tag][k] for s, w in zip(STEPS, want) if tag in w}
            assert sorted(got) == sorted(ref), tag + stat
            for s, v in ref.items():
                np.testing.assert_allclose(got[s], v, rtol=1e-5, atol=1e-5, err_msg=tag + stat)


def test_mlflow_writer_rejects_bad_options_at_creation(tmp_path):
    with pytest.raises(TypeError, match=r"hparam 'opt'=.*MLflow params"):
        jm.MLflowWriter(hparams={"opt": object()})
    with pytest.raises(TypeError, match="tags must be a dict of strings"):
        jm.MLflowWriter(tags={"k": 1})
    with pytest.raises(TypeError, match="experiment must be a non-empty string"):
        jm.MLflowWriter("")
    with pytest.raises(ValueError, match="cannot use the MLflow tracking store 'nope://x'"):
        jm.MLflowWriter(tracking_uri="nope://x")
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(ValueError, match=r"tracking store 'sqlite:///.*/file/m.db': FileExists"):
        jm.MLflowWriter(tracking_uri=f"sqlite:///{blocker}/m.db")


def test_mlflow_writer_makes_a_child_of_a_given_parent_run(mlflow_uri):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(mlflow_uri)
    experiment = client.create_experiment("parented")
    parent = client.create_run(experiment, run_name="sweep").info.run_id
    writer = jm.MLflowWriter("parented", tracking_uri=mlflow_uri, parent_run_id=parent)
    writer.open([])
    writer.close()
    run = client.get_run(writer.run_id)
    assert run.data.tags["mlflow.parentRunId"] == parent
    assert run.info.status == "FINISHED"


def test_mlflow_store_errors_surface_on_the_callers_thread(mlflow_uri):
    from mlflow.tracking import MlflowClient

    uri = mlflow_uri
    metrics = jm.Metrics(logged=["x"])
    writer = jm.MLflowWriter("errors", tracking_uri=uri)
    logger = jm.Logger(metrics, [writer])
    MlflowClient(uri).delete_run(writer.run_id)  # MLflow refuses metrics of a deleted run
    logger.flush(metrics.log(metrics.init(1), {"x": jnp.float32(1.0)}), 5)
    with pytest.raises(RuntimeError, match=r"writer <.*MLflowWriter.* of run 0 failed at step 5"):
        logger.close()


# ---------------------------------------------------------------- both


def test_backends_are_imported_only_when_their_writer_is_created(tmp_path):
    # (and `import jaxmetrics` never imports MuJoCo Playground)
    code = (
        "import sys, jaxmetrics as jm\n"
        "seen = lambda: [m for m in ('wandb', 'mlflow', 'mujoco_playground') if m in sys.modules]\n"
        "print(seen())\n"
        f"jm.WandbWriter('p', mode='disabled', dir={str(tmp_path)!r})\n"
        "print(seen())\n"
        "try:\n"
        "    jm.MLflowWriter(tracking_uri='nope://x')\n"  # imports mlflow, then refuses
        "except ValueError:\n"
        "    print(seen())\n"
    )
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    env = dict(os.environ, PYTHONPATH=path, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:3] == ["[]", "['wandb']", "['wandb', 'mlflow']"]


def test_mlflow_logs_the_good_metrics_of_a_record_with_a_refused_key(mlflow_uri):
    # A key MLflow refuses (here from Brax's progress_fn, whose keys are Brax's) used to
    # fail the whole log_batch: every metric of the record was lost.
    from mlflow.tracking import MlflowClient

    writer = jm.MLflowWriter("refused", tracking_uri=mlflow_uri)
    writer.open([])
    record = jm.Record(
        step=3,
        wall_time=1.0,
        scalars={"Train/a": 1.5, "Brax/custom//thing": 2.0, "Train/b": 2.5},
        histograms={},
        windows={},
    )
    with pytest.raises(ValueError, match=r"refused 1 of the 3 metrics .* 'Brax/custom//thing'"):
        writer.write(record)
    writer.close()
    logged = MlflowClient(mlflow_uri).get_run(writer.run_id).data.metrics
    assert logged == {"Train/a": 1.5, "Train/b": 2.5}
