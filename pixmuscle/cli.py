"""Command-line interface (typer): a thin layer over :mod:`pixmuscle.stages` and :mod:`pixmuscle.pipeline`.

Every command turns a :class:`~pixmuscle.errors.PixmuscleError` into one line on stderr and an
exit code (:data:`EXIT_CODES`); ``--debug`` shows the traceback instead; Ctrl-C and SIGTERM end it with one line and exit
code 130 or 143 (docs/failures.md). Logs and progress go to
stderr; the paths of the files a command wrote go to stdout, one per line, so
``$(pixmuscle report results.h5)`` is the report's ``index.html``. A failed solve still prints
what it wrote (the report of its converged steps, or the results file) before exiting with
:data:`EXIT_SOLVE_FAILED`. The global options ``-v``/``-q``/``--debug`` work before or after the
command name.
"""

from __future__ import annotations

import functools
import importlib
import inspect
import logging
import signal
import sys
from collections.abc import Callable
from pathlib import Path

import typer

from . import __version__
from .errors import Interrupted, PixmuscleError, SolverError

#: a bad input (file, config key, value) or an output that could not be written
EXIT_BAD_INPUT = 2
#: a solve that stopped before its last load step; what it converged is written and its path printed
EXIT_SOLVE_FAILED = 3
#: exit codes of every command (documented in docs/failures.md)
EXIT_CODES = {0: "success", 1: "a cohort or study in which some cases failed (the others ran)",
              EXIT_BAD_INPUT: "bad input, or an output that could not be written",
              EXIT_SOLVE_FAILED: "a failed solve (its converged steps are written and reported)",
              130: "interrupted (Ctrl-C)", 143: "terminated (SIGTERM)"}

# plain (click) help: flags without a type, options with their value's type (``-o, --output PATH``)
app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None, help=(
    "pixmuscle: limb MRI + DTI → pixel-based meshfree (RKPM) muscle model → force.\n\n"
    "Stages: segment → build-model → coarsen → solve → report, or all at once with `run`. "
    "Units: cm, N, N/cm².\n\n"
    "Exit codes: 0 success; 1 a cohort or study in which some cases failed; 2 bad input or an output that "
    "could not be written; 3 a failed solve (the converged steps are written, and the report or results "
    "path is printed on stdout); 130 interrupted (Ctrl-C); 143 terminated (SIGTERM)."))
verify_app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None, help="Verification against analytic and reference solutions.")
app.add_typer(verify_app, name="verify")

_STATE = {"debug": False}
_LOG = logging.getLogger("pixmuscle.cli")


def _out(*paths) -> None:
    """Print result paths on stdout (one per line; never wrapped)."""
    for p in paths:
        sys.stdout.write(f"{p}\n")
    sys.stdout.flush()

def _load(module: str):
    """Import a stage module when its command runs (the CLI starts without loading every stage)."""
    return importlib.import_module(module)


_VERBOSE_HELP = ("More log output on stderr: -v the details of every stage (load steps, segmentation), -vv debug "
                 "messages (every Newton iteration) with time and logger name.")
_QUIET_HELP = "Only warnings and errors."
_DEBUG_HELP = "Show Python tracebacks."

#: the global options again on every command, so that they work after the command name too
_COMMAND_GLOBALS = [
    inspect.Parameter("verbose_", inspect.Parameter.KEYWORD_ONLY, annotation=int,
                      default=typer.Option(0, "--verbose", "-v", count=True, help=_VERBOSE_HELP, show_default=False)),
    inspect.Parameter("quiet_", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                      default=typer.Option(False, "--quiet", "-q", help=_QUIET_HELP, show_default=False)),
    inspect.Parameter("debug_", inspect.Parameter.KEYWORD_ONLY, annotation=bool,
                      default=typer.Option(False, "--debug", help=_DEBUG_HELP, show_default=False)),
]


def _apply_globals(verbose: int, quiet: bool, debug: bool) -> None:
    """Combine the global options given after the command with those given before it."""
    if not (verbose or quiet or debug):
        return
    from .progress import setup_logging

    _STATE["debug"] = _STATE["debug"] or debug
    _STATE["verbose"] = _STATE.get("verbose", 0) + verbose
    _STATE["quiet"] = _STATE.get("quiet", False) or quiet
    setup_logging(-1 if _STATE["quiet"] else _STATE["verbose"])


def _solve_failed(exc: SolverError) -> None:
    """Print what a failed solve left (its report, else its results file) and exit with its own code."""
    made = [p for p in (getattr(exc, "report", None), getattr(exc, "results_path", None)) if p]
    if made and Path(made[0]).exists():
        _out(made[0])
    typer.echo(f"error: {exc}", err=True)
    raise typer.Exit(EXIT_SOLVE_FAILED)


def _guard(fn: Callable) -> Callable:
    """Run a command, mapping PixmuscleError to a one-line message and its exit code; adds the
    global options (-v, -q, --debug) to the command."""

    @functools.wraps(fn)
    def wrapper(*args, verbose_: int = 0, quiet_: bool = False, debug_: bool = False, **kwargs):
        _apply_globals(verbose_, quiet_, debug_)
        try:
            return fn(*args, **kwargs)
        except SolverError as exc:
            if _STATE["debug"]:
                raise
            _solve_failed(exc)
        except PixmuscleError as exc:
            if _STATE["debug"]:
                raise
            typer.echo(f"error: {exc}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except OSError as exc:  # a file system refusing a write (disk full, read-only): one line too
            from .outdir import WRITE_ERRNOS, describe_os_error

            if _STATE["debug"] or exc.errno not in WRITE_ERRNOS:
                raise
            typer.echo(f"error: {describe_os_error(exc, verb=None)}", err=True)
            raise typer.Exit(EXIT_BAD_INPUT) from None
        except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM (see main)
            if not isinstance(exc, Interrupted):
                exc = Interrupted("SIGINT")
            typer.echo(exc.message(), err=True)
            raise typer.Exit(exc.exit_code) from None

    sig = inspect.signature(fn)
    wrapper.__signature__ = sig.replace(parameters=[*sig.parameters.values(), *_COMMAND_GLOBALS])
    wrapper.__annotations__ = {**fn.__annotations__, "verbose_": int, "quiet_": bool, "debug_": bool}
    return wrapper


def _version(value: bool) -> None:
    if value:
        typer.echo(f"pixmuscle {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    verbose: int = typer.Option(0, "--verbose", "-v", count=True, help=_VERBOSE_HELP, show_default=False),
    quiet: bool = typer.Option(False, "--quiet", "-q", help=_QUIET_HELP, show_default=False),
    debug: bool = typer.Option(False, "--debug", help=_DEBUG_HELP, show_default=False),
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version."),
) -> None:
    from .progress import setup_logging

    _STATE.update(debug=debug, verbose=verbose, quiet=quiet)
    setup_logging(-1 if quiet else verbose)


def _synthetic(config: Path) -> bool:
    from .pipeline import load_config

    return bool(load_config(config).synthetic)


def _config_folder(config: Path):
    """Stage files written inside record their input paths relative to the config file's folder too."""
    from .store import config_folder

    return config_folder(config.parent)


def _section(config: Path, name: str):
    from .pipeline import load_config

    return getattr(load_config(config), name)


@app.command()
@_guard
def segment(
    config: Path = typer.Option(..., "--config", "-c", help="YAML config with a `segment` section."),
    output: Path = typer.Option(Path("segmentation.h5"), "--output", "-o", help="Output HDF5 (also writes label/fibre NIfTI and QC PNGs beside it)."),
) -> None:
    """Segment MRI + DTI into a tissue label volume (Chan–Vese, multiphase Vese–Chan)."""
    mod = _load("pixmuscle.stages.segment")
    cfg = _section(config, "segment")
    if cfg is None:
        raise PixmuscleError(f"{config}: no `segment` section")
    with _config_folder(config):
        mod.run_segment(cfg, output, synthetic=_synthetic(config))
    _out(output)


@app.command("build-model")
@_guard
def build_model(
    segmentation: Path | None = typer.Argument(None, help=(
        "segmentation.h5 written by `pixmuscle segment` (default: the input named in the config's build_model "
        "section; with a `segment` section and no labels, segmentation.h5 in the current folder).")),
    config: Path = typer.Option(..., "--config", "-c", help="YAML config (its `build_model` section, may be empty)."),
    output: Path = typer.Option(Path("model.h5"), "--output", "-o", help="Output model HDF5."),
) -> None:
    """Turn a label volume (NIfTI or segmentation.h5) into a pixel-point model."""
    from .pipeline import load_config
    from .plan import _with_segmentation

    mod = _load("pixmuscle.stages.build_model")
    cfg = load_config(config)
    bm = cfg.build_model
    named = bm is not None and (getattr(bm, "labels", None) is not None or getattr(bm, "segmentation", None) is not None)
    if segmentation is None and not named and cfg.segment is not None:
        segmentation = Path("segmentation.h5")
    if segmentation is not None:
        if not segmentation.is_file():
            raise PixmuscleError(f"{segmentation}: segmentation file not found (run `pixmuscle segment --config "
                                 f"{config} -o {segmentation}` first)")
        bm = _with_segmentation(bm, segmentation.resolve(), cfg.base_dir)
    with _config_folder(config):
        mod.run_build_model(bm, output, synthetic=cfg.synthetic)
    _out(output)


@app.command()
@_guard
def coarsen(
    model: Path = typer.Argument(..., help="Input model.h5."),
    factor: int = typer.Option(2, "--factor", min=1, help="Keep every FACTOR-th pixel in-plane."),
    output: Path = typer.Option(Path("coarse.h5"), "--output", "-o", help="Output model HDF5."),
) -> None:
    """Coarse model: keep every second (FACTOR-th) pixel in-plane, slices unchanged."""
    mod = _load("pixmuscle.stages.coarsen")
    mod.run_coarsen(model, factor, output)
    _out(output)


@app.command()
@_guard
def solve(
    model: Path = typer.Argument(..., help="Input model.h5."),
    config: Path = typer.Option(..., "--config", "-c", help="YAML config with a `solve` section."),
    output: Path = typer.Option(Path("results.h5"), "--output", "-o", help="Output results HDF5."),
) -> None:
    """Finite-strain SCNI–RKPM solve: ramp activation, record reaction forces.

    Under ``mpiexec -n P`` (backend petsc) every rank runs this; rank 0 logs and writes the results.
    """
    from . import parallel

    mod = _load("pixmuscle.stages.solve")
    with parallel.abort_on_failure(), _config_folder(config):
        parallel.quiet_other_ranks()
        mod.run_solve(model, _section(config, "solve"), output, synthetic=_synthetic(config))
    if parallel.rank() == 0:
        _out(output)


@app.command()
@_guard
def report(
    results: Path = typer.Argument(..., help="Input results.h5."),
    output: Path | None = typer.Option(None, "--output", "-o", help=(
        "Output folder (default: <results stem>_report next to the results file).")),
    config: Path | None = typer.Option(None, "--config", "-c", help="YAML config with a `report` section (optional)."),
) -> None:
    """Force–activation curves, tissue table, ParaView fields, 3-D view, slices, HTML summary."""
    mod = _load("pixmuscle.stages.report")
    cfg = _section(config, "report") if config else None
    extra = {"synthetic": True} if config and _synthetic(config) else None
    index = mod.run_report(results, output, cfg, extra=extra)
    _out(index)


@app.command()
@_guard
def run(
    config: Path = typer.Argument(..., help="Pipeline YAML (one subject or a cohort)."),
    output: Path | None = typer.Option(None, "--output", "-o", help=(
        "Output folder (relative to the current folder), instead of the config's output_dir.")),
    set_: list[str] = typer.Option([], "--set", help=(
        "Override a config key, typed and checked like the file: --set solve.steps=5 "
        "--set 'solve.activation={from: 0, to: 0.5}' (repeatable).")),
    subject: str | None = typer.Option(None, "--subject", help="Run only this subject of a cohort."),
    force: bool = typer.Option(False, "--force", help="Redo stages even when their inputs are unchanged."),
    start: str | None = typer.Option(None, "--from", help="First stage: segment, build-model, coarsen, solve, report."),
    until: str | None = typer.Option(None, "--until", help="Last stage."),
    workers: int | None = typer.Option(None, "--workers", min=0, help=(
        "Run the cases on a local Dask cluster of N worker processes (0: one after the other in this process), "
        "instead of the config's execution section. Default: that section, else serial for one case and a local "
        "cluster sized to the machine for several.")),
    scheduler: str | None = typer.Option(None, "--scheduler", help=(
        "Address of an existing Dask scheduler (tcp://HOST:PORT), instead of the config's execution section.")),
    allow_stale: bool = typer.Option(False, "--allow-stale", help=(
        "With --from: go on even when a file of an earlier stage was made under another config (else the "
        "run is refused, naming the key); the report then shows the mismatch at the top.")),
) -> None:
    """Run segment → build-model → coarsen → solve → report, skipping up-to-date stages.

    A cohort (`subjects:`) or a parameter study (`study:`) runs its cases in parallel on Dask.
    Prints on stdout, one per line, each case's report (else its results files, else its
    folder), then the cohort/study pages.
    """
    from .pipeline import run_cases

    done = run_cases(config, force=force, start=start, until=until, workers=workers, scheduler=scheduler,
                     overrides=set_, output_dir=output, subject=subject, allow_stale=allow_stale)
    for s in done["summaries"]:
        made = [s["report"]] if s.get("report") else [p for p in s.get("results", {}).values() if Path(p).exists()]
        _out(*(made or [s["output_dir"]]))
    _out(*done["pages"])
    if done["failures"]:
        raise typer.Exit(1)


@app.command()
@_guard
def synth(
    output: Path = typer.Option(Path("data/synthetic"), "--output", "-o", help="Output folder."),
) -> None:
    """Regenerate the bundled SYNTHETIC phantoms (not patient data) deterministically."""
    mod = _load("pixmuscle.synth")
    mod.generate_samples(output)
    _out(output)


def _console():
    """Tables of the verify commands go to stderr with the logs (stdout holds the paths)."""
    from rich.console import Console

    return Console(stderr=True, soft_wrap=True)


@verify_app.command("rk")
@_guard
def verify_rk(output: Path = typer.Option(Path("out/verify"), "--output", "-o")) -> None:
    """RK convergence table (paper Fig. 3) and material transition (Fig. 4)."""
    from .verify.rk import verify_rk as _v

    res = _v(output, console=_console())
    _out(*res["figures"])


@verify_app.command("mechanics")
@_guard
def verify_mechanics(output: Path = typer.Option(Path("out/verify"), "--output", "-o")) -> None:
    """Patch test, uniaxial bar, isometric and oblique muscle blocks vs analytic solutions."""
    res = _load("pixmuscle.verify.mechanics").verify_mechanics(output, console=_console())
    _out(res["csv"], res["png"])
    if not res["all_ok"]:
        raise typer.Exit(1)


@verify_app.command("tendon")
@_guard
def verify_tendon(output: Path = typer.Option(Path("out/verify"), "--output", "-o")) -> None:
    """Paper Example 1: meshfree tendon vs a scikit-fem finite-element reference."""
    res = _load("pixmuscle.verify.mechanics").verify_tendon(output, console=_console())
    _out(res["csv"], res["png"])
    if not res["ok"]:
        raise typer.Exit(1)


def _on_sigterm(signum, frame) -> None:
    """SIGTERM (batch schedulers before they kill) is handled like Ctrl-C: the running stage's partial
    output is removed on the way out and the command ends with one line and exit code 143. A second
    SIGTERM during that clean-up is ignored."""
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    raise Interrupted("SIGTERM")


def main() -> None:  # console-script entry point
    signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        app()
    except SystemExit:
        raise
    except PixmuscleError as exc:
        if _STATE["debug"]:
            raise
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(EXIT_SOLVE_FAILED if isinstance(exc, SolverError) else EXIT_BAD_INPUT)


if __name__ == "__main__":
    main()
