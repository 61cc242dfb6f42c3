"""Strict JAX for the whole suite: implicit rank/dtype promotion over the env axis is the
bug class these settings catch. Eight CPU devices make the sharding tests real (meshes of 2, 4 and 8)."""

import os
import subprocess
import sys

# The suite is compile-bound and its programs are small: LLVM's optimization passes cost
# more compile time than they save at run time, and XLA:CPU's older elemental emitters
# compile the suite's programs about a third faster than its MLIR fusion emitters (a Brax
# SAC training and an MJX rollout 49 -> 38 s: commit aa0c47b). HLO-level
# fusion, which the op-count and collective tests read, is not affected. Subprocesses
# (scripts, notebooks, xdist's workers) inherit the flags.
FAST_COMPILE_FLAGS = (
    "--xla_backend_optimization_level=0",
    "--xla_llvm_disable_expensive_passes=true",
    # Gone from XLA in JAX 0.12 (the emitters it chose between are gone too).
    "--xla_cpu_use_fusion_emitters=false",
)
_PROBED = "JAXMETRICS_TEST_XLA_FLAGS_PROBED"


def _xla_accepts(flags: list[str]) -> bool:
    """Whether this Python's XLA starts with `flags`: XLA ends the process on a flag it
    does not know (a fatal log, not an exception), so each probe is a process of its own."""
    env = {**os.environ, "XLA_FLAGS": " ".join(flags), "JAX_PLATFORMS": "cpu"}
    probe = [sys.executable, "-c", "import jax; jax.devices()"]
    return subprocess.run(probe, env=env, capture_output=True).returncode == 0


def _known_flags(flags: tuple[str, ...]) -> list[str]:
    """The flags of `flags` this process's XLA knows (one probe for all, one each if that
    fails)."""
    if _xla_accepts(list(flags)):
        return list(flags)
    return [flag for flag in flags if _xla_accepts([flag])]


if _PROBED not in os.environ:  # xdist's workers inherit the controller's result
    os.environ["XLA_FLAGS"] = " ".join(
        filter(None, (os.environ.get("XLA_FLAGS"), *_known_flags(FAST_COMPILE_FLAGS)))
    )
    os.environ[_PROBED] = "1"

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")
# Compiles of Brax/MJX rollouts dominate the suite; a persistent cache makes reruns cheap.
jax.config.update(
    "jax_compilation_cache_dir",
    os.environ.get(
        "JAXMETRICS_TEST_CACHE", os.path.join(os.path.dirname(__file__), "..", ".jax_cache")
    ),
)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)


@pytest.fixture
def env_sharded() -> jax.sharding.NamedSharding:
    """The env axis split over 2 CPU devices (an Auto mesh axis "env")."""
    mesh = jax.make_mesh(
        (2,), ("env",), axis_types=(jax.sharding.AxisType.Auto,), devices=jax.devices("cpu")[:2]
    )
    return jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("env"))


@pytest.fixture
def brax_ppo_on_this_jax(monkeypatch):
    """Brax 0.14.2's ppo.train calls jax.device_put_replicated, which JAX 0.10 removed from
    the public namespace (the function is still in jax._src.api): the name is restored for
    the test only, so that Brax's real trainer runs."""
    import jax._src.api

    monkeypatch.setattr(
        jax, "device_put_replicated", jax._src.api.device_put_replicated, raising=False
    )


def _shared_module_fixtures(item: pytest.Item) -> list[str]:
    info = getattr(item, "_fixtureinfo", None)  # doctest items have none
    if info is None:
        return []
    return [
        f"{item.path.stem}.{name}"
        for name, defs in info.name2fixturedefs.items()
        if defs and defs[-1].scope == "module"
    ]


@pytest.hookimpl(tryfirst=True)  # before xdist reads the xdist_group marks
def pytest_collection_modifyitems(items):
    # Tests that share a module-scoped fixture (a notebook run, the benchmark, a trained
    # policy) go to one xdist worker as one group (--dist loadgroup): split over the two
    # workers, each would build the fixture. A group is every test linked through such
    # fixtures; every other test is scheduled on its own.
    root: dict[str, str] = {}

    def find(key: str) -> str:
        while root.setdefault(key, key) != key:
            key = root[key]
        return key

    for item in items:
        keys = _shared_module_fixtures(item)
        for key in keys[1:]:
            root[find(key)] = find(keys[0])
    for item in items:
        if keys := _shared_module_fixtures(item):
            item.add_marker(pytest.mark.xdist_group(find(keys[0])))
    # The slow tests (Brax trainings and rollouts, notebooks, subprocesses) first: the first
    # worker takes them from the front, the others take the short tests from the back.
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """--dist loadgroup, a test (or group) at a time in collection order
    (--no-loadscope-reorder), the first worker from the front of the queue and the others
    from its back: two slow tests at once run about half as fast each as beside short
    ones, so one worker runs the slow tests while the other runs the short ones, until
    they meet."""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadGroupScheduling

    class FromBothEnds(LoadGroupScheduling):
        def _assign_work_unit(self, node):
            if node is not self.nodes[0]:
                self.workqueue.move_to_end(next(reversed(self.workqueue)), last=False)
            super()._assign_work_unit(node)

    return FromBothEnds(config, log)
