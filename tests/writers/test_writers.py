"""Writers: what lands in TensorBoard event files, JSON lines, memory and the console,
checked against a float64 numpy reference of the same data (files read back with
TensorBoard's own reader and the json module)."""

import io
import json
import os
import re
import subprocess
import sys

import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from tensorboard.backend.event_processing import event_accumulator as ea
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import plugin_data_pb2

import jaxmetrics as jm

WINDOW = 5
BINS, RANGE = 4, (0.0, 1.0)
STEPS = [10, 20, 30, 40]
OWN_LINE = b'{"step":1,"wall_time":2.0,"scalars":{},"histograms":{},"windows":{}}\n'


def _periods():
    # Multiples of 1/64 are exact in float32, so bin membership cannot differ from the
    # float64 reference by rounding. Period 2 is empty; values fall outside RANGE too.
    rng = np.random.default_rng(0)
    sizes = [6, 3, 0, 7]
    return [rng.integers(-8, 72, size=n) / 64.0 for n in sizes]


def _reference(periods):
    """Float64 numpy reference per flush: period stats, window, histogram, EMA."""
    out, history, ema = [], [], None
    for vals in periods:
        for v in vals:
            ema = v if ema is None else 0.5 * v + 0.5 * ema
        history.extend(vals.tolist())
        window = np.array(history[-WINDOW:])
        counts, _ = np.histogram(vals[(vals >= RANGE[0]) & (vals <= RANGE[1])], BINS, RANGE)
        ref = {
            "Train/x/count": len(vals),
            "Train/x/sum": float(vals.sum()),
            "Train/x/histogram": counts,
            "under": int((vals < RANGE[0]).sum()),
            "over": int((vals > RANGE[1]).sum()),
        }
        if len(vals):
            ref.update(
                {
                    "Train/x": vals.mean(),
                    "Train/x/std": vals.std(),
                    "Train/x/min": vals.min(),
                    "Train/x/max": vals.max(),
                }
            )
        if len(window):
            ref.update(
                {
                    "Train/x/window_mean": window.mean(),
                    "Train/x/window_std": window.std(),
                    "Train/x/window_min": window.min(),
                    "Train/x/window_max": window.max(),
                    "Train/x/window_p50": np.percentile(window, 50),
                    "Train/x/ema": ema,
                    "window": window,
                }
            )
        out.append(ref)
    return out


FLOAT_TAGS = [
    "Train/x",
    "Train/x/std",
    "Train/x/min",
    "Train/x/max",
    "Train/x/sum",
    "Train/x/ema",
    "Train/x/window_mean",
    "Train/x/window_std",
    "Train/x/window_min",
    "Train/x/window_max",
    "Train/x/window_p50",
]


@pytest.fixture(scope="module")
def written(tmp_path_factory):
    """One logger writing the same flushes to TensorBoard, JSON lines, memory, console."""
    root = tmp_path_factory.mktemp("writers")
    periods = _periods()
    stats = ("mean", "std", "min", "max", "sum", "count", jm.ema(0.5))
    stats += (jm.window(WINDOW, percentiles=(50,)), jm.histogram(BINS, RANGE))
    metrics = jm.Metrics(logged={"x": jm.Logged(stats=stats)}, counters=["updates"])
    console = io.StringIO()
    memory = jm.MemoryWriter()
    writers = [
        jm.TensorBoardWriter(root / "tb", hparams={"lr": 0.001, "algo": "ppo"}),
        jm.TensorBoardWriter(root / "tb_bands", std_bands=True),
        jm.JsonlWriter(root / "metrics.jsonl"),
        memory,
        jm.ConsoleWriter(console, width=200),
    ]
    state = metrics.init(1)
    with jm.Logger(metrics, writers) as logger:
        for step, vals in zip(STEPS, periods):
            if len(vals):
                state = metrics.log(state, {"x": jnp.asarray(vals, jnp.float32)})
            state = metrics.increment(state, "updates", 2)
            state = logger.flush(state, step)
    acc, bands = (
        ea.EventAccumulator(
            str(root / run), size_guidance={ea.SCALARS: 0, ea.HISTOGRAMS: 0, ea.TENSORS: 0}
        )
        for run in ("tb", "tb_bands")
    )
    acc.Reload()
    bands.Reload()
    return {
        "root": root,
        "ref": _reference(periods),
        "acc": acc,
        "bands": bands,
        "memory": memory,
        "console": console.getvalue(),
    }


def _tb_scalars(acc, tag):
    return {e.step: e.value for e in acc.Scalars(tag)}


def test_tensorboard_scalars_match_float64_reference_and_skip_empty(written):
    acc, ref = written["acc"], written["ref"]
    for tag in FLOAT_TAGS:
        got = _tb_scalars(acc, tag)
        want = {s: r[tag] for s, r in zip(STEPS, ref) if tag in r}
        assert sorted(got) == sorted(want), tag  # the empty period is a gap, not a 0
        for s, v in want.items():
            np.testing.assert_allclose(got[s], v, rtol=1e-5, atol=1e-6, err_msg=f"{tag}@{s}")
    assert 30 not in _tb_scalars(acc, "Train/x")
    assert _tb_scalars(acc, "Train/x/count") == {s: r["Train/x/count"] for s, r in zip(STEPS, ref)}
    assert _tb_scalars(acc, "Counters/updates") == {s: 2 * (i + 1) for i, s in enumerate(STEPS)}


def test_tensorboard_histogram_statistic_has_spec_edges_and_numpy_counts(written):
    acc, ref = written["acc"], written["ref"]
    events = {e.step: e.histogram_value for e in acc.Histograms("Train/x/histogram")}
    want_steps = [s for s, r in zip(STEPS, ref) if r["Train/x/histogram"].sum() > 0]
    assert sorted(events) == want_steps
    edges = np.linspace(*RANGE, BINS + 1)
    for s in want_steps:
        h, r = events[s], ref[STEPS.index(s)]
        np.testing.assert_array_equal(h.bucket, r["Train/x/histogram"])
        np.testing.assert_array_equal(h.bucket_limit, edges[1:])
        assert (h.min, h.max, h.num) == (edges[0], edges[-1], r["Train/x/histogram"].sum())
    under = _tb_scalars(acc, "Train/x/histogram/underflow")
    first = next(i for i, r in enumerate(ref) if r["under"])
    assert under == {s: r["under"] for s, r in list(zip(STEPS, ref))[first:]}


def test_tensorboard_window_histogram_matches_numpy_histogram_of_window(written):
    acc, ref = written["acc"], written["ref"]
    events = {e.step: e.histogram_value for e in acc.Histograms("Train/x/window_values")}
    assert sorted(events) == STEPS  # the window persists through the empty period
    for s, r in zip(STEPS, ref):
        h, w = events[s], r["window"]
        counts, edges = np.histogram(w, bins=30)
        np.testing.assert_array_equal(h.bucket, counts)
        np.testing.assert_allclose(h.bucket_limit, edges[1:])
        np.testing.assert_allclose(
            [h.min, h.max, h.num, h.sum, h.sum_squares],
            [w.min(), w.max(), w.size, w.sum(), w @ w],
            rtol=1e-12,
        )


def test_tensorboard_writes_std_bands_only_on_request(written):
    acc, bands = written["acc"], written["bands"]
    assert not [t for t in acc.Tags()["scalars"] if t.startswith("Margin/")]
    assert "custom_scalars__config__" not in acc.Tags()["tensors"]
    banded = sorted(t for t in bands.Tags()["scalars"] if t.startswith("Margin/"))
    assert banded == ["Margin/Train/x/lower", "Margin/Train/x/upper"]
    assert set(bands.Tags()["scalars"]) - set(banded) == set(acc.Tags()["scalars"])


def test_tensorboard_margin_layout_pairs_each_mean_with_its_std_band(written):
    acc, ref = written["bands"], written["ref"]
    (event,) = acc.Tensors("custom_scalars__config__")
    layout = layout_pb2.Layout()
    layout.ParseFromString(event.tensor_proto.string_val[0])
    series = {
        s.value: (s.lower, s.upper)
        for c in layout.category
        for chart in c.chart
        for s in chart.margin.series
    }
    assert series == {"Train/x": ("Margin/Train/x/lower", "Margin/Train/x/upper")}
    lower, upper = (
        _tb_scalars(acc, "Margin/Train/x/lower"),
        _tb_scalars(acc, "Margin/Train/x/upper"),
    )
    want = {s: (r["Train/x"], r["Train/x/std"]) for s, r in zip(STEPS, ref) if "Train/x" in r}
    assert sorted(lower) == sorted(upper) == sorted(want)
    for s, (m, sd) in want.items():
        np.testing.assert_allclose([lower[s], upper[s]], [m - sd, m + sd], rtol=1e-5, atol=1e-6)


def test_tensorboard_hparams_session_lists_hparams_and_mean_metrics(written):
    content = written["acc"].PluginTagToContent("hparams")
    start = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/session_start_info"])
    hp = start.session_start_info.hparams
    assert (hp["lr"].number_value, hp["algo"].string_value) == (0.001, "ppo")
    exp = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"])
    assert [m.name.tag for m in exp.experiment.metric_infos] == ["Train/x"]
    end = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/session_end_info"])
    assert end.HasField("session_end_info")


def test_jsonl_round_trip_matches_reference(written):
    with open(written["root"] / "metrics.jsonl") as f:
        lines = [json.loads(line) for line in f]
    assert [d["step"] for d in lines] == STEPS
    for d, r in zip(lines, written["ref"]):
        sc = d["scalars"]
        for tag in FLOAT_TAGS:
            assert (tag in sc) == (tag in r), tag
            if tag in r:
                np.testing.assert_allclose(sc[tag], r[tag], rtol=1e-5, atol=1e-6)
        assert isinstance(sc["Train/x/count"], int) and sc["Train/x/count"] == r["Train/x/count"]
        h = d["histograms"].get("Train/x/histogram")
        if r["Train/x/histogram"].sum() + r["under"] + r["over"] == 0:
            assert h is None
        else:
            assert h["counts"] == r["Train/x/histogram"].tolist()
            assert (h["underflow"], h["overflow"]) == (r["under"], r["over"])
            assert h["edges"] == np.linspace(*RANGE, BINS + 1).tolist()
        assert d["windows"]["Train/x/window_values"] == r["window"].tolist()


def test_memory_dataframe_is_long_format_of_every_scalar(written):
    df, ref = written["memory"].dataframe(), written["ref"]
    assert list(df.columns) == ["step", "tag", "value"]
    assert [str(t) for t in df.dtypes] == ["int64", "object", "float64"]
    for tag in FLOAT_TAGS:
        got = df[df.tag == tag]
        want = [(s, r[tag]) for s, r in zip(STEPS, ref) if tag in r]
        assert got.step.tolist() == [s for s, _ in want]
        np.testing.assert_allclose(got.value, [v for _, v in want], rtol=1e-5, atol=1e-6)
    records = written["memory"].records
    np.testing.assert_array_equal(records[0].windows["Train/x/window_values"], ref[0]["window"])


def test_memory_plot_draws_each_tag_with_its_std_band(written):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ax = written["memory"].plot("Train/x", "Train/x/window_mean")
    lines = {line.get_label(): line for line in ax.get_lines()}
    assert sorted(lines) == ["Train/x", "Train/x/window_mean"]
    ref = written["ref"]
    np.testing.assert_allclose(
        lines["Train/x"].get_ydata(), [r["Train/x"] for r in ref if "Train/x" in r], rtol=1e-5
    )
    assert len(ax.collections) == 1  # only Train/x has a recorded std
    with pytest.raises(ValueError, match="Train/nope"):
        written["memory"].plot("Train/nope")
    plt.close("all")


def test_console_prints_a_row_per_metric_per_flush(written):
    out = written["console"]
    assert [line.split()[1] for line in out.splitlines() if line.startswith("step")] == [
        str(s) for s in STEPS
    ]
    first = next(line for line in out.splitlines() if line.startswith("Train/x"))
    cells = first.split()[1:6]
    want = [written["ref"][0][t] for t in FLOAT_TAGS[:4]]
    np.testing.assert_allclose([float(c) for c in cells[:4]], want, rtol=1e-3)
    assert cells[4] == "6"


def test_nonfinite_counts_appear_only_from_the_first_nonfinite_value(tmp_path):
    metrics = jm.Metrics(logged=["x"])
    memory = jm.MemoryWriter()
    state = metrics.init(1)
    with jm.Logger(metrics, [memory, jm.TensorBoardWriter(tmp_path)]) as logger:
        for step, v in enumerate([1.0, np.nan, 2.0]):
            state = metrics.log(state, {"x": jnp.float32(v)})
            if step == 2:
                with pytest.warns(RuntimeWarning, match="'x': 1 non-finite"):
                    state = logger.flush(state, step)
            else:
                state = logger.flush(state, step)
    acc = ea.EventAccumulator(str(tmp_path))
    acc.Reload()
    assert _tb_scalars(acc, "Train/x/nonfinite") == {1: 1, 2: 0}
    assert _tb_scalars(acc, "Train/x") == {0: 1.0, 2: 2.0}  # the NaN-only period is a gap
    df = memory.dataframe()
    assert df[df.tag == "Train/x/nonfinite"].step.tolist() == [1, 2]


@pytest.mark.parametrize("make", [jm.TensorBoardWriter, jm.JsonlWriter])
def test_invalid_log_path_fails_at_writer_creation_naming_it(tmp_path, make):
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    bad = [a_file / "run", tmp_path / "bad\0name"]
    bad.append(a_file if make is jm.TensorBoardWriter else tmp_path)  # a file / a directory
    for path in bad:
        with pytest.raises(ValueError) as e:
            make(path)
        assert repr(os.fspath(path))[1:-1] in str(e.value)
    with pytest.raises(ValueError, match="non-empty"):
        make("")


def test_band_tag_colliding_with_a_metric_tag_is_rejected_at_logger_creation(tmp_path):
    metrics = jm.Metrics(
        terms={"Train/x/lower": lambda s: s}, logged=["x"], episode_prefix="Margin"
    )
    with pytest.raises(ValueError, match="Margin/Train/x/lower"):
        jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path, std_bands=True)])
    assert os.listdir(tmp_path) == []  # no event file left behind
    jm.Logger(metrics, [jm.TensorBoardWriter(tmp_path)]).close()  # no bands, no collision


def test_logger_rejects_objects_that_are_not_writers():
    metrics = jm.Metrics(logged=["x"])
    with pytest.raises(TypeError, match="open\\(tags\\), write\\(record\\)"):
        jm.Logger(metrics, [print])
    with pytest.raises(TypeError, match="wrap the writer"):
        jm.Logger(metrics, jm.MemoryWriter())


def test_import_jaxmetrics_does_not_import_writer_backends():
    code = (
        "import sys, jaxmetrics\n"
        "heavy = [m for m in ('tensorboardX', 'tensorboard', 'rich', 'pandas', 'matplotlib')"
        " if m in sys.modules]\n"
        "print(heavy)"
    )
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    env = dict(os.environ, PYTHONPATH=path, JAX_PLATFORMS="cpu")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_jsonl_writer_appends_when_a_run_resumes(tmp_path):
    metrics = jm.Metrics(logged=["x"])
    path = tmp_path / "m.jsonl"
    for step in (0, 1):  # two processes' worth of loggers on the same file
        with jm.Logger(metrics, [jm.JsonlWriter(path)]) as logger:
            logger.flush(metrics.log(metrics.init(1), {"x": jnp.float32(step)}), step)
    with open(path) as f:
        assert [(d["step"], d["scalars"]["Train/x"]) for d in map(json.loads, f)] == [
            (0, 0.0),
            (1, 1.0),
        ]


def test_tensorboard_writer_rejects_bad_options_at_creation(tmp_path):
    with pytest.raises(ValueError, match="needs hparams"):
        jm.TensorBoardWriter(tmp_path, hparam_metrics=["Train/x"])
    with pytest.raises(TypeError, match="list of tags"):
        jm.TensorBoardWriter(tmp_path, hparams={"lr": 0.1}, hparam_metrics="Train/x")
    with pytest.raises(TypeError, match="'opt'"):
        jm.TensorBoardWriter(tmp_path, hparams={"opt": object()})
    with pytest.raises(ValueError, match="window_bins"):
        jm.TensorBoardWriter(tmp_path, window_bins=0)
    with pytest.raises(TypeError, match="std_bands must be a bool"):
        jm.TensorBoardWriter(tmp_path, std_bands="yes")
    assert os.listdir(tmp_path) == []  # the event file is created by open(), not here


@pytest.mark.parametrize(
    "content",
    [
        b'{"lr": 0.1}',  # another program's JSON, no final newline
        b'{"lr": 0.1}\n',
        b"notes\nlast line without newline",
        OWN_LINE + b'{"a": 1}\n',
        # Another program's JSON that starts like this writer's lines, and a lone brace:
        b'{"step": 10, "lr": 0.1, "note": "my config"}',  # json.dump: no final newline
        b'{"step":10,"lr":0.1}',
        b"{",
        # Compact JSON that starts as this writer's lines do, whole or cut, and then differs:
        b'{"step":100,"lr":0.001,}',
        b'{"step":3,"config":{"lr":0.1,"bat',
        b'{"step":3,"',  # too short to tell from the line above
        b'{"step":3,"wall_time":1.5,"loss":0.25',
        OWN_LINE + b'{"step":3,"config":{"lr":0.1,"bat',
        OWN_LINE + b'{"step":3,"wall_time":1.5,"scalars":{"x":1.0},"histograms":[',
        # This writer's keys in its order, but not its spacing or its values' shape:
        OWN_LINE.replace(b",", b", ") + b"{",
        OWN_LINE.replace(b'"scalars":{}', b'"scalars":{"x":"high"}') + b"{",
        OWN_LINE + b'{"step":2,"wall_time":3.0,"scalars":{"x":1.0,"x":2.0},"histograms":{},'
        b'"windows":{}}',  # a whole JSON value, but no line of this writer (a tag twice)
    ],
)
def test_jsonl_writer_refuses_a_file_that_is_not_its_own_and_touches_nothing(tmp_path, content):
    path = tmp_path / "config.json"
    path.write_bytes(content)
    os.chmod(path, 0o600)
    with pytest.raises(
        jm.ForeignFileError, match=r"config.json.*JsonlWriter record.*left untouched"
    ):
        jm.JsonlWriter(path)
    assert path.read_bytes() == content
    assert os.stat(path).st_mode & 0o777 == 0o600


@pytest.mark.parametrize(
    ("before", "cut"),
    [
        (b"", b'{"step":2,"wall_time":3.0,"scal'),  # the first record, cut
        (b'{"step":1,"wall_time":2.0,"scalars":{},"histograms":{},"windows":{}}\n', b"{"),
        (b'{"step":1,"wall_time":2.0,"scalars":{},"histograms":{},"windows":{}}\n', b'{"step":1'),
    ],
)
def test_jsonl_writer_drops_only_its_own_cut_record(tmp_path, before, cut):
    path = tmp_path / "m.jsonl"
    path.write_bytes(before + cut)
    jm.JsonlWriter(path).close()
    assert path.read_bytes() == before


_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=5),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3)
    ),
    max_leaves=6,
)


@settings(
    max_examples=200,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(
    step=st.integers(),
    rest=st.dictionaries(st.text(max_size=10), _JSON, max_size=4),
    compact=st.booleans(),
    ascii_only=st.booleans(),
    after_own_lines=st.booleans(),
    cut=st.integers(1, 200),
    newline=st.booleans(),
)
def test_jsonl_writer_never_modifies_another_programs_json_that_starts_like_its_lines(
    tmp_path, step, rest, compact, ascii_only, after_own_lines, cut, newline
):
    # Another program's object with "step" first, as json.dumps writes it, cut anywhere (or
    # whole, with or without its newline), alone or after whole lines of this writer.
    obj = {"step": step, **rest}
    separators = (",", ":") if compact else None
    text = json.dumps(obj, separators=separators, ensure_ascii=ascii_only).encode()
    line = text[:cut] + (b"\n" if newline and cut >= len(text) else b"")
    # This writer's first two keys start its records: past them, a cut line could be its own.
    assume(list(obj)[1:2] != ["wall_time"])
    if after_own_lines:
        # A cut inside those keys could be its own too, after its own lines.
        assume(not f'{{"step":{step},"wall_time":'.encode().startswith(line))
    content = (OWN_LINE if after_own_lines else b"") + line
    path = tmp_path / "other.jsonl"
    path.write_bytes(content)
    with pytest.raises(jm.ForeignFileError, match=r"other.jsonl.*left untouched"):
        jm.JsonlWriter(path)
    assert path.read_bytes() == content


_FINITE = st.floats(allow_nan=False, allow_infinity=False)
_TAGS = st.text(max_size=6)
_RECORDS = st.builds(
    jm.Record,
    step=st.integers(min_value=-(2**63), max_value=2**63),
    wall_time=st.floats(min_value=0.0, max_value=4e9),
    scalars=st.dictionaries(_TAGS, _FINITE | st.integers(0, 2**64), max_size=3),
    histograms=st.dictionaries(
        _TAGS,
        st.builds(
            jm.HistogramData,
            edges=st.lists(_FINITE, min_size=1, max_size=3).map(lambda e: np.array(e, np.float64)),
            counts=st.lists(st.integers(0, 2**40), max_size=2).map(lambda c: np.array(c, np.int64)),
            underflow=st.integers(0, 9),
            overflow=st.integers(0, 9),
        ),
        max_size=1,
    ),
    windows=st.dictionaries(
        _TAGS, st.lists(_FINITE, max_size=3).map(lambda w: np.array(w, np.float64)), max_size=2
    ),
)


@settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
@given(records=st.lists(_RECORDS, min_size=1, max_size=2))
def test_jsonl_writer_recovers_its_own_last_record_cut_at_any_byte(tmp_path, records):
    path = tmp_path / "m.jsonl"
    path.unlink(missing_ok=True)
    writer = jm.JsonlWriter(path)
    for record in records:
        writer.write(record)
    writer.close()
    data = path.read_bytes()
    start = data.rfind(b"\n", 0, -1) + 1
    before, last = data[:start], data[start:]
    for k in range(1, len(last)):
        path.write_bytes(before + last[:k])
        if before or re.match(rb'\{"step":-?\d+,"wall_time":', last[:k]):
            jm.JsonlWriter(path).close()
            # Cut before its newline, the record is dropped; cut at it, it is whole and kept.
            assert path.read_bytes() == (data if k == len(last) - 1 else before), k
        else:
            # A first line cut before its first two keys could be another program's.
            with pytest.raises(jm.ForeignFileError, match=r"m.jsonl.*too short.*delete it"):
                jm.JsonlWriter(path)
            assert path.read_bytes() == last[:k]


def test_jsonl_writer_repairs_a_crash_cut_record_keeping_mode_and_symlink(tmp_path):
    record = b'{"step":1,"wall_time":2.0,"scalars":{"Train/x":1.0},"histograms":{},"windows":{}}\n'
    real = tmp_path / "real.jsonl"
    real.write_bytes(record + b'{"step":2,"wall_time":3.0,"scal')  # cut by a crash
    os.chmod(real, 0o640)
    link = tmp_path / "link.jsonl"
    os.symlink(real, link)
    jm.JsonlWriter(link).close()
    assert os.path.islink(link) and os.readlink(link) == str(real)
    assert real.read_bytes() == record
    assert os.stat(real).st_mode & 0o777 == 0o640


def test_jsonl_writer_refuses_a_fifo_at_once_instead_of_blocking(tmp_path):
    fifo = tmp_path / "pipe.jsonl"
    os.mkfifo(fifo)
    with pytest.raises(ValueError, match=r"pipe.jsonl.*not a regular file"):
        jm.JsonlWriter(fifo)  # used to block for ever in open()


def test_two_runs_given_one_jsonl_path_are_refused_when_the_writers_are_made(tmp_path):
    path = tmp_path / "m.jsonl"
    metrics = jm.Metrics(logged=["x"])
    with pytest.raises(ValueError, match=r"another JsonlWriter .* has it open.*its own file"):
        jm.Logger(metrics, lambda run: [jm.JsonlWriter(path)], runs=2)
    writer = jm.JsonlWriter(path)  # the refused Logger left the file free again
    writer.close()
    jm.JsonlWriter(os.path.join(tmp_path, ".", "m.jsonl")).close()  # and after close


def test_jsonl_writer_ends_its_own_last_record_that_lost_only_its_newline(tmp_path):
    path = tmp_path / "m.jsonl"
    second = OWN_LINE.replace(b'"step":1', b'"step":2')
    for before in (b"", OWN_LINE):
        path.write_bytes(before + second[:-1])
        writer = jm.JsonlWriter(path)
        writer.write(jm.Record(3, 4.0, {"x": 0.5}, {}, {}))
        writer.close()
        lines = path.read_bytes().splitlines(keepends=True)
        assert lines[:-1] == [*([before] if before else []), second]
        assert json.loads(lines[-1])["step"] == 3


def test_a_second_jsonl_writer_through_a_hard_link_to_an_open_file_is_refused(tmp_path):
    path, link = tmp_path / "m.jsonl", tmp_path / "link.jsonl"
    writer = jm.JsonlWriter(path)
    os.link(path, link)
    with pytest.raises(ValueError, match=r"link.jsonl.*another JsonlWriter .* has it open"):
        jm.JsonlWriter(link)
    writer.write(jm.Record(1, 2.0, {}, {}, {}))
    writer.close()
    jm.JsonlWriter(link).close()  # free once closed
    # A purge that rewrites the file (a middle line dropped) keeps the writer's hold on it.
    path.write_bytes(b"".join(OWN_LINE.replace(b":1,", f":{s},".encode(), 1) for s in (0, 5, 1)))
    writer = jm.JsonlWriter(path, purge_step=3)
    with pytest.raises(ValueError, match=r"m.jsonl.*another JsonlWriter .* has it open"):
        jm.JsonlWriter(path)
    writer.close()
    assert [json.loads(line)["step"] for line in path.read_bytes().splitlines()] == [0, 1]
