"""Every Python block of the README runs as pasted.

The `>>>` blocks run as doctests, each in a fresh namespace, so that a block cannot lean
on the imports of the one before it. The other blocks (Brax, raw MJX, Brax's trainer)
run as scripts in a fresh interpreter with JAX's default settings, as a new user who
pastes them into a file would run them; their sizes are small enough to run as written.
"""

import doctest
import io
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from tensorboard.backend.event_processing import event_accumulator

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"


def python_blocks() -> list[tuple[int, str]]:
    """(line of the opening fence, text) of every ```python block of the README."""
    text = README.read_text()
    return [
        (text.count("\n", 0, m.start()) + 1, m.group(1))
        for m in re.finditer(r"^```python\n(.*?)^```$", text, re.M | re.S)
    ]


BLOCKS = python_blocks()
DOCTESTS = [(line, b) for line, b in BLOCKS if b.startswith(">>>")]
SCRIPTS = [(line, b) for line, b in BLOCKS if not b.startswith(">>>")]


def test_every_python_block_is_a_doctest_or_a_script():
    assert len(BLOCKS) >= 6
    assert DOCTESTS and SCRIPTS
    for line, block in SCRIPTS:
        assert ">>>" not in block, f"README.md:{line} mixes a script with doctest prompts"


@pytest.mark.parametrize("line, block", DOCTESTS, ids=[f"line{n}" for n, _ in DOCTESTS])
def test_doctest_block_runs_on_its_own(line, block):
    test = doctest.DocTestParser().get_doctest(block, {}, f"README.md:{line}", str(README), line)
    out = io.StringIO()
    runner = doctest.DocTestRunner()
    runner.run(test, out=out.write)
    assert runner.failures == 0, out.getvalue()
    assert runner.tries > 0


@pytest.mark.slow
@pytest.mark.parametrize("line, block", SCRIPTS, ids=[f"line{n}" for n, _ in SCRIPTS])
def test_script_block_runs_as_pasted(line, block, tmp_path):
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
    assert out.returncode == 0, f"README.md:{line}\n{out.stdout}\n{out.stderr}"
    if "import jaxmetrics.brax" in block:
        # Imported before Brax, jaxmetrics.brax keeps MuJoCo's warp lines and Brax's
        # maintenance warning off the screen.
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


@pytest.mark.slow
def test_the_sharding_block_runs_on_jax_default_mesh_too(tmp_path):
    # `jax.make_mesh` without `axis_types=` makes Explicit axes; the block used to fail
    # there ("Resource axis: env ... is not found in mesh: ()") unless the user also
    # entered `jax.set_mesh(mesh)`, which the README never mentions.
    (block,) = [b for _, b in SCRIPTS if "axis_types=(AxisType.Auto,)" in b]
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
