"""``hammer-ros reproduce real``: the measured benchmark records the repository ships, each run
through the same ``diagnose`` a user runs, with its benchmark's own estimation/test convention,
beside the published numbers (``hammer_ros/data/*/PROVENANCE.md``).

Only the data convention is per record: which arrays are input and output, the estimation
and test parts, and the nominal order where the benchmark's physical model states one (the
``order`` argument of ``diagnose``, as ``--order`` on the command line; the diagnosis may
still find more dynamics). Nothing of the diagnosis is tuned per record. Every record is
read from ``hammer_ros/data`` (never from outside the package).

Rows per record (``table`` = the record, ``case`` = its samples and order): the benchmark's
convention beside ours; the documented physics beside what the named cause means; baseline
test RMSE and fit; the cause (published = the cause the physics calls for, or "nearest
listed: ..." where no listed cause describes it exactly) and the cause chain (the diagnosis'
``steps`` when it reports a chain, else the single cause); whether the named cause matches
the physics ("yes", "nearest listed", "partly" = only a later step does, "no"); confidence;
extended test RMSE and gain (and each step's RMSE for a chain); the published test numbers,
each beside our final model (the extended model when a cause is named, else the baseline) on
the same test samples; the diagnosis' wall time. RMSE is taken over the whole test part (the
benchmarks' optional state initialisation windows of 20-50 samples are not skipped; a
separate test record is simulated from rest at the operating point of its first outputs, as
``diagnose --validation`` does). Native libraries' messages (LAPACK prints its argument
errors on file descriptor 1) are sent to stderr while a record runs.

The records and what to expect:

* Cascaded Tanks (1024 + 1024 samples, separate records, order 2): the square-root outflow
  feedback and the overflow clipping need state that 1024 samples of slow dynamics barely
  identify; the diagnosis answers ``none`` rather than overfit (see docs/diagnosis.md), which
  does not match the physics: said so in its row.
* Wiener-Hammerstein 2009 (100 000 + 78 800 samples, continuous, order 6 = the two 3rd-order
  filters): the front filter is ``input_dynamics``.
* Wigren coupled tanks, tanks2 (70 % / 30 %, continuous): the upper tank (column 3, ``y2``: it
  answers the pump within one sample, see its PROVENANCE.md) with order 1, the lower tank
  (column 2, ``y1``) with order 2. Both drain through Bernoulli outlets: ``output_feedback``.
* EMPS (24 841 + 24 841 samples, separate records, vir -> qm, order 2 from the rigid-body
  model): a position loop around an integrating plant with Coulomb friction. The data are
  closed loop (the controller makes vir from qm and the reference), and the open-loop model
  vir -> qm the benchmark asks for contains an integrator: the plain Hammerstein free run on
  the separate test record drifts (negative fit) with any error in the static gain or the
  friction offset. The friction is a static nonlinearity of the velocity fed back, which no
  listed cause holds exactly: ``output_feedback`` feeds back a map of the position, not the
  velocity, and ``input_dynamics`` holds it to first order (the velocity is the force
  low-pass filtered by the mass, M/Fv = 0.47 s, so the friction is roughly a static map of a
  filtered input); both count as "nearest listed". Taking the velocity diff(qm)/Ts as the
  output instead (not the benchmark's convention, so not a row here) removes the integrator,
  and ``output_feedback`` then puts a breakpoint of the feedback map at zero velocity: the
  Coulomb friction itself.
* DaISy heat exchanger (3000 + 1000 samples, continuous, no nominal order): the flow sets the
  time constants as well as the gain (a flow x temperature product) and the response is
  non-minimum-phase; no listed cause holds that exactly. The nearest: a parallel path (two
  branches of different speed and sign, which also gives the non-minimum-phase zero) or
  output feedback (operating-point-dependent time constants); both count as "nearest listed".
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ..diagnosis.causes import MEANING
from ..diagnosis.diagnose import DiagnosisRun, diagnose
from ..diagnosis.split import Split, check_split, split_record
from ..io.records import load_record

DATA_DIR = Path(__file__).resolve().parents[1] / "data"


@dataclass(frozen=True)
class Published:
    """A published test number: ``kind`` 'rmse' (in the record's unit) or 'fit' (percent)."""

    label: str
    kind: str
    value: float


@dataclass(frozen=True)
class RealRecord:
    key: str
    paper: str
    table: str
    case: str  # the ``case`` column: estimation/test samples, order
    benchmark: str  # the benchmark's own convention (PROVENANCE.md)
    convention: str  # ours: files/arrays, parts, initial state, order and why
    unit: str  # of the output, as printed
    scale: float  # output unit -> printed unit (1000 for V -> mV)
    order: int | None
    load: Callable[[], Split]
    lengths: tuple[int, int]  # estimation and test samples
    physics: str
    expected: tuple[str, ...]  # the cause chain the physics calls for ((): no listed cause is exact)
    matching: frozenset[str]  # causes that describe the physics
    exact: bool = True  # False: ``matching`` holds only the nearest listed cause, not the physics itself
    published: tuple[Published, ...] = ()


def _separate(estimation: str, test: str, input_name: str = "u", output_name: str = "y") -> Callable[[], Split]:
    """Estimation record and separate test record (``diagnose DATA --validation DATA2``)."""
    def load() -> Split:
        est = load_record(DATA_DIR / estimation, input_name, output_name)
        val = load_record(DATA_DIR / test, input_name, output_name)
        split = Split(est.v, est.y, val.v, val.y, continuous=False)
        check_split(split)
        return split

    return load


def _continuous(path: str, n_est: int | None, fraction: float | None, input_name: str = "u",
                output_name: str = "y") -> Callable[[], Split]:
    """One record, the first ``n_est`` samples (or ``fraction``) for estimation, the rest for
    the test (``diagnose DATA --split F``)."""
    def load() -> Split:
        record = load_record(DATA_DIR / path, input_name, output_name)
        split = split_record(record.v, record.y, fraction if n_est is None else n_est / record.v.size)
        if n_est is not None and split.n_est != n_est:  # the fraction must land exactly on the published cut
            raise AssertionError(f"{path}: split at {split.n_est}, expected {n_est}")
        return split

    return load


RECORDS: dict[str, RealRecord] = {r.key: r for r in (
    RealRecord(
        key="cascaded_tanks",
        paper="Schoukens, Mattsson, Wigren, Noel 2016",
        table="Cascaded Tanks",
        case="1024 est -> 1024 test (separate records), order 2",
        benchmark="estimate on uEst/yEst only; simulation RMSE (V) on uVal/yVal, the whole record (older papers) or "
                  "after a 50-sample state-initialisation window (nonlinear-benchmarks loader)",
        convention="estimation.csv -> test.csv (the CSV's two records), the test simulated from rest at its first "
                   "outputs, RMSE over all 1024 test samples; order 2: the benchmark's two-tank model",
        unit="V", scale=1.0, order=2,
        load=_separate("cascaded_tanks/estimation.csv", "cascaded_tanks/test.csv"),
        lengths=(1024, 1024),
        physics=("The pump fills the upper tank, which drains through a free outlet into the lower tank whose level is "
                 "measured: Bernoulli outflows make the time constants depend on the levels (sqrt(h) fed back), and "
                 "large inputs overflow the tanks, clipping the measured level at 10 V."),
        expected=("output_feedback", "output_nonlinearity"),
        matching=frozenset({"output_feedback", "output_nonlinearity"}),
        published=(Published("best linear approximation (Relan et al. 2017)", "rmse", 0.75),
                   Published("nonlinear state space, NLSS2 init (Relan et al. 2017)", "rmse", 0.34),
                   Published("best known: grey box with overflow (Rogers et al. 2017)", "rmse", 0.18)),
    ),
    RealRecord(
        key="wiener_hammerstein_2009",
        paper="Ljung, Schoukens, Suykens 2009",
        table="Wiener-Hammerstein 2009",
        case="100000 est -> 78800 test (continuous), order 6",
        benchmark="samples [5200, 184000): first 100 000 for estimation, remaining 78 800 for the test, simulation "
                  "RMSE in mV (nonlinear-benchmarks loader; a 50-sample state initialisation window allowed)",
        convention="wh2009.npz (that range) split at 100 000, the test continuing the estimation simulation, RMSE over "
                   "all 78 800 test samples; order 6: the circuit's two 3rd-order filters",
        unit="mV", scale=1000.0, order=6,
        load=_continuous("wiener_hammerstein_2009/wh2009.npz", 100_000, None),
        lengths=(100_000, 78_800),
        physics=("An electronic circuit: a 3rd-order Chebyshev low-pass filter, then a diode-resistor static "
                 "nonlinearity, then a 3rd-order inverse Chebyshev filter; the nonlinearity sees the filtered input, "
                 "which no static map of the input can represent (a filter before the map)."),
        expected=("input_dynamics",),
        matching=frozenset({"input_dynamics"}),
        published=(Published("dynoNet, WH structure (Forgione & Piga 2021)", "rmse", 1.2),
                   Published("dynoNet, WH structure (Forgione & Piga 2021)", "fit", 99.5),
                   Published("best known: WH via BLA separation (Schoukens et al. 2014)", "rmse", 0.28)),
    ),
    RealRecord(
        key="wigren_upper",
        paper="Wigren 2010 (UU report 2010-020)",
        table="Wigren coupled tanks, upper tank (tanks2 column 3, y2)",
        case="5250 est -> 2250 test (continuous), order 1",
        benchmark="none official: one file for estimation, the other or a later segment for validation",
        convention="tanks2.npz u -> y2: first 70 % for estimation, last 30 % for the test (tanks1.dat, at Ts = 5 s "
                   "instead of 4 s, cannot validate a model fitted at 4 s); order 1: one tank",
        unit="V", scale=1.0, order=1,
        load=_continuous("wigren_coupled_tanks/tanks2.npz", None, 0.7, "u", "y2"),
        lengths=(5250, 2250),
        physics=("The tank the pump fills (its level answers the pump within one sample): inflow proportional to the "
                 "pump voltage, outflow through a free outlet ~ sqrt(level), so a static nonlinearity of the measured "
                 "level is fed back and the time constant grows with the level; no overflow."),
        expected=("output_feedback",),
        matching=frozenset({"output_feedback"}),
    ),
    RealRecord(
        key="wigren_lower",
        paper="Wigren 2010 (UU report 2010-020)",
        table="Wigren coupled tanks, lower tank (tanks2 column 2, y1)",
        case="5250 est -> 2250 test (continuous), order 2",
        benchmark="none official: one file for estimation, the other or a later segment for validation",
        convention="tanks2.npz u -> y1: first 70 % for estimation, last 30 % for the test; order 2: two tanks",
        unit="V", scale=1.0, order=2,
        load=_continuous("wigren_coupled_tanks/tanks2.npz", None, 0.7, "u", "y1"),
        lengths=(5250, 2250),
        physics=("Fed only by the upper tank's outflow ~ sqrt(upper level) and draining ~ sqrt(own level): two "
                 "level-dependent square-root feedbacks, of which only the own level's is a function of the measured "
                 "output; the level lags the pump by the upper tank."),
        expected=("output_feedback",),
        matching=frozenset({"output_feedback"}),
    ),
    RealRecord(
        key="emps",
        paper="Janot, Gautier, Brunot 2019",
        table="EMPS (vir -> qm)",
        case="24841 est -> 24841 test (separate records), order 2",
        benchmark="u = vir, y = qm; train on DATA_EMPS, test on DATA_EMPS_PULSES (nonlinear-benchmarks loader, "
                  "20-sample state initialisation window)",
        convention="DATA_EMPS.npz -> DATA_EMPS_PULSES.npz, vir -> qm, the test simulated from rest at its first "
                   "outputs, RMSE over all 24 841 test samples; order 2: the rigid-body model with viscous friction",
        unit="mm", scale=1000.0, order=2,
        load=_separate("emps/DATA_EMPS.npz", "emps/DATA_EMPS_PULSES.npz", "vir", "qm"),
        lengths=(24_841, 24_841),
        physics=("A prismatic joint, M q'' = tau - Fv q' - Fc sign(q') - offset: an integrator from force to "
                 "position with Coulomb friction, a static nonlinearity of the velocity fed back, recorded in closed "
                 "loop (a P/PI position-velocity controller makes vir from qm and the reference). Nearest listed "
                 "causes: output_feedback (a static map fed back, but of the position, not the velocity) or "
                 "input_dynamics (the velocity is to first order the force low-pass filtered by the mass, so the "
                 "friction is a static map of a filtered input)."),
        expected=(),
        matching=frozenset({"output_feedback", "input_dynamics"}),
        exact=False,
        published=(Published("best linear model (Janot et al. 2019, quoted by Forgione & Piga 2021)", "fit", 25.4),
                   Published("dynoNet G-NN-integrator (Forgione & Piga 2021)", "rmse", 2.64),
                   Published("dynoNet G-NN-integrator (Forgione & Piga 2021)", "fit", 96.8)),
    ),
    RealRecord(
        key="heat_exchanger",
        paper="DaISy 97-002 (Bittanti & Piroddi 1996)",
        table="DaISy heat exchanger (q -> th)",
        case="3000 est -> 1000 test (continuous), order chosen",
        benchmark="none official; common practice: first part for estimation, the rest for validation (e.g. 3000/1000)",
        convention="exchanger.npz q -> th: first 3000 for estimation, last 1000 for the test; no nominal order stated, "
                   "so the diagnosis chooses it",
        unit="degC", scale=1.0, order=None,
        load=_continuous("daisy_heat_exchanger/exchanger.npz", 3000, None, "q", "th"),
        lengths=(3000, 1000),
        physics=("Water heated by saturated steam in a copper tube: the liquid flow sets the static gain and also "
                 "the time constants (transit time, heat transfer), a flow x temperature product no listed cause "
                 "holds, and its fast and slow effects on the outlet temperature oppose each other (a non-minimum-"
                 "phase response); the nearest listed causes: parallel_path (two branches of different speed and "
                 "sign) or output_feedback (time constants that depend on the operating point)."),
        expected=(),
        matching=frozenset({"parallel_path", "output_feedback"}),
        exact=False,
    ),
)}


def cause_chain(doc: dict) -> list[str]:
    """The causes of a ``diagnose`` JSON document in order: its ``steps`` when it reports a
    chain, else the single cause."""
    steps = doc.get("steps") or []
    chain = [str(s["cause"]) for s in steps if s.get("cause")]
    return chain or [str(doc["cause"])]


def matches_physics(chain: list[str], record: RealRecord) -> str:
    """'yes' when the named cause (first of the chain) describes the record's physics, 'nearest
    listed' when it is only the nearest of the listed causes to it, 'partly' when only a later
    step of the chain does, 'no' otherwise (also for ``none``)."""
    if chain[0] in record.matching:
        return "yes" if record.exact else "nearest listed"
    if any(c in record.matching for c in chain[1:]):
        return "partly"
    return "no"


@contextmanager
def native_output_to_stderr() -> Iterator[None]:
    """File descriptor 1 points at stderr inside the block: messages that native libraries
    write straight to it (LAPACK's "** On entry to DLASCL parameter number 4 had an illegal
    value" on a NaN) go to stderr, so ``--json`` keeps one JSON document alone on stdout."""
    try:
        out, err = sys.stdout.fileno(), sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):  # stdout/stderr without a descriptor (captured)
        yield
        return
    sys.stdout.flush()
    saved = os.dup(out)
    try:
        os.dup2(err, out)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, out)
        os.close(saved)


def run_record(record: RealRecord) -> tuple[DiagnosisRun, float]:
    """The diagnosis of one record with its convention, and the seconds it took."""
    split = record.load()
    start = time.perf_counter()
    with native_output_to_stderr():
        run = diagnose(split, record.order)
    seconds = time.perf_counter() - start
    print(f"reproduce real: {record.table}: {run.diagnosis.cause}, {seconds:.1f} s", file=sys.stderr)
    return run, seconds


def record_rows(record: RealRecord, run: DiagnosisRun, seconds: float | None = None) -> list[dict]:
    """The rows of one record from its diagnosis."""
    d = run.diagnosis
    doc = d.to_json()
    chain = cause_chain(doc)
    unit, scale = record.unit, record.scale
    final = d.extended if d.extended is not None else d.baseline
    out: list[dict] = []

    def row(quantity: str, published, ours, case: str = record.case) -> None:
        out.append({"paper": record.paper, "table": record.table, "case": case, "quantity": quantity,
                    "published": published, "ours": ours})

    row("convention (benchmark / ours)", record.benchmark, record.convention)
    row("physics (documented) / what the named cause means", record.physics, MEANING.get(d.cause, d.cause))
    row(f"baseline test RMSE ({unit})", None, float(d.baseline.rms * scale))
    row("baseline test fit (%)", None, float(d.baseline.fit_percent))
    nearest = "nearest listed: " + " or ".join(sorted(record.matching)) if record.matching else None
    row("cause", record.expected[0] if record.expected else nearest, d.cause)
    row("cause chain", " -> ".join(record.expected) if record.expected else nearest, " -> ".join(chain))
    row("cause matches physics", None, matches_physics(chain, record))
    row("confidence (0..1)", None, float(d.confidence))
    row(f"extended test RMSE ({unit})", None, None if d.extended is None else float(d.extended.rms * scale),
        case=record.case if d.extended is None else d.extended.structure)
    row("gain (baseline / extended test RMSE)", None, None if d.gain is None else float(d.gain))
    steps = doc.get("steps") or []
    if len(steps) > 1:
        for i, step in enumerate(steps, start=1):
            row(f"step {i} test RMSE ({unit})", None, float(step["rms"]) * scale,
                case=f"{step['cause']}: {step['structure']}")
    for p in record.published:
        if p.kind == "rmse":
            row(f"test RMSE ({unit}): {p.label}", p.value, float(final.rms * scale), case=f"ours: {final.structure}")
        else:
            row(f"test fit (%): {p.label}", p.value, float(final.fit_percent), case=f"ours: {final.structure}")
    if seconds is not None:
        row("diagnosis wall time (s)", None, round(float(seconds), 1))
    return out


def rows(runs: int | None = None, seed: int = 0, records: tuple[str, ...] | None = None) -> list[dict]:
    """Every shipped record (or ``records`` by key) through ``diagnose``; ``runs`` and ``seed``
    are unused (measured data, one diagnosis per record)."""
    del runs, seed
    out: list[dict] = []
    for key in RECORDS if records is None else records:
        record = RECORDS[key]
        run, seconds = run_record(record)
        out.extend(record_rows(record, run, seconds))
    return out
