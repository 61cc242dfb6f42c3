"""MLflow runs through `MlflowClient` (mlflow imported when the writer is created)."""

import threading
from collections.abc import Mapping, Sequence
from typing import Any

from .._core import _tags
from .._core._tags import TagInfo
from .._host._record import Record
from ._paths import check_hparams

# MLflow's limit on the metrics of one `log_batch` call.
_BATCH = 1000


def _check_str(value: Any, who: str, name: str) -> None:
    if value is not None and (not isinstance(value, str) or not value):
        raise TypeError(f"{who}: {name} must be a non-empty string, got {value!r}.")


def _params(hparams: Any, who: str) -> dict[str, str]:
    """The hparams as MLflow params (strings)."""
    checked = check_hparams(hparams, who, " (MLflow params)")
    return {k: str(v) for k, v in checked.items()}


def _check_tags(tags: Any, who: str) -> dict[str, str]:
    if tags is None:
        return {}
    if not isinstance(tags, Mapping) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in tags.items()
    ):
        raise TypeError(f"{who}: tags must be a dict of strings, got {tags!r}.")
    return dict(tags)


class _Parent:
    """The parent run of `MLflowWriter.per_seed`'s children: created with the first
    child, finished when the last child closes."""

    def __init__(
        self,
        client: Any,
        experiment_id: str,
        run_name: str,
        params: dict[str, str],
        tags: dict[str, str],
    ):
        self._client, self._experiment_id = client, experiment_id
        self._run_name, self._params, self._tags = run_name, params, tags
        self._lock = threading.Lock()
        self._open = 0
        self.run_id: str | None = None

    def acquire(self) -> str:
        with self._lock:
            if self.run_id is None:
                run = self._client.create_run(
                    self._experiment_id, run_name=self._run_name, tags=self._tags
                )
                self.run_id = run.info.run_id
                assert self.run_id is not None  # a created run has its id
                _log_params(self._client, self.run_id, self._params)
            self._open += 1
            return self.run_id

    def release(self) -> None:
        with self._lock:
            self._open -= 1
            if self._open == 0 and self.run_id is not None:
                self._client.set_terminated(self.run_id)


def _log_params(client: Any, run_id: str, params: dict[str, str]) -> None:
    from mlflow.entities import Param

    if params:
        client.log_batch(run_id, params=[Param(k, v) for k, v in params.items()])


class MLflowWriter:
    """Writes one MLflow run.

    What it writes, per record (`MlflowClient.log_batch`): every scalar of the record as
    a metric at `step=record.step` and `timestamp=record.wall_time`, under its tag
    (TensorBoard-sanitized, which MLflow accepts; the spec already rejects tags that
    would collide). Empty statistics are not in a record, so nothing is logged as a fake
    0. MLflow stores metric values as float64: counters past 2^53 show rounded there
    (they are exact in `JsonlWriter`, `MemoryWriter` and `WandbWriter`). MLflow has no
    histogram type: histograms and window contents are left out (their statistics and
    under/overflow counts are scalars and are written).

    `hparams` become the run's params; `tags` its tags. The run is created in `open`
    (when the `Logger` starts, or at a `ProgressFn`'s first call) and set FINISHED in
    `close`. For `Logger(runs=N)` (vmapped seeds), `per_seed` makes each seed a child
    run of one parent run, which is how MLflow's UI groups runs.

    Args:
      experiment: the experiment's name; created if missing.
      run_name: the run's name (MLflow makes one up when None).
      tracking_uri: where runs go, e.g. `"sqlite:///mlflow.db"` or `"http://host:5000"`;
        None: MLflow's default (`MLFLOW_TRACKING_URI`, or the local SQLite store
        `mlflow.db` in the working directory). The store is reached here, so a bad URI
        fails before training.
      parent_run_id: make this run a child of that run (`mlflow.parentRunId`).
      hparams: hyperparameters (name -> bool/int/float/str), the run's params.
      tags: run tags (name -> str).

    Raises:
      TypeError: arguments of the wrong type.
      ValueError: a tracking store that cannot be reached or written.

    Examples:
      One child run per seed under one parent::

          logger = jm.Logger(metrics, jm.MLflowWriter.per_seed("ppo", run_name="ant"),
                             runs=4)
    """

    def __init__(
        self,
        experiment: str = "jaxmetrics",
        *,
        run_name: str | None = None,
        tracking_uri: str | None = None,
        parent_run_id: str | None = None,
        hparams: Mapping[str, bool | int | float | str] | None = None,
        tags: Mapping[str, str] | None = None,
    ):
        who = "MLflowWriter"
        for name, value in (
            ("experiment", experiment),
            ("run_name", run_name),
            ("tracking_uri", tracking_uri),
            ("parent_run_id", parent_run_id),
        ):
            _check_str(value, who, name)
        if experiment is None:
            raise TypeError(f"{who}: experiment must be a non-empty string, got None.")
        self._params = _params(hparams, who)
        tags = _check_tags(tags, who)
        self.client, self.experiment_id = _experiment(experiment, tracking_uri, who)
        self._run_name = run_name
        self._tags = tags
        self._parent_run_id = parent_run_id
        self._parent: _Parent | None = None  # set by per_seed
        self._into_parent = False  # per_seed's summary writer: logs into the parent run
        self.run_id: str | None = None

    @staticmethod
    def per_seed(
        experiment: str = "jaxmetrics",
        *,
        run_name: str = "run",
        tracking_uri: str | None = None,
        hparams: Mapping[str, bool | int | float | str] | None = None,
        tags: Mapping[str, str] | None = None,
    ) -> "MLflowSeeds":
        """A `Logger(..., runs=N)` writer factory: one parent run `run_name` and, for run
        i, a child run `<run_name>/seed_<i>`; each has the hparams as params and the tags.
        Its `seeds_summary()` is a writer into the parent run, for the cross-seed summary.

        The parent is created with the first child's (or the summary's) run and finished
        when the last of them closes. Arguments as for `MLflowWriter`.
        """
        who = "MLflowWriter.per_seed"
        _check_str(run_name, who, "run_name")
        params = _params(hparams, who)
        parent_tags = _check_tags(tags, who)
        client, experiment_id = _experiment(experiment, tracking_uri, who)
        parent = _Parent(client, experiment_id, run_name, params, parent_tags)
        return MLflowSeeds(parent, experiment, run_name, tracking_uri, hparams, tags)

    def open(self, tags: Sequence[TagInfo]) -> None:
        """Creates the run and logs its params (the summary writer of `per_seed` logs
        into the parent run)."""
        if self._into_parent and self._parent is not None:
            self.run_id = self._parent.acquire()
            return
        run_tags = dict(self._tags)
        parent = self._parent.acquire() if self._parent is not None else self._parent_run_id
        if parent is not None:
            run_tags["mlflow.parentRunId"] = parent
        run = self.client.create_run(self.experiment_id, run_name=self._run_name, tags=run_tags)
        self.run_id = run.info.run_id
        assert self.run_id is not None  # a created run has its id
        _log_params(self.client, self.run_id, self._params)

    def write(self, record: Record) -> None:
        """Logs the record's scalars at `record.step`."""
        from mlflow.entities import Metric

        ms = int(record.wall_time * 1000)
        metrics = [
            Metric(_tags.sanitize(tag), float(v), ms, record.step)
            for tag, v in record.scalars.items()
        ]
        refused: list[str] = []
        for i in range(0, len(metrics), _BATCH):
            batch = metrics[i : i + _BATCH]
            try:
                self.client.log_batch(self.run_id, metrics=batch)
            except Exception:  # noqa: BLE001 (one refused key fails its whole batch)
                refused += self._log_one_by_one(batch)
        if refused:
            raise ValueError(
                f"MLflow refused {len(refused)} of the {len(metrics)} metrics of the record at "
                f"step {record.step} (the others are logged): " + "; ".join(refused)
            )

    def _log_one_by_one(self, batch: Sequence[Any]) -> list[str]:
        """Logs a refused batch metric by metric, so that one bad key (or value) loses
        only itself; returns what was refused, and why."""
        refused = []
        for metric in batch:
            try:
                self.client.log_batch(self.run_id, metrics=[metric])
            except Exception as e:  # noqa: BLE001 (named in the writer's error)
                refused.append(f"{metric.key!r}: {e}")
        return refused

    def close(self) -> None:
        """Sets the run FINISHED (if created); with `per_seed`, the parent too once every
        seed's run is."""
        if self.run_id is None:
            return
        if not self._into_parent:
            self.client.set_terminated(self.run_id)
        if self._parent is not None:
            self._parent.release()


class MLflowSeeds:
    """`MLflowWriter.per_seed`'s factory: `factory(run)` is run `run`'s writers (a child
    run of the shared parent)."""

    def __init__(
        self,
        parent: _Parent,
        experiment: str,
        run_name: str,
        tracking_uri: str | None,
        hparams: Mapping[str, bool | int | float | str] | None,
        tags: Mapping[str, str] | None,
    ):
        self._parent, self._experiment, self._run_name = parent, experiment, run_name
        self._tracking_uri, self._hparams, self._tags = tracking_uri, hparams, tags

    def __call__(self, run: int) -> list[MLflowWriter]:
        return [self._writer(f"{self._run_name}/seed_{run}")]

    def seeds_summary(self) -> list[MLflowWriter]:
        """The writers of the cross-seed summary (`Logger(seeds_summary=...)`): metrics
        logged into the parent run, which MLflow's UI shows above its seeds."""
        writer = self._writer(self._run_name)
        writer._into_parent = True
        return [writer]

    def _writer(self, run_name: str) -> MLflowWriter:
        writer = MLflowWriter(
            self._experiment,
            run_name=run_name,
            tracking_uri=self._tracking_uri,
            hparams=self._hparams,
            tags=self._tags,
        )
        writer._parent = self._parent
        return writer


def _experiment(name: str, tracking_uri: str | None, who: str) -> tuple[Any, str]:
    """The client and the id of experiment `name` (created if missing)."""
    from mlflow.tracking import MlflowClient

    try:
        client = MlflowClient(tracking_uri)
        found = client.get_experiment_by_name(name)
        return client, found.experiment_id if found else client.create_experiment(name)
    except Exception as e:  # noqa: BLE001 (MLflow's, SQLAlchemy's or the OS's, all re-raised)
        raise ValueError(
            f"{who}: cannot use the MLflow tracking store {tracking_uri!r}: "
            f"{type(e).__name__}: {e}. Pass a reachable, writable tracking_uri (e.g. "
            "'sqlite:///mlflow.db')."
        ) from e
