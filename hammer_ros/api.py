"""The Python API (``import hammer_ros``): read a record, identify a Hammerstein model, diagnose it.

    record = hammer_ros.read("run.csv")                  # or .npz, .mcap, a rosbag2 directory; a list: runs
    model = hammer_ros.identify(record.u, record.y, order=3, delay=1)
    model.poles, model.gain, model.nonlinearity(0.5), model.simulate(record.u)
    model.to_dict()                                      # exactly ``hammer-ros identify --json``
    diagnosis = hammer_ros.diagnose(record.u, record.y, split=0.7)
    diagnosis.cause, diagnosis.to_dict()                 # exactly ``hammer-ros diagnose --json``

The command line is a layer over these functions (``cli.cmd_identify`` calls ``identify``). May import
``identification``, ``io`` and ``diagnosis``; never rclpy (matplotlib only inside ``Model.plot``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from .errors import UsageError
from .identification.methods import IdentifyOptions
from .identification.methods import identify as identify_with
from .identification.result import IdentificationResult
from .identification.runs import Runs, several
from .identification.trust import ModelWarning
from .io.records import Record

__all__ = ["Diagnosis", "Model", "Record", "diagnose", "identify", "read", "split_records"]

CONFIDENCE_SDS = 1.96  # half-width of the plotted 95 % regions, in standard deviations
OPTION_NAMES = tuple(f for f in IdentifyOptions.__dataclass_fields__ if f not in ("order", "delay", "runs"))


def read(path: str | Path | Sequence[str | Path], *, input: str | None = None, output: str | None = None,
         config: str | Path | None = None, reference: str | None = None) -> Record:
    """The record in a CSV or NPZ file (columns ``input``/``output``, default u and y; a ``t`` column:
    time stamps; a ``run`` column: run labels) or a bag (.mcap, rosbag2 directory; ``input``/``output``
    as /topic:field.path or a msg_config YAML ``config``). Several paths: one record of runs.
    ``reference``: the closed loop's reference r (a column or /topic:field.path)."""
    from .io.records import concatenate_records, load_record

    if not isinstance(path, (str, Path)):
        return concatenate_records([read(p, input=input, output=output, config=config, reference=reference)
                                    for p in path])
    text = str(path)
    if Path(text).suffix.lower() == ".mcap" or Path(text).is_dir():
        from .io.bags import load_bag_record

        return load_bag_record(text, input_spec=input, output_spec=output,
                               config=None if config is None else str(config), reference_spec=reference)
    if config:
        raise UsageError(f"--config: a msg_config maps bag topics, but {text} is a CSV/NPZ file (use --input/--output)")
    return load_record(text, input or "u", output or "y", reference_name=reference)


def _record(u: Any, y: Any, runs: Runs | Sequence[int] | None, reference: Any) -> Record:
    """``u`` as it is when it is a Record (then ``y`` is None), else a Record of the arrays (u, y);
    ``runs``: a Runs or the run lengths; ``reference``: r of a closed loop."""
    if isinstance(u, Record) == (y is not None):
        raise UsageError("give a Record, or the arrays u and y")
    if isinstance(u, Record):
        record = u
    else:
        v, out = np.asarray(u, dtype=float).ravel(), np.asarray(y, dtype=float).ravel()
        if v.size != out.size:
            raise UsageError(f"u and y differ in length ({v.size} and {out.size})")
        record = Record(v, out)
    if runs is not None:
        runs = runs if isinstance(runs, Runs) else Runs.from_lengths(runs)
        record = replace(record, runs=None if runs.count == 1 else runs)
    if reference is not None:
        record = replace(record, r=np.asarray(reference, dtype=float).ravel())
    return record


def identify(u: Any, y: Any = None, *, method: str = "cls-markov", order: int = 3, delay: int = 1,
             runs: Runs | Sequence[int] | None = None, refine: bool = False, **options: Any) -> Model:
    """The Hammerstein model y = G(q) F(u) + noise of a record (``u`` a Record, or the arrays u and y)
    by ``method`` (``identification.methods.METHODS``: cls-markov, cls-arx, plls-hammerstein, bf-hammerstein,
    ...) with a linear block of ``order`` n and relative degree ``delay`` d. ``runs``: separate experiments
    laid end to end (run lengths); ``refine``: the estimate refined on the simulation error.
    ``options``: the other fields of ``IdentifyOptions`` (mu, poly, partition, tau_max, harmonic,
    feedback_partition, reference)."""
    unknown = sorted(set(options) - set(OPTION_NAMES))
    if unknown:
        raise UsageError(f"identify: unknown option {unknown[0]!r} (choose from {', '.join(OPTION_NAMES)})")
    record = _record(u, y, runs, options.pop("reference", None))
    settings = IdentifyOptions(order=order, delay=delay, **options, reference=record.r, runs=record.runs)
    result = identify_with(method, record.v, record.y, settings)
    if refine:
        from .identification.instrumental import refinement_input
        from .identification.refinement import refine_result

        result = refine_result(result, refinement_input(record.v, record.r, record.runs), record.y, record.runs)
    return Model(result, record)


def _sample_time(record: Record) -> float | bool:
    """The record's sample period (s) from its time stamps, else True (scipy: unspecified)."""
    steps = np.diff(record.t) if record.t is not None and record.t.size > 1 else np.zeros(0)
    return float(np.median(steps)) if steps.size and np.median(steps) > 0 else True


@dataclass(frozen=True, eq=False)
class Model:
    """An identified Hammerstein model with the record it came from: u -> F(u) -> G(q) -> y."""

    result: IdentificationResult
    record: Record

    @property
    def poles(self) -> np.ndarray:
        return self.result.poles

    @property
    def zeros(self) -> np.ndarray:
        return self.result.zeros

    @property
    def gain(self) -> float | None:
        """The method's gain figure (CLS/NLS: h1_hat / h1, the first Markov parameter of the chain)."""
        return None if self.result.gain is None else float(self.result.gain)

    @property
    def nonlinearity(self):
        """F as a callable (a static map of ``identification.static_maps``; None for a linear method)."""
        return self.result.nonlinearity

    def simulate(self, u: Any, y: Any = None, runs: Runs | None = None) -> np.ndarray:
        """The free-run output of the whole model on ``u`` from zero state (each of ``runs`` anew); with
        the measured ``y``, each run starts as the reported fit does (at rest at its first input or from
        zero state, whichever explains y's first samples: ``IdentificationResult.free_run``)."""
        u = np.asarray(u, dtype=float).ravel()
        runs = Runs.one(u.size) if runs is None else runs
        if y is None:
            return runs.simulate(self.result.simulate, u, at_rest=(False,) * runs.count)
        return self.result.free_run(u, np.asarray(y, dtype=float).ravel(), runs)

    def warnings(self) -> tuple[ModelWarning, ...]:
        """The record's warnings and the ``closed_loop`` warning of a model identified without a
        reference (``diagnosis.closed_loop.closed_loop_warnings`` on its free-run residual)."""
        from .diagnosis.closed_loop import closed_loop_warnings

        record = self.record
        if record.r is not None:
            return record.warnings
        with np.errstate(all="ignore"):  # the residual of the free run the fit is measured on
            residual = record.y - self.result.free_run(record.v, record.y, record.runs)
        return (*record.warnings, *closed_loop_warnings(record.v, residual, several(record.runs)))

    def to_dict(self) -> dict:
        """The ``hammer-ros identify --json`` document: the model, its bounds, fit and rms on its record."""
        record = self.record
        doc = self.result.to_json(record.v, record.y, record.runs, warnings=self.warnings())
        doc["runs"] = record.run_count
        return doc

    def to_scipy(self):
        """The linear block G as a ``scipy.signal.dlti`` (zeros, poles, gain; dt from the record's time
        stamps when it has them)."""
        from scipy.signal import dlti

        b = self.result.linear.b
        leading = b[np.flatnonzero(b)[0]] if b.any() else 0.0
        return dlti(self.zeros, self.poles, float(leading), dt=_sample_time(self.record))

    def plot(self, path: str | Path | None = None):
        """The pole-zero map with 95 % regions of the poles and zeros, and F with its 95 % band (when the
        method gives bounds); saved to ``path`` when given. Needs matplotlib. Returns the figure."""
        import matplotlib.pyplot as plt
        from matplotlib.patches import Circle, Ellipse

        doc = self.to_dict()
        nonlinearity = doc.get("nonlinearity", {})
        figure, axes = plt.subplots(1, 2 if nonlinearity.get("points") else 1, figsize=(10, 4.5), squeeze=False)
        ax = axes[0][0]
        ax.add_patch(Circle((0, 0), 1.0, fill=False, linestyle=":", color="grey"))
        for key, marker in (("poles", "x"), ("zeros", "o")):
            roots = np.asarray(doc[key], dtype=float).reshape(-1, 2)
            ax.plot(roots[:, 0], roots[:, 1], marker, mfc="none", linestyle="none", label=key)
            for (re, im), sd in zip(roots, doc.get(f"{key}_std", ())):
                if sd[0] is not None and sd[1] is not None:
                    ax.add_patch(Ellipse((re, im), 2 * CONFIDENCE_SDS * sd[0], 2 * CONFIDENCE_SDS * sd[1],
                                         alpha=0.25))
        ax.set(aspect="equal", xlabel="Re z", ylabel="Im z", title=f"G: {doc['method']}, order {doc['order']}")
        ax.legend()
        if nonlinearity.get("points"):
            ax = axes[0][1]
            points = np.asarray(nonlinearity["points"], dtype=float)
            ax.plot(points[:, 0], points[:, 1], label="F")
            if nonlinearity.get("points_std"):
                sd = np.asarray([np.nan if s is None else s for s in nonlinearity["points_std"]], dtype=float)
                ax.fill_between(points[:, 0], points[:, 1] - CONFIDENCE_SDS * sd, points[:, 1] + CONFIDENCE_SDS * sd,
                                alpha=0.25, label="95 %")
            ax.set(xlabel="u", ylabel="F(u)", title=f"F: {nonlinearity['kind']}")
            ax.legend()
        figure.tight_layout()
        if path is not None:
            figure.savefig(path)
        return figure


def split_records(record: Record, *, split: float | str = 0.7, validation: Record | None = None):
    """(Split, the records' warnings) of a diagnosis: ``record`` for estimation and ``validation`` for
    validation, or ``record`` split at the fraction ``split`` (or ``"auto"``: ``coverage.auto_split``).
    A record of several runs is split into whole runs (``split.split_runs``; ``"auto"`` as 0.7)."""
    from .diagnosis.coverage import auto_split
    from .diagnosis.split import Split, check_split, split_record, split_runs
    from .identification.instrumental import check_reference

    if validation is not None:
        parts = Split(record.v, record.y, validation.v, validation.y, continuous=False, runs_est=record.runs,
                      runs_val=validation.runs)
        if parts.has_runs:
            parts = replace(parts, note=f"estimation on {parts.est_runs.describe()}, validation (--validation) on "
                                        f"{parts.val_runs.describe()}")
        check_split(parts)
        warnings = (*record.warnings, *validation.warnings)
        if record.r is None:
            return parts, warnings
        return replace(parts, r_est=check_reference(record.r, record.v.size),
                       r_val=check_reference(validation.r, validation.v.size)), warnings
    if record.runs is not None and record.runs.count > 1:
        return split_runs(record.v, record.y, record.runs, 0.7 if split == "auto" else float(split),
                          record.r), record.warnings
    if split == "auto":
        return auto_split(record.v, record.y, record.r), record.warnings
    return split_record(record.v, record.y, float(split), record.r), record.warnings


def diagnose(u: Any, y: Any = None, *, order: int | None = None, split: float | str = 0.7,
             validation: Record | tuple[Any, Any] | None = None, reference: Any = None,
             delay: int | None = None) -> Diagnosis:
    """What the nominal Hammerstein model of the record (``u`` a Record, or the arrays u and y) gets wrong,
    why (the cause) and the extended model (``diagnosis.diagnose``): estimated on the first ``split`` of
    the record (or ``"auto"``), validated on the rest, or on ``validation`` (a Record or a (u, y) pair).
    ``reference``: the closed loop's r (with ``validation``, give Records that hold theirs)."""
    from .diagnosis.diagnose import diagnose as diagnose_split

    if order is not None and order < 1:
        raise UsageError(f"diagnose: order must be >= 1 (got {order})")
    if delay is not None and order is not None and delay > order:
        raise UsageError(f"diagnose: relative degree {delay} exceeds order {order}")
    record = _record(u, y, None, reference)
    held_out = validation if validation is None or isinstance(validation, Record) else _record(*validation, None, None)
    parts, warnings = split_records(record, split=split, validation=held_out)
    return Diagnosis(diagnose_split(parts, order, delay), parts, warnings)


@dataclass(frozen=True, eq=False)
class Diagnosis:
    """A diagnosis: the ``cause`` of the nominal model's errors, the ``extended`` model that removes
    them (None when the cause is none), ``to_dict`` and an HTML ``report``."""

    run: Any  # diagnosis.diagnose.DiagnosisRun
    split: Any  # diagnosis.split.Split
    record_warnings: tuple[ModelWarning, ...] = field(default=())

    @property
    def cause(self) -> str:
        return self.run.diagnosis.cause

    @property
    def extended(self):
        """The extended model (``diagnosis.extensions.ExtendedModel``, the chain's last), or None."""
        return self.run.extended

    @property
    def baseline_rms(self) -> float:
        return float(self.run.diagnosis.baseline.rms)

    def warnings(self) -> tuple[ModelWarning, ...]:
        """The records' warnings and the diagnosis' reasons not to trust its models: the baseline's
        validation fit, the estimation part's excitation, and the ``closed_loop`` evidence row when it
        fails without a reference."""
        from .diagnosis.closed_loop import TEST_NAME as CLOSED_LOOP_TEST
        from .identification.trust import closed_loop_warning, excitation_warnings, fit_warnings

        d, split = self.run.diagnosis, self.split
        closed = next((e for e in d.evidence if e.test == CLOSED_LOOP_TEST), None)
        feedback = closed is not None and not closed.passed and split.r_est is None
        return (*self.record_warnings, *fit_warnings(d.baseline.fit_percent, "the validation data"),
                *excitation_warnings(split.v_est, split.y_est),
                *((closed_loop_warning(closed.value, closed.bound),) if feedback else ()))

    def to_dict(self) -> dict:
        """The ``hammer-ros diagnose --json`` document."""
        from .identification.trust import warnings_json

        return {**self.run.diagnosis.to_json(), "runs": self.split.run_count,
                "warnings": warnings_json(self.warnings())}

    def report(self, path: str | Path, title: str = "hammer-ros diagnosis") -> None:
        """A self-contained HTML report (the ``diagnose --report`` page; needs matplotlib)."""
        from .diagnosis.report import write_report

        write_report(self.run, path, title=title)
