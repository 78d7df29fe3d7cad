"""uwbcal: a thin typer CLI over the convert / pipeline / evaluate packages (no algorithm code here)."""

from __future__ import annotations

import functools
import os
import signal
import sys
from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

# The filters work on small matrices: multi-threaded BLAS only adds contention (10-100x slower under load).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from uwbcal.pipeline.core.errors import InputError  # noqa: E402
from uwbcal.pipeline.core.names import INIT_METHODS, REFINE_METHODS  # noqa: E402

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    help="Robust UWB anchor calibration from a visual-inertial estimate (logging-first, offline).",
)
convert_app = typer.Typer(no_args_is_help=True, help="Normalise a dataset into one MCAP recording.")
app.add_typer(convert_app, name="convert")

_DEBUG = {"on": False}


@app.callback()
def _main(debug: Annotated[bool, typer.Option("--debug", help="Show tracebacks.")] = False) -> None:
    _DEBUG["on"] = debug


def _guard(fn):
    """The error policy, in one place: an expected failure (bad input, an OS error on an input or output, a
    decoding error) -> one line on stderr naming the user's file and exit 2; SIGTERM / Ctrl-C -> temporary outputs
    removed, exit 143 / 130; anything else is a bug -> one line and exit 1 (the traceback only with --debug).
    Python warnings are shown once each, as one line."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        import warnings

        import click

        from uwbcal.pipeline.core.atomic import discard_all
        from uwbcal.pipeline.core.errors import EstimateFailed, Terminated, os_error_message

        def _term(signum, frame):
            raise Terminated()

        try:
            previous = signal.signal(signal.SIGTERM, _term)
        except ValueError:  # not the main thread
            previous = None
        caught: list[warnings.WarningMessage] = []
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                return fn(*args, **kwargs)
        except (typer.Exit, typer.Abort, click.exceptions.Exit, click.exceptions.Abort, click.ClickException):
            raise
        except Terminated:
            discard_all()
            typer.echo("error: terminated (SIGTERM); finished outputs kept, partial ones removed", err=True)
            raise typer.Exit(143) from None
        except KeyboardInterrupt:
            discard_all()
            typer.echo("error: interrupted; finished outputs kept, partial ones removed", err=True)
            raise typer.Exit(130) from None
        except Exception as exc:
            if _DEBUG["on"]:
                raise
            if isinstance(exc, EstimateFailed):
                typer.echo("error: " + " ".join(str(exc).split("\n")).strip(), err=True)
                raise typer.Exit(3) from None
            if isinstance(exc, InputError):
                msg = str(exc)
            elif isinstance(exc, OSError):
                msg = os_error_message(exc)
            elif isinstance(exc, UnicodeDecodeError):
                msg = f"an input is not UTF-8 text ({exc.reason} at byte {exc.start}); convert it to UTF-8"
            else:
                first = (str(exc).strip().splitlines() or [""])[0]
                typer.echo(
                    f"error: internal error ({type(exc).__name__}: {first}); this is a bug in uwbcal, "
                    "please report it with the output of --debug",
                    err=True,
                )
                raise typer.Exit(1) from None
            typer.echo("error: " + " ".join(msg.split("\n")).strip(), err=True)
            raise typer.Exit(2) from None
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)
            _show_warnings(caught)

    return wrapper


_NUMERIC = ("encountered in", "Mean of empty slice", "Degrees of freedom <= 0", "All-NaN slice")


def _show_warnings(caught: list) -> None:
    """Each warning once, as one line; a library's numerical RuntimeWarning (numpy's 'invalid value encountered
    in divide') becomes a note naming where it arose, not the library's raw text."""
    seen = set()
    for w in caught:
        if not issubclass(w.category, (UserWarning, RuntimeWarning, FutureWarning)):
            continue
        text = " ".join(str(w.message).split())
        if issubclass(w.category, RuntimeWarning) and any(k in text for k in _NUMERIC):
            where = Path(w.filename)
            where = "/".join(where.parts[-3:]) if where.parts else "?"
            text = (
                f"note: a numerical step produced NaN/inf ({text}, at {where}:{w.lineno}); the run went on — "
                "if a result looks wrong, rerun with --debug and report it"
            )
        else:
            text = f"warning: {text}"
        if text not in seen:
            seen.add(text)
            typer.echo(text, err=True)


def _output_file(path: Path) -> None:
    """Refuse an output file path that cannot be one (a directory, /dev/null) before any work is done."""
    from uwbcal.pipeline.core.atomic import check_output_file

    check_output_file(path)


class Align(str, Enum):
    none = "none"
    posyaw = "posyaw"
    se3 = "se3"
    sim3 = "sim3"


class TableFormat(str, Enum):
    md = "md"
    csv = "csv"
    latex = "latex"


InitMethod = Enum("InitMethod", {m.replace("-", "_"): m for m in INIT_METHODS}, type=str)
RefineMethod = Enum("RefineMethod", {m: m for m in (*REFINE_METHODS, "none")}, type=str)


class Experiment(str, Enum):
    ri_vs_lsi = "ri-vs-lsi"
    ri_vs_lsi_drift = "ri-vs-lsi-drift"
    table1 = "table1"
    ntu_viral = "ntu-viral"
    anchor_nees = "anchor-nees"


Output = Annotated[Path, typer.Option("-o", "--output", help="Output path.")]
StampUnit = Enum("StampUnit", {u: u for u in ("s", "ms", "us", "ns")}, type=str)
TimeOffset = Annotated[
    float,
    typer.Option(
        help="Seconds added to every range stamp: a known range-to-pose clock offset (ranges 0.2 s late: -0.2)."
    ),
]


@app.command()
@_guard
def demo(output: Annotated[Path, typer.Option("-o", "--output")] = Path("recordings/demo")) -> None:
    """Simulate the built-in trajectory, run every stage, evaluate and print a summary."""
    from uwbcal.evaluate.demo import run_demo

    typer.echo(run_demo(output))


# the options of `simulate`
_SimScenario = Annotated[
    str | None,
    typer.Option(
        help="A class of real setup: planar (ground trolley, coplanar anchors), large-area (~400 m, anchors "
        "ranged late or briefly), per-link (3 tags, an offset per link), nlos (NLOS junk on some links), "
        "climbing-drone (a drone climbing on the spot), far-cluster (a drive out to ~55 m from a clustered "
        "constellation, ranges ~0.2 s late), clock-offset (ranges 0.1-0.2 s late), antenna-pattern (a handheld rig, "
        "a direction-dependent range bias per anchor). Ranges + odometry, no camera unless --camera; other options "
        "override the scenario's."
    ),
]
_SimTrajectory = Annotated[
    str | None,
    typer.Option(
        help="EuRoC ground-truth name (MH_01_easy) or file, or built-in: default, planar, campus, climb, far-field, handheld."
    ),
]
_SimDuration = Annotated[float | None, typer.Option(help="Seconds to simulate (default: whole trajectory).")]
_SimNlosRate = Annotated[
    float | None, typer.Option(help="Fraction of ranges with a positive NLOS bias (default 0).")
]
_SimDropoutRate = Annotated[float | None, typer.Option(help="Fraction of ranges dropped (default 0).")]
_SimOdometryRate = Annotated[
    float | None,
    typer.Option(help="Also write /odometry at this rate [Hz], drifting as the odometry filter models it."),
]
_SimOdometryNoiseScale = Annotated[
    float,
    typer.Option(min=0.0, help="Factor on the odometry drift sigmas (declared in the calibration)."),
]
_SimCamera = Annotated[
    bool | None,
    typer.Option("--camera/--no-camera", help="Simulate camera feature tracks (default: yes)."),
]
_SimImuFrom = Annotated[
    Path | None,
    typer.Option(
        help="A converted recording with a real IMU and ground truth: keep its IMU, ground truth and "
        "biases, simulate tracks and ranges along its trajectory (a hybrid recording)."
    ),
]


@app.command()
@_guard
def simulate(
    output: Output,
    scenario: _SimScenario = None,
    trajectory: _SimTrajectory = None,
    anchors: Annotated[int | None, typer.Option(min=1, help="Number of anchors (default 4).")] = None,
    duration: _SimDuration = None,
    seed: Annotated[int, typer.Option(help="Random seed.")] = 0,
    nlos_rate: _SimNlosRate = None,
    dropout_rate: _SimDropoutRate = None,
    max_range: Annotated[float | None, typer.Option(help="Maximum UWB range [m].")] = None,
    odometry_rate: _SimOdometryRate = None,
    odometry_noise_scale: _SimOdometryNoiseScale = 1.0,
    camera: _SimCamera = None,
    imu_from: _SimImuFrom = None,
) -> None:
    """Simulate IMU, camera feature tracks, UWB ranges and ground truth into a recording."""
    from uwbcal.convert.simulator import SimConfig, simulate_to_file

    _output_file(output)

    given = {
        "trajectory": trajectory,
        "n_anchors": anchors,
        "duration": duration,
        "nlos_rate": nlos_rate,
        "dropout_rate": dropout_rate,
        "max_range": max_range,
        "odometry_rate": odometry_rate,
        "camera": camera,
    }
    given = {k: v for k, v in given.items() if v is not None}
    if odometry_noise_scale != 1.0:
        given["odometry_noise_scale"] = odometry_noise_scale
    if imu_from is not None:
        from uwbcal.convert.hybrid import hybrid_to_file

        if scenario is not None or trajectory is not None or odometry_rate is not None:
            raise InputError(
                f"{imu_from}: --imu-from takes the trajectory from the recording's ground truth; drop "
                "--scenario / --trajectory / --odometry-rate"
            )
        typer.echo(hybrid_to_file(imu_from, SimConfig(seed=seed, **given), output))
        return
    if scenario is not None:
        from uwbcal.convert.scenarios import scenario_to_file

        if anchors is not None:
            raise InputError(f"--anchors {anchors}: scenario {scenario} fixes its anchors; drop --anchors")
        typer.echo(scenario_to_file(scenario, output, seed=seed, **given))
        return
    typer.echo(simulate_to_file(SimConfig(seed=seed, **given), output))


@convert_app.command("euroc")
@_guard
def convert_euroc(
    path: Annotated[Path, typer.Argument(help="EuRoC ASL folder (containing mav0/) or ROS1 .bag")],
    output: Output,
    groundtruth: Annotated[
        Path | None, typer.Option(help="External ground truth (EuRoC CSV or TUM).")
    ] = None,
) -> None:
    """Convert EuRoC (ASL folder or ROS1 bag)."""
    from uwbcal.convert.euroc import convert_euroc as run

    _output_file(output)

    typer.echo(run(path, output, groundtruth=groundtruth))


@convert_app.command("ntu-viral")
@_guard
def convert_ntu_viral(
    path: Annotated[Path, typer.Argument(help="NTU-VIRAL ROS1 .bag or sequence folder of CSVs")],
    output: Output,
    antennas: Annotated[
        Path | None, typer.Option(help="uwb_antennas.yaml (default: next to the data).")
    ] = None,
    anchors_truth: Annotated[
        Path | None,
        typer.Option(
            help="Published/surveyed anchors CSV [site,]anchor,x,y,z -> uwbcal.truth "
            "(default: published_anchors.csv next to the data; the sequence's site is taken)."
        ),
    ] = None,
) -> None:
    """Convert NTU-VIRAL (ROS1 bag or CSV sequence folder)."""
    from uwbcal.convert.ntu_viral import convert_ntu_viral as run

    _output_file(output)

    typer.echo(run(path, output, antennas=antennas, anchors_truth=anchors_truth))


@convert_app.command("tabular")
@_guard
def convert_tabular(
    poses: Annotated[Path, typer.Option(help="TUM trajectory: t x y z qx qy qz qw")],
    ranges: Annotated[Path, typer.Option(help="CSV: stamp,tag,antenna,anchor,distance")],
    output: Output,
    antennas: Annotated[Path | None, typer.Option(help="Antenna lever-arm yaml.")] = None,
    anchors_truth: Annotated[
        Path | None,
        typer.Option(
            help="Surveyed anchors CSV anchor,x,y,z (the poses' frame) -> uwbcal.truth; "
            "uwbcal evaluate then reports anchor errors against it."
        ),
    ] = None,
    pose_error: Annotated[
        str,
        typer.Option(
            help="Error model of the poses: bounded (in the anchors' world frame: ground truth, SLAM with a map) "
            "or drift (dead-reckoning odometry whose error grows).",
        ),
    ] = "bounded",
    stamp_unit: Annotated[
        StampUnit | None,
        typer.Option(help="Unit of the range stamps (default: detected, and the summary says how)."),
    ] = None,
    time_offset: TimeOffset = 0.0,
) -> None:
    """Convert any odometry (TUM) plus UWB ranges (CSV)."""
    from uwbcal.convert.tabular import convert_tabular as run

    _output_file(output)

    typer.echo(
        run(
            poses,
            ranges,
            output,
            antennas=antennas,
            anchors_truth=anchors_truth,
            pose_error=pose_error,
            stamp_unit=stamp_unit and stamp_unit.value,
            time_offset=time_offset,
        )
    )


@convert_app.command("bag")
@_guard
def convert_bag(
    path: Annotated[Path, typer.Argument(help="ROS 1 .bag, ROS 2 .db3 / .mcap, or a ROS 2 bag folder")],
    output: Output,
    imu: Annotated[str | None, typer.Option(help="IMU topic (sensor_msgs/Imu).")] = None,
    cam0: Annotated[str | None, typer.Option(help="First camera topic (Image / CompressedImage).")] = None,
    cam1: Annotated[str | None, typer.Option(help="Second camera topic.")] = None,
    uwb: Annotated[
        list[str] | None, typer.Option(help="UWB range topic (repeatable); default: every UWB type found.")
    ] = None,
    odometry: Annotated[str | None, typer.Option(help="External odometry topic (nav_msgs/Odometry).")] = None,
    groundtruth: Annotated[str | None, typer.Option(help="Ground-truth pose or position topic.")] = None,
    antennas: Annotated[Path | None, typer.Option(help="Antenna lever-arm yaml.")] = None,
    calibration: Annotated[
        Path | None, typer.Option(help="Calibration yaml (imu, cameras, uwb, groundtruth, odometry).")
    ] = None,
    anchors_truth: Annotated[
        Path | None,
        typer.Option(
            help="Surveyed anchors CSV anchor,x,y,z (the ground truth's frame) -> uwbcal.truth; "
            "uwbcal evaluate then reports anchor errors against it."
        ),
    ] = None,
    start: Annotated[
        float | None,
        typer.Option(min=0.0, help="Keep messages from this many seconds after the bag's start."),
    ] = None,
    end: Annotated[
        float | None,
        typer.Option(min=0.0, help="Keep messages before this many seconds after the bag's start."),
    ] = None,
    time_offset: TimeOffset = 0.0,
) -> None:
    """Convert any ROS 1 / ROS 2 bag (topics found by message type unless given)."""
    from uwbcal.convert.bag import convert_bag as run

    typer.echo(
        run(
            path,
            output,
            imu=imu,
            cam0=cam0,
            cam1=cam1,
            uwb=uwb,
            odometry=odometry,
            groundtruth=groundtruth,
            antennas=antennas,
            calibration=calibration,
            anchors_truth=anchors_truth,
            start_s=start,
            end_s=end,
            time_offset=time_offset,
        )
    )


@app.command()
@_guard
def info(
    recording: Annotated[Path, typer.Argument(help="A .mcap recording, or a ROS bag (what would be mapped)")],
) -> None:
    """Topics, counts, rates, duration, calibration and problems found (of a bag: the topic map)."""
    from uwbcal.convert.bag import bag_info, is_bag
    from uwbcal.convert.info import recording_info

    if is_bag(recording):
        typer.echo(bag_info(recording))
        return
    typer.echo(recording_info(recording).render())


@app.command()
@_guard
def calibrate(
    path: Annotated[
        Path | None,
        typer.Argument(
            help="A ROS 1/2 bag, EuRoC folder (mav0/), NTU-VIRAL sequence folder, a folder with poses.tum + "
            "ranges.csv, or a uwbcal recording"
        ),
    ] = None,
    output: Output = Path("calibration"),
    poses: Annotated[Path | None, typer.Option(help="Tabular input: TUM trajectory (with --ranges).")] = None,
    ranges: Annotated[Path | None, typer.Option(help="Tabular input: ranges CSV (with --poses).")] = None,
    antennas: Annotated[
        Path | None, typer.Option(help="Antenna lever-arm yaml (default: antennas.yaml beside the data).")
    ] = None,
    anchors_truth: Annotated[
        Path | None, typer.Option(help="Surveyed anchors CSV (default: anchors_truth.csv beside the data).")
    ] = None,
    calibration: Annotated[
        Path | None, typer.Option(help="Bag input: calibration yaml (default: calibration.yaml beside it).")
    ] = None,
    stamp_unit: Annotated[
        StampUnit | None, typer.Option(help="Tabular input: unit of the range stamps.")
    ] = None,
    time_offset: TimeOffset = 0.0,
    config: Annotated[Path | None, typer.Option(help="TOML config (default: the defaults).")] = None,
    log: Annotated[bool, typer.Option("--log", help="Also write run.rrd (the rerun viewer's log).")] = False,
    overwrite: Annotated[
        bool, typer.Option("--overwrite", help="Replace OUTPUT's calibration of another input.")
    ] = False,
) -> None:
    """Calibrate the anchors in one command: convert, check, run with the defaults, evaluate when truth exists,
    export anchors.json / uwb_anchors.yaml / localization.yaml (with covariance) and report.html."""
    from uwbcal.evaluate.calibrate import CalibrateInput
    from uwbcal.evaluate.calibrate import calibrate as run

    inp = CalibrateInput(
        path,
        poses,
        ranges,
        antennas,
        anchors_truth,
        calibration,
        stamp_unit and stamp_unit.value,
        time_offset,
        config,
        log,
        overwrite,
    )
    typer.echo(run(inp, output, progress=lambda s: typer.echo(s, err=True)))


@app.command()
@_guard
def check(
    recording: Annotated[Path, typer.Argument(help="A .mcap recording")],
    anchors_truth: Annotated[
        Path | None,
        typer.Option(
            help="Surveyed anchors CSV anchor,x,y,z in the poses' frame (default: the recording's truth, if any)."
        ),
    ] = None,
) -> None:
    """A recording's own consistency before calibrating: range statistics, stamps, pose excitation; with truth
    the anchor ids, lever arms and range-to-pose clock offset. Ends in one verdict line per problem."""
    from uwbcal.evaluate.check import check_recording

    typer.echo(check_recording(recording, anchors_truth).render())


@app.command("config")
@_guard
def config_cmd(
    reference: Annotated[
        bool,
        typer.Option("--reference", help="The configuration reference (Markdown) instead of the defaults"),
    ] = False,
) -> None:
    """The default configuration as TOML (a starting point for --config), or its reference."""
    from uwbcal.pipeline.run.config import PipelineConfig
    from uwbcal.pipeline.run.config_reference import reference_markdown

    typer.echo(reference_markdown() if reference else PipelineConfig().to_toml(), nl=False)


@app.command()
@_guard
def run(
    recording: Annotated[Path, typer.Argument(help="A .mcap recording")],
    output: Output,
    config: Annotated[Path | None, typer.Option(help="TOML config.")] = None,
    init: Annotated[InitMethod | None, typer.Option(help="Initialiser.")] = None,
    refine: Annotated[RefineMethod | None, typer.Option(help="Refinement.")] = None,
    stages: Annotated[str | None, typer.Option(help="Comma-separated subset of stages.")] = None,
    no_log: Annotated[bool, typer.Option("--no-log", help="Do not write run.rrd.")] = False,
    overwrite: Annotated[
        bool, typer.Option(help="Replace the artefacts of another recording in the output directory.")
    ] = False,
) -> None:
    """Run the pipeline stages on a recording into a run directory (one recording per directory)."""
    from uwbcal.evaluate.evaluation import evaluate_stage
    from uwbcal.pipeline.run.stages.pipeline import run_cli

    typer.echo(
        run_cli(
            recording,
            output,
            config=config,
            init=init and init.value,
            refine=refine and refine.value,
            stages=stages,
            log=not no_log,
            evaluator=evaluate_stage,
            overwrite=overwrite,
        )
    )


@app.command()
@_guard
def evaluate(
    run_dir: Annotated[Path, typer.Argument(help="A run directory")],
    align: Annotated[Align | None, typer.Option(help="Trajectory alignment.")] = None,
    fmt: Annotated[TableFormat, typer.Option("--format", help="Table format.")] = TableFormat.md,
) -> None:
    """Compute metrics.json, results.md and report.html (rewritten together); print the results table."""
    from uwbcal.evaluate.evaluation import evaluate_run_cli

    typer.echo(evaluate_run_cli(run_dir, align=align and align.value, fmt=fmt.value))


@app.command()
@_guard
def export(
    run_dir: Annotated[Path, typer.Argument(help="A run directory")],
    output: Output,
    fmt: Annotated[str, typer.Option("--format", help="tum, anchors-yaml or anchors-json.")] = "tum",
) -> None:
    """Export estimate.tum (+ groundtruth.tum at its stamps), or the anchors with covariance (yaml / json)."""
    from uwbcal.evaluate.export import export_run

    typer.echo(export_run(run_dir, output, fmt=fmt))


@app.command()
@_guard
def experiment(
    name: Annotated[Experiment, typer.Argument(help="Which experiment")],
    output: Output,
    runs: Annotated[int | None, typer.Option(min=1, help="Runs per cell.")] = None,
    jobs: Annotated[int, typer.Option(min=1, help="Local worker processes.")] = 1,
    scheduler: Annotated[str | None, typer.Option(help="Dask scheduler address.")] = None,
    seed: Annotated[int, typer.Option(help="Base seed.")] = 0,
    param: Annotated[
        list[str] | None,
        typer.Option(
            help="Experiment parameter KEY=VALUE (repeatable), e.g. table1: prior=tuned, duration=60; "
            "anchor-nees: pose_sources=groundtruth,odometry odometry_noise_scale=0.1."
        ),
    ] = None,
) -> None:
    """Run a Monte Carlo experiment (tables, plots, per-run metrics)."""
    from uwbcal.evaluate.experiments import run_experiment

    params = dict(_key_value(p) for p in param or [])
    typer.echo(
        run_experiment(
            name.value, output, runs=runs, jobs=jobs, scheduler=scheduler, seed=seed, params=params
        )
    )


def _key_value(text: str) -> tuple[str, str]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise typer.BadParameter(f"--param {text!r}: expected KEY=VALUE")
    return key.strip(), value.strip()


@app.command()
@_guard
def diff(
    baseline: Annotated[Path, typer.Argument(help="Reference metrics (file or folder)")],
    current: Annotated[Path, typer.Argument(help="Current metrics (file or folder)")],
    rtol: Annotated[float, typer.Option(help="Relative tolerance.")] = 0.05,
) -> None:
    """Compare metrics; exit 1 when CURRENT regresses beyond tolerance."""
    from uwbcal.evaluate.diff import diff_paths

    report = diff_paths(baseline, current, rtol=rtol)
    typer.echo(report.render())
    if report.regressed:
        raise typer.Exit(1)


@app.command()
@_guard
def view(
    run_dirs: Annotated[list[Path], typer.Argument(help="One or more run directories")],
    web: Annotated[bool, typer.Option("--web", help="Serve the web viewer on localhost.")] = False,
) -> None:
    """Open run.rrd in the rerun viewer (several runs side by side)."""
    from uwbcal.pipeline.viz.runlog import view_runs

    view_runs(run_dirs, web=web)


@app.command()
@_guard
def bench(
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Write results as JSON.")] = None,
    cases: Annotated[str | None, typer.Option(help="Comma-separated case names.")] = None,
    quick: Annotated[bool, typer.Option(help="Small sizes (smoke run).")] = False,
    against: Annotated[
        Path | None,
        typer.Option(help="Another uwbcal checkout (e.g. a git worktree of main): run every case on it too."),
    ] = None,
) -> None:
    """Run the benchmarks (wall time, real-time factor, peak memory, ratio to baseline)."""
    from uwbcal.benchmarks.runner import run_benchmarks

    typer.echo(run_benchmarks(output, cases=cases, quick=quick, against=against))


def main() -> None:  # pragma: no cover
    sys.exit(app())


if __name__ == "__main__":  # pragma: no cover
    main()
