"""Checkpoints of a host-mode run's whole carry (orbax-checkpoint), and the checks that let
only the run that wrote them resume from them."""

import os
from collections.abc import Sequence
from typing import Any

import jax

from ._algorithm import TrainState
from ._config import PPOConfig, config_values


class Checkpoints:
    """Orbax checkpoints of the stacked `TrainState`s of all seeds, at `directory/<step>`.

    A checkpoint also holds the run's config and seeds (JSON), which a resume must match.
    Saving is asynchronous (orbax's own thread); a checkpoint appears under its step only
    once complete, so a killed run leaves the previous one to resume from.
    """

    def __init__(self, directory: str, config: PPOConfig, seeds: Sequence[int]):
        import orbax.checkpoint as ocp  # the `train` extra; only runs that checkpoint need it

        self._ocp = ocp
        self.directory = os.path.abspath(directory)
        self._run = {"config": config_values(config), "seeds": list(seeds)}
        self._manager = ocp.CheckpointManager(
            self.directory, options=ocp.CheckpointManagerOptions(max_to_keep=2, create=True)
        )

    def save(self, step: int, state: TrainState) -> None:
        """Starts saving `state` as the checkpoint of `step` (returns before it is on disk)."""
        ocp = self._ocp
        self._manager.save(
            step,
            args=ocp.args.Composite(
                state=ocp.args.StandardSave(_without_empty(state)),
                run=ocp.args.JsonSave(self._run),
            ),
        )

    def newest(self) -> int:
        """The newest checkpoint's step, once its run's settings are checked."""
        ocp = self._ocp
        step = self._manager.latest_step()
        if step is None:
            raise ValueError(f"train(resume=True): no checkpoint in {self.directory!r}.")
        run = self._manager.restore(step, args=ocp.args.Composite(run=ocp.args.JsonRestore()))
        if run["run"] != self._run:
            saved, now = _flat_settings(run["run"]), _flat_settings(self._run)
            diff = {k: (saved.get(k), now.get(k)) for k in sorted(saved.keys() | now.keys())}
            shown = ", ".join(f"{k}: {a!r} then, {b!r} now" for k, (a, b) in diff.items() if a != b)
            raise ValueError(
                f"train(resume=True): the checkpoint {self.directory}/{step} is of a run with "
                f"other settings ({shown}). Resume with the same settings, or start a new run "
                "in another directory."
            )
        return step

    def restore(self, step: int, target: TrainState) -> TrainState:
        """The checkpoint of `step`, restored into arrays shaped and placed like `target`."""
        ocp = self._ocp
        restored = self._manager.restore(
            step,
            args=ocp.args.Composite(state=ocp.args.StandardRestore(_without_empty(target))),
        )["state"]
        # Zero-size leaves were not saved: they come from `target` (they hold no values).
        # Both sides are flattened with None as a leaf: the MetricsState's spec identity is
        # a None of its own, in both trees.
        leaves, treedef = jax.tree.flatten(target, is_leaf=lambda x: x is None)
        got = jax.tree.leaves(restored, is_leaf=lambda x: x is None)
        if len(got) != len(leaves):
            raise ValueError(f"the checkpoint {self.directory}/{step} does not match this run.")
        return jax.tree.unflatten(treedef, [t if g is None else g for t, g in zip(leaves, got)])

    def close(self) -> None:
        """Waits for the last save to finish."""
        self._manager.wait_until_finished()
        self._manager.close()


def _flat_settings(run: dict[str, Any]) -> dict[str, Any]:
    return {**run["config"], "seeds": run["seeds"]}


def _without_empty(state: TrainState) -> Any:
    """`state` with its zero-size arrays (MJX has some) as None: orbax refuses to save them."""
    return jax.tree.map(lambda x: None if x.size == 0 else x, state)
