"""Every Python block of the README and of the docs pages runs as pasted.

The pages are README.md and every docs/*.md but benchmarks.md (its figures come from the
benchmark, which has tests of its own). The `>>>` blocks run as doctests, each in a fresh
namespace, so that a block cannot lean on the imports of the one before it. The other blocks
(Brax, raw MJX, Playground, Brax's trainer, many devices) run as scripts in a fresh
interpreter with JAX's default settings, as a new user who pastes them into a file would run
them; their sizes are small enough to run as written.
"""

import doctest
import importlib.util
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing import event_accumulator

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
PAGES = [README] + sorted(p for p in (ROOT / "docs").glob("*.md") if p.name != "benchmarks.md")


def blocks(page: Path, language: str) -> list[tuple[str, int, str]]:
    """(page name, line of the opening fence, text) of every ```<language> block of a page."""
    text = page.read_text()
    return [
        (page.name, text.count("\n", 0, m.start()) + 1, m.group(1))
        for m in re.finditer(rf"^```{language}\n(.*?)^```$", text, re.M | re.S)
    ]


BLOCKS = [b for page in PAGES for b in blocks(page, "python")]
DOCTESTS = [b for b in BLOCKS if b[2].startswith(">>>")]
SCRIPTS = [b for b in BLOCKS if not b[2].startswith(">>>")]


def ids(blocks: list[tuple[str, int, str]]) -> list[str]:
    return [f"{page}:line{line}" for page, line, _ in blocks]


def test_every_python_block_is_a_doctest_or_a_script():
    for page in PAGES:
        # A fence the pattern misses (unclosed, or closed by a line that is not exactly ```)
        # would leave its block untested.
        assert len(blocks(page, "python")) == page.read_text().count("```python\n"), page.name
    assert DOCTESTS and SCRIPTS
    for page, line, block in SCRIPTS:
        assert ">>>" not in block, f"{page}:{line} mixes a script with doctest prompts"


def test_the_readme_test_command_is_what_ci_runs():
    # The README promises that its test command is CI's: .ci/run must run that exact line.
    demo, tests = [b.strip() for _, _, b in blocks(README, "bash")]
    ci = [line for line in (ROOT / ".ci" / "run").read_text().splitlines() if line.strip()]
    assert ci[-1] == tests
    assert tests == (
        'pip install -e ".[test]" && ruff check . && ruff format --check . && pyright && '
        "mkdocs build --strict && python -m pytest -q && .ci/floors && .ci/newest"
    )
    assert demo == 'pip install -e ".[train]" && python -m jaxmetrics.examples.ppo'
    assert "`python -m jaxmetrics.examples.brax_ppo`" in README.read_text()
    for module in ("ppo", "brax_ppo"):
        assert importlib.util.find_spec(f"jaxmetrics.examples.{module}") is not None, module


@pytest.mark.parametrize("page, line, block", DOCTESTS, ids=ids(DOCTESTS))
def test_doctest_block_runs_on_its_own(page, line, block):
    name = f"{page}:{line}"
    test = doctest.DocTestParser().get_doctest(block, {}, name, page, line)
    out = io.StringIO()
    runner = doctest.DocTestRunner()
    runner.run(test, out=out.write)
    assert runner.failures == 0, out.getvalue()
    assert runner.tries > 0


@pytest.mark.slow
@pytest.mark.parametrize("page, line, block", SCRIPTS, ids=ids(SCRIPTS))
def test_script_block_runs_as_pasted(page, line, block, tmp_path):
    script = tmp_path / "block.py"
    script.write_text(block)
    path = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    env = dict(
        os.environ,
        PYTHONPATH=path,
        JAX_PLATFORMS="cpu",
        # The suite's compilation cache (tests/conftest.py), for reruns.
        JAX_COMPILATION_CACHE_DIR=os.environ.get("JAXMETRICS_TEST_CACHE", str(ROOT / ".jax_cache")),
        JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="1",
    )
    out = subprocess.run(
        [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True
    )
    assert out.returncode == 0, f"{page}:{line}\n{out.stdout}\n{out.stderr}"
    if "quiet_upstream()" in block:
        # Its block keeps MuJoCo's warp lines and Brax's maintenance warning off the screen.
        assert "Failed to import" not in out.stdout
        assert "not actively being maintained" not in out.stderr
    if "ProgressFn" in block:
        acc = event_accumulator.EventAccumulator(str(tmp_path / "runs" / "brax_ppo" / "brax"))
        acc.Reload()
        tags = set(acc.Tags()["scalars"])
        assert {"Eval_Metrics/episode_return", "Train/value_loss", "Counters/env_steps"} <= tags
        # The reporting wrapper's records, every 256 env steps, from inside ppo.train.
        acc = event_accumulator.EventAccumulator(str(tmp_path / "runs" / "brax_ppo" / "metrics"))
        acc.Reload()
        counts = acc.Scalars("Episode_Metrics/return/count")
        assert [e.step for e in counts] == [256, 512, 768, 1024]
        assert all(e.value > 0 for e in counts)
        assert out.stdout.split() == ["4"]
    if "curriculum.main(" in block:
        # The example's records: the level per group and success per (group, level).
        acc = event_accumulator.EventAccumulator(str(tmp_path / "runs" / "curriculum"))
        acc.Reload()
        tags = set(acc.Tags()["scalars"])
        for group in ("jitter", "kick"):
            assert f"Episode_Metrics/level/{group}" in tags
            assert f"Episode_Metrics/success_rate/{group}_l0/window_mean" in tags


@pytest.mark.slow
def test_the_sharding_block_runs_on_jax_default_mesh_too(tmp_path):
    # `jax.make_mesh` without `axis_types=` makes Explicit axes; docs/devices.md says the
    # block runs either way, without `jax.set_mesh(mesh)`.
    (block,) = [b for _, _, b in SCRIPTS if "axis_types=(AxisType.Auto,)" in b]
    outputs = []
    for variant in (block, block.replace(", axis_types=(AxisType.Auto,)", "")):
        script = tmp_path / "block.py"
        script.write_text(variant)
        env = dict(
            os.environ,
            PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p),
            JAX_PLATFORMS="cpu",
            XLA_FLAGS="--xla_force_host_platform_device_count=4",
        )
        out = subprocess.run(
            [sys.executable, str(script)], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert out.returncode == 0, out.stderr
        outputs.append(out.stdout)
    assert outputs[0] == outputs[1]
    assert outputs[0].split()[-2:] == ["(4,", "2)"]  # 4 shards: the envs were split
