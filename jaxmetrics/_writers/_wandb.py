"""Weights & Biases runs through `wandb` (imported when the writer is created)."""

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from .._core._tags import TagInfo
from .._core._validate import is_int
from .._host._record import Record
from ._paths import writable_dir

# `wandb.Histogram` refuses more bins than this (`wandb.sdk.data_types.histogram`).
MAX_BINS = 512
_MODES = ("online", "offline", "disabled", "shared")


def _check_str(value: Any, name: str) -> None:
    if value is not None and (not isinstance(value, str) or not value):
        raise TypeError(f"WandbWriter: {name} must be a non-empty string, got {value!r}.")


def _coarsen(counts: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(counts, edges)` in at most `MAX_BINS` bins: runs of `ceil(bins / MAX_BINS)`
    adjacent bins summed (the last run may be shorter), on a subset of the same edges."""
    k = -(-counts.size // MAX_BINS)
    if k == 1:
        return counts, edges
    return np.add.reduceat(counts, np.arange(0, counts.size, k)), edges[
        np.r_[np.arange(0, counts.size, k), counts.size]
    ]


class WandbWriter:
    """Writes one Weights & Biases run.

    What it writes, per record (one `run.log(..., step=record.step)`):

    - every scalar of the record under its tag (W&B groups the charts by the tag's first
      part: `Episode_Metrics`, `Train`, `Counters`, ...). Empty statistics are not in a
      record, so nothing is logged as a fake 0. Counts and counters are logged as Python
      ints: W&B keeps them exact, in the history and in the run summary (its last value);
    - `<metric>/histogram`: a `wandb.Histogram` of the statistic's in-range bins with the
      spec's edges (`np_histogram=(counts, edges)`). W&B keeps at most 512 bins: a
      histogram with more is written with runs of `ceil(bins / 512)` adjacent bins summed,
      on every `ceil(bins / 512)`-th edge (the exact bins are in `JsonlWriter`'s lines).
      Under/overflow counts are the scalars `<metric>/histogram/underflow|overflow`;
    - `<metric>/window_values`: a `window_bins`-bin `wandb.Histogram` of the window
      contents.

    `hparams` become the run config. One writer is one run: for `Logger(runs=N)` (vmapped
    seeds) give each seed its own writer in the same `group`, which `per_seed` builds; the
    W&B UI then draws the group's mean and band, never one merged run.

    The run starts in `open` (when the `Logger` starts, or at a `ProgressFn`'s first
    call) and finishes in `close`; W&B's service process then writes (or uploads) the
    rest in the background, and waits for it at interpreter exit. To read an offline
    run's files in the same process, call `wandb.teardown()` first. `record.step` must
    grow from record to record, as W&B requires (it drops rows with a smaller step, with
    a warning); records with equal steps are merged into one row. W&B stamps rows with
    its own clock, not `record.wall_time`.

    Args:
      project: the W&B project.
      name: the run's display name (W&B makes one up when None).
      group: the run group (e.g. the experiment, with one run per seed).
      hparams: hyperparameters, the run's config (name -> JSON-able value).
      mode: "online", "offline" (written under `dir`, uploaded later with
        `wandb sync`), "disabled" or "shared"; None: W&B's default (`WANDB_MODE`, or
        online).
      dir: directory of W&B's local files; created if missing and checked here.
      window_bins: bins of the window-contents histograms, at most 512.
      init_kwargs: further arguments of `wandb.init` (`entity`, `tags`, `notes`,
        `job_type`, `id`, `resume`, `settings`, ...), which checks them.

    Raises:
      ValueError: bad `mode`, `dir`, `window_bins`, or `init_kwargs` that repeat an
        argument above.
      TypeError: arguments of the wrong type.

    Examples:
      One run per seed, grouped::

          logger = jm.Logger(metrics, jm.WandbWriter.per_seed("my-project", group="ppo"),
                             runs=4)
    """

    def __init__(
        self,
        project: str,
        *,
        name: str | None = None,
        group: str | None = None,
        hparams: Mapping[str, Any] | None = None,
        mode: str | None = None,
        dir: str | os.PathLike | None = None,  # noqa: A002 (wandb.init's name)
        window_bins: int = 30,
        init_kwargs: Mapping[str, Any] | None = None,
    ):
        for arg, value in (("project", project), ("name", name), ("group", group)):
            _check_str(value, arg)
        if project is None:
            raise TypeError("WandbWriter: project must be a non-empty string, got None.")
        if mode is not None and mode not in _MODES:
            raise ValueError(f"WandbWriter: mode must be one of {_MODES} or None, got {mode!r}.")
        if not is_int(window_bins) or not 1 <= window_bins <= MAX_BINS:
            raise ValueError(
                f"WandbWriter: window_bins must be an int in [1, {MAX_BINS}] (W&B's limit), "
                f"got {window_bins!r}."
            )
        if hparams is not None and (
            not isinstance(hparams, Mapping) or not all(isinstance(k, str) for k in hparams)
        ):
            raise TypeError(
                f"WandbWriter: hparams must be a dict with string keys, got {hparams!r}."
            )
        if init_kwargs is not None and not isinstance(init_kwargs, Mapping):
            raise TypeError(f"WandbWriter: init_kwargs must be a dict, got {init_kwargs!r}.")
        kwargs = dict(init_kwargs or {})
        own = {"project", "name", "group", "config", "mode", "dir", "reinit"} & set(kwargs)
        if own:
            raise ValueError(
                f"WandbWriter: pass {sorted(own)} as WandbWriter's own arguments (config is "
                "hparams), not in init_kwargs."
            )
        if dir is not None:
            dir = writable_dir(dir, "WandbWriter", "dir")  # noqa: A001
        import wandb

        self._wandb = wandb
        # Several runs live side by side in one process (one per seed).
        self._init = dict(
            kwargs,
            project=project,
            name=name,
            group=group,
            config=None if hparams is None else dict(hparams),
            mode=mode,
            dir=dir,
            reinit="create_new",
        )
        self._bins = window_bins
        self.run: Any = None

    @staticmethod
    def per_seed(
        project: str, *, group: str, name: str | None = None, **kwargs: Any
    ) -> "WandbSeeds":
        """A `Logger(..., runs=N)` writer factory: run i writes the W&B run
        `<name or group>/seed_<i>` in `group`; its `seeds_summary()` is the writer of the
        cross-seed summary run `<name or group>/seeds_summary` in the same group.

        Args:
          project: the W&B project.
          group: the group of the seeds' runs (required: it is what keeps them apart and
            together).
          name: the runs' name stem (default: `group`).
          **kwargs: the other arguments of `WandbWriter` (`hparams`, `mode`, `dir`, ...).
        """
        _check_str(group, "group")
        if group is None:
            raise TypeError("WandbWriter.per_seed: group must be a non-empty string.")
        return WandbSeeds(project, group, group if name is None else name, kwargs)

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Starts the W&B run."""
        self.run = self._wandb.init(**self._init)

    def write(self, record: Record) -> None:
        """Logs the record as one row at `record.step`."""
        Histogram = self._wandb.Histogram
        row: dict[str, Any] = dict(record.scalars)
        for tag, h in record.histograms.items():
            row[tag] = Histogram(np_histogram=_coarsen(h.counts, h.edges))
        for tag, w in record.windows.items():
            row[tag] = Histogram(np_histogram=np.histogram(w, bins=self._bins))
        self.run.log(row, step=record.step)

    def close(self) -> None:
        """Finishes the run (if started)."""
        if self.run is not None:
            self.run.finish()


class WandbSeeds:
    """`WandbWriter.per_seed`'s factory: `factory(run)` is run `run`'s writers."""

    def __init__(self, project: str, group: str, stem: str, kwargs: Mapping[str, Any]):
        self._project, self._group, self._stem, self._kwargs = project, group, stem, kwargs

    def __call__(self, run: int) -> list[WandbWriter]:
        return [self._writer(f"seed_{run}")]

    def seeds_summary(self) -> list[WandbWriter]:
        """The writers of the cross-seed summary run (`Logger(seeds_summary=...)`): the
        W&B run `<stem>/seeds_summary` in the seeds' group. Its mean across seeds has
        the seeds' own tags, so W&B draws it in their charts; as one more run of the
        group it leaves the group's mean and min/max band unchanged."""
        return [self._writer("seeds_summary")]

    def _writer(self, suffix: str) -> WandbWriter:
        return WandbWriter(
            self._project, name=f"{self._stem}/{suffix}", group=self._group, **self._kwargs
        )
