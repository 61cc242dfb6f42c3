"""The package's layout: one owner per concept, and layers that import only downwards;
the tests in one folder per layer.

The layers are folders: `_core` (the spec, the state and its in-graph functions, tags,
registries) <- `_host` (report -> Record, the logger) <- `_writers` <- integrations
(`brax` <- `playground`, which builds on it) <- `examples`. The registries of statistics and
reductions are the only lists of their names; the in-graph modules that use the names
(`_stream`, `_episode`) are checked against them here.
"""

import ast
import subprocess
import sys
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

import jaxmetrics as jm
import jaxmetrics.brax as jmb
from jaxmetrics._core import _episode, _reductions, _spec, _statistics, _stream, _tags

PACKAGE = Path(jm.__file__).resolve().parent

# The layer folders from the bottom up; the package's `__init__` re-exports the first three.
LAYERS = ["_core", "_host", "_writers", "__init__", "brax", "playground", "examples"]
# Layers whose modules are checked one by one (a module there is a unit, e.g. `_core/_spec`).
SPLIT = {"_core", "_host"}
# What a writer sees (TagInfo, Record, the registries) must not pull in JAX.
PURE = {"_core/_reductions", "_host/_record", "_core/_spec", "_core/_statistics"}
PURE |= {"_core/_tags", "_core/_validate", "_writers"}


def unit(parts: list[str] | tuple[str, ...]) -> str:
    """The unit a module path belongs to: `_core/_spec` in the split layers, else its folder."""
    if parts and parts[0] in SPLIT:
        return "/".join(parts[:2]) if len(parts) > 1 else parts[0]
    return parts[0] if parts else "__init__"


def layer(name: str) -> int:
    return LAYERS.index(name.split("/")[0])


def imports(path: Path) -> tuple[set[str], set[str]]:
    """(jaxmetrics units, other top-level packages) that `path` imports."""
    rel = path.relative_to(PACKAGE).with_suffix("").parts
    ours, others = set(), set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "jaxmetrics":
                    ours.add(unit(parts[1:]))
                else:
                    others.add(parts[0])
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                parts = (node.module or "").split(".")
                if parts[0] != "jaxmetrics":
                    others.add(parts[0])
                    continue
                target = parts[1:]
            else:
                target = [*rel[: len(rel) - node.level], *(node.module or "").split(".")]
                target = [t for t in target if t]
            if target in ([], *([s] for s in SPLIT)):  # `from .. import x`: each x a module
                for a in node.names:
                    name = unit([*target, a.name])
                    ours.add(
                        name
                        if (PACKAGE / name).exists() or name.split("/")[0] in SPLIT
                        else "__init__"
                    )
            else:
                ours.add(unit(target))
    return ours, others


MODULES = sorted(p for p in PACKAGE.rglob("*.py"))


def test_every_module_is_in_a_layer_folder():
    flat = [p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py"]
    assert not flat, f"modules outside the layer folders: {flat}"
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(LAYERS) - {"__init__"}


@pytest.mark.parametrize("path", MODULES, ids=[str(p.relative_to(PACKAGE)) for p in MODULES])
def test_modules_import_only_their_layer_or_below(path):
    rel = path.relative_to(PACKAGE).with_suffix("").parts
    own = unit(rel)
    ours, others = imports(path)
    for dep in ours - {own}:
        assert layer(dep) <= layer(own), f"{'/'.join(rel)} (layer {layer(own)}) imports {dep}"
    if own in PURE:
        assert ours - {own} <= PURE, f"{'/'.join(rel)} imports the JAX core: {ours - PURE}"
        assert "jax" not in others, f"{'/'.join(rel)} imports jax"
    # The benchmarks are no part of the installed package.
    assert "benchmarks" not in others, f"{'/'.join(rel)} imports the benchmarks"


def test_no_module_imports_itself_through_others():
    # A circle (even one through a TYPE_CHECKING import) means two modules share one
    # concept: each should own its part.
    graph: dict[str, set[str]] = {}
    for path in MODULES:
        own = unit(path.relative_to(PACKAGE).with_suffix("").parts)
        graph.setdefault(own, set()).update(imports(path)[0] - {own})

    def circle(node: str, trail: list[str]) -> list[str] | None:
        if node in trail:
            return trail[trail.index(node) :] + [node]
        for dep in sorted(graph.get(node, ())):
            found = circle(dep, [*trail, node])
            if found:
                return found
        return None

    for own in sorted(graph):
        found = circle(own, [])
        assert found is None, " -> ".join(found)


TESTS = PACKAGE.parent / "tests"
# The test folders, each with the package layers its tests pin, from the bottom up; a test
# imports no module of a layer above its folder's. `import jaxmetrics` (the public names)
# is allowed everywhere. Of the benchmarks (top-level `benchmarks/`, not installed), the
# tests of the benchmarks (`examples`) import anything, the others only the HLO inspection
# that the tests share with them.
TEST_FOLDERS = {"core": 0, "host": 1, "writers": 2, "integrations": 5, "examples": 6, "docs": 6}
SHARED_WITH_TESTS = {"benchmarks._hlo"}


def test_tests_are_in_folders_by_layer_and_import_nothing_above_it():
    assert {p.name for p in TESTS.iterdir() if p.is_dir() and p.name != "__pycache__"} == set(
        TEST_FOLDERS
    )
    assert not [p.name for p in TESTS.glob("test_*.py") if p.name != "test_layering.py"]
    for folder, top in TEST_FOLDERS.items():
        for path in (TESTS / folder).glob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [f"{node.module}.{a.name}" for a in node.names]
                for name in names:
                    parts = name.split(".")
                    if parts[0] == "benchmarks" and folder != "examples":
                        shared = ".".join(parts[:2]) in SHARED_WITH_TESTS
                        assert shared, f"tests/{folder}/{path.name} imports {name}"
                    if parts[0] != "jaxmetrics" or len(parts) < 2:
                        continue
                    if parts[1] in LAYERS:
                        assert layer(parts[1]) <= top, f"tests/{folder}/{path.name} imports {name}"


def test_progress_fn_builds_records_without_the_jax_core():
    ours, _ = imports(PACKAGE / "brax" / "_progress.py")
    assert ours <= PURE, ours - PURE


def test_old_module_names_are_gone():
    for gone in ("_flush.py", "_step.py", "_writers/_record.py", "_reporting.py", "_emitted.py"):
        assert not (PACKAGE / gone).exists(), gone
    # The fused GPU kernel (Pallas, Triton) and what only it needed: retired.
    for gone in ("_kernel", "_program", "_layout", "_reached", "_chunks"):
        assert not (PACKAGE / "_core" / "_stream" / f"{gone}.py").exists(), gone


def every_stat_metrics() -> jm.Metrics:
    stats = (*_statistics.SIMPLE_STATS, jm.ema(0.5), jm.window(3, (10, 99.9)))
    stats += (jm.histogram(2, (0.0, 1.0)), jm.quantiles((50, 99.9)))
    return jm.Metrics(
        terms={"r": jm.Term(lambda x: x, stats=stats)},
        logged={"loss": jm.Logged(stats=stats)},
        counters=["updates"],
    )


def test_the_stream_computes_exactly_the_statistics_the_registry_reports():
    metrics = every_stat_metrics()
    spec = metrics.metric_specs["loss"]
    plan = _stream.StreamPlan.build([spec], jnp.float32)
    columns = _stream.compute(plan, _stream.init(plan))
    assert sorted(name for name, rows, _ in columns if 0 in rows) == sorted(
        _spec.reported(spec.stats)
    )


def test_every_tag_is_its_metric_tag_plus_the_registry_suffix():
    metrics = every_stat_metrics()
    with jm.Logger(metrics, [], include_running=True) as logger:
        tags = logger.tags
    stats = {i.stat for i in tags}
    assert {"total", "per_sec", "running", "window_p10", "window_p99.9", "q50", "q99.9"} <= stats
    assert "histogram/underflow" in stats
    prefixes = {"episode": "Episode_Metrics", "logged": "Train", "counter": "Counters"}
    for i in tags:
        assert i.tag == _tags.tag(prefixes[i.group], i.metric, i.stat)
        assert _tags.metric_tag(i) == f"{prefixes[i.group]}/{i.metric}"
    counters = [i for i in tags if i.group == "counter"]
    assert {i.stat for i in counters} == {"total", "per_sec"}


def test_console_columns_and_simple_stats_come_from_the_registry():
    assert _statistics.COLUMNS == ("mean", "std", "min", "max", "count")
    assert _statistics.SIMPLE_STATS == ("mean", "std", "min", "max", "sum", "count")
    with pytest.raises(KeyError, match="'median' is not a jaxmetrics statistic"):
        _statistics.get("median")
    with pytest.raises(KeyError, match="'quality' is not a jaxmetrics statistic"):
        _statistics.get("quality")  # a family member is its prefix and a number
    assert _statistics.get("q99.9").suffix == "/q99.9"


def test_reductions_registry_matches_the_episode_blocks_and_the_helpers():
    assert sorted(_reductions.NAMES) == sorted(_episode.ORDER)
    built = {"discounted": jm.discounted(0.9)}  # the reductions that take a parameter
    assert set(built) == {r.name for r in _reductions.REDUCTIONS if r.builder is not None}
    for r in _reductions.NAMES:
        jm.Metrics(terms={"x": jm.Term(lambda s: s, reduce=built.get(r, r))})
        assert _reductions.name(built.get(r, r)) == r
    flags = [r for r in _reductions.NAMES if r in _reductions.FLAG_REDUCTIONS]
    assert flags == ["mean", "max", "min", "last"]
    for r in _reductions.NAMES:
        if r in flags:
            assert jmb.success_rate(lambda t: t.done, reduce=r).reduce == r
        else:
            with pytest.raises(ValueError, match=r"'last' \(at episode end\)"):
                jmb.success_rate(lambda t: t.done, reduce=r)


def test_validation_helper_refuses_bools_and_accepts_numpy_ints():
    from jaxmetrics._core._validate import is_int, is_number

    assert [is_int(v) for v in (3, np.int64(3), True, 3.0, "3")] == [1, 1, 0, 0, 0]
    assert [is_number(v) for v in (3, 2.5, np.float32(2.5), False, None)] == [1, 1, 1, 0, 0]
    assert jm.window(np.int64(4)).size == 4 and type(jm.window(np.int64(4)).size) is int
    with pytest.raises(ValueError, match="window size must be a positive int"):
        jm.window(True)


def test_one_public_name_per_concept_and_no_plumbing():
    # A builder and its return type were both exported (`ema` and `Ema`, ...): one name per
    # concept, as optax exports `adam` and not the state it builds.
    import jaxmetrics.playground as jmp

    for module in (jm, jmb, jmp):
        names = list(module.__all__)
        assert sorted(names) == sorted(n for n in vars(module) if n in names)
        lower = [n.lower() for n in names]
        assert len(set(lower)) == len(lower), sorted(n for n in names if lower.count(n.lower()) > 1)
    assert not {"STATE_KEY", "norm"} & (set(jmb.__all__) | set(jmp.__all__))


def test_importing_jaxmetrics_imports_no_pallas_backend_and_warns_of_nothing():
    """No GPU backend of Pallas is imported (JAX deprecates the Triton one and will remove
    it: an import of it would make `import jaxmetrics` fail), and importing warns of
    nothing, on whatever JAX the suite runs (CI runs the newest too)."""
    probe = (
        "import sys, jax; jax_own = set(sys.modules); import jaxmetrics; "
        "print(sorted(m for m in set(sys.modules) - jax_own if 'pallas' in m or 'triton' in m))"
    )
    out = subprocess.run(
        [sys.executable, "-W", "error", "-c", probe],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=PACKAGE.parent,
    )
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"
