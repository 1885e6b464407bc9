"""Command line of greybox.

``greybox demo tape-drive|motor-pump [--json] [--out DIR] [--force] [--no-plots] [--quiet]``
``greybox update MODEL.json ESTIMATION.csv --validate VALIDATION.csv [--out DIR] [--json]
[--force] [--no-plots] [--quiet]``
``greybox fleet MODEL.json UNITS_DIR --out DIR [--workers N] [--scheduler ADDRESS] [--force]
[--timeout S] [--json] [--quiet]`` (exit code 3 when some units failed)

The command line only parses arguments, calls public functions and prints or
saves their records. Bad input ends with one line on stderr and exit code 2;
Ctrl-C with one line and exit code 130 (while the package imports too,
through the ``greybox_cli`` entry module). Every precondition (input files,
output folder writable) is checked before computing. Under ``--json`` stdout
holds the JSON document alone (strict: no NaN or Infinity); warnings,
progress and anything a numerical library prints go to stderr. A report
folder is written into a temporary folder beside the target and renamed into
place at the end, so an interrupted run leaves the old report or the new one.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings
from pathlib import Path

import numpy as np

from .exceptions import GreyboxError

__all__ = ["main"]


def _pct(v: float, fmt: str) -> str:
    """A percentage, or "n/a" when it is undefined (NaN)."""
    return "n/a" if not np.isfinite(v) else format(v, fmt)


def _fmt_table2(t2) -> str:
    s = t2.setting
    lines = [
        "Table II - estimation error EE (eq. 42, relative RMS, mean over 6 outputs)",
        f"  setting: {s.nsteps} samples at Ts = {s.dt:g} s, voltages {s.amplitude:g} V std "
        f"low-passed at {s.bandwidth:g} Hz, truth with "
        f"{'process and ' if s.process_noise else ''}measurement noise, seed {s.seed}",
        f"  {'filter':<34}{'EE ours [%]':>12}{'EE paper [%]':>14}",
        f"  {'Kalman filter (ignores tension)':<34}{t2.kalman_filter_ee:>12.2f}{29.5:>14.1f}",
        f"  {'unknown-input filter':<34}{t2.unknown_input_filter_ee:>12.2f}{0.2:>14.1f}",
        f"  tension: RMS {t2.tension_rms:.3f} N, estimate RMS error {t2.tension_rmse:.3f} N, "
        f"95% interval covers the truth in {100 * t2.tension_ci95_coverage:.1f}% of samples",
    ]
    return "\n".join(lines)


def _fmt_table3(t3) -> str:
    paper = {"initial": (6, 38.6, 26.4), "dynamic": (7, 5.2, 0.3), "parallel": (12, 6.7, 4.5)}
    lines = [
        "Table III - validation on fresh data (eq. 42, relative RMS, mean over 6 outputs)",
        f"  {'model':<26}{'order':>6}{'SE [%]':>9}{'PE [%]':>9}"
        f"{'paper order/SE/PE':>22}",
    ]
    for name, v in t3.rows.items():
        ref = paper.get(name)
        ref_s = f"{ref[0]} / {ref[1]} / {ref[2]}" if ref else "-"
        lines.append(f"  {name:<26}{v.order:>6}{_pct(v.se.value, '>9.2f'):>9}"
                     f"{_pct(v.pe.value, '>9.2f'):>9}{ref_s:>22}")
    lines.append(f"  greybox selects: {t3.selected} (orders 0..2, see identify_subsystem)")
    lines += [f"  {note}" for note in t3.notes]
    return "\n".join(lines)


class _Run:
    """What every subcommand shares: quiet stdout, progress, the staged output folder."""

    def __init__(self, args):
        self.args = args
        self.stage = None
        self.inputs = ()  # input files: never moved or removed with an old output
        self.progress = None
        if not args.quiet:  # a rewritten line on a terminal, whole lines in a log (CI)
            from .progress import LogProgress, TerminalProgress

            self.progress = TerminalProgress() if sys.stderr.isatty() else LogProgress()

    @contextlib.contextmanager
    def computing(self):
        """stdout (file descriptor 1) sent to stderr while computing.

        Fortran and C libraries (LAPACK's XERBLA, SLICOT) print on the file
        descriptor, bypassing ``sys.stdout``: under ``--json`` nothing but
        the document may reach stdout.
        """
        sys.stdout.flush()
        try:
            saved = os.dup(1)
        except OSError:  # pragma: no cover - no file descriptor 1
            yield
            return
        try:
            os.dup2(2, 1)
            yield
        finally:
            sys.stdout.flush()
            os.dup2(saved, 1)
            os.close(saved)
            if self.progress is not None:
                self.progress.close()

    def stage_dir(self) -> Path:
        from .io import stage_output_dir

        self.stage = stage_output_dir(self.args.out)
        return self.stage

    def commit(self, kind: str, names) -> Path:
        from .io import commit_output_dir

        out = commit_output_dir(self.stage, self.args.out, kind=kind, names=names,
                                force=self.args.force, inputs=self.inputs)
        self.stage = None
        return out

    def cleanup(self) -> None:
        from .io import discard_output_dir

        discard_output_dir(self.stage)
        self.stage = None


def _save(fig_path_pairs, figures, stage, final):
    """Save figures into the staging folder; record their final paths."""
    import matplotlib.pyplot as plt

    from .io import save_figure

    for key, fig in fig_path_pairs:
        save_figure(fig, stage / f"{key}.png")
        figures[key] = str(Path(final) / f"{key}.png")
        plt.close(fig)


def _demo_tape_drive(args, run: _Run) -> int:
    from .io import atomic_write_json, check_output_dir, dumps_json
    from .reproduce import reproduce_table2, reproduce_table3

    check_output_dir(args.out, force=args.force, kind="demo")  # fail fast, create nothing
    with run.computing():
        t2 = reproduce_table2()
        t3 = reproduce_table3(t2)
        summary = {"table2": t2.as_dict(), "table3": t3.as_dict()}
        figures = {}
        stage = run.stage_dir()
        if not args.no_plots:
            import matplotlib

            matplotlib.use("Agg")
            from .plotting import plot_residual_autocorrelation, plot_unknown_input

            arts = plot_unknown_input(t2.uif, "T", d_true=t2.tension, window=(1750, 2250))
            arts["ax"].set_title("Fig. 1: true and estimated tape tension")
            arts["ax"].set_ylabel("tape tension T [N]")
            _save([("fig1_tension", arts["figure"])], figures, stage, args.out)
            arts = plot_residual_autocorrelation([t3.rows["initial"], t3.rows[t3.selected]])
            _save([("fig2_autocorrelation", arts["figure"])], figures, stage, args.out)
            figures = {"fig1": figures.get("fig1_tension"),
                       "fig2": figures.get("fig2_autocorrelation")}
        summary["figures"] = figures
        atomic_write_json(stage / "summary.json", summary)
        run.commit("demo", ["summary.json", *figures.values()])
    if args.json:
        print(dumps_json(summary))
    else:
        print(_fmt_table2(t2))
        print()
        print(_fmt_table3(t3))
        for name, path in figures.items():
            print(f"saved {name}: {path}")
    return 0


def _fmt_table5(t5) -> str:
    s = t5.setting
    lines = [
        "Table V - motor-pump, estimation error EE (eq. 42, relative RMS, mean over 3 outputs)",
        f"  setting: {s.nsteps} samples at Ts = {s.dt:g} s, V = {s.voltage:g} V + "
        f"{s.voltage_std:g} V std below {s.bandwidth:g} Hz, load h_r = {s.load_mean:g} + "
        f"{s.load_amplitude:g} sin(2 pi {s.load_frequency:g} t) + {s.load_step:g} step, "
        f"seed {s.seed}",
        f"  {'filter':<40}{'EE ours [%]':>12}{'EE paper [%]':>14}",
        f"  {'UKF ignoring the pump load':<40}{t5.ukf_ee:>12.3f}{1.4:>14.2f}",
        f"  {'unknown-input UKF':<40}{t5.ui_ukf_ee:>12.3f}{0.05:>14.2f}",
        f"  {f'ensemble unknown-input filter ({s.nmembers})':<40}{t5.ensemble_ee:>12.3f}"
        f"{'-':>14}",
        f"  pump load h_r^ = -d^/Mdot^^2: RMS error {t5.hr_rms_error:.2f}, bias "
        f"{t5.hr_bias_pct:+.3f} % (G = [0 0 Ts], d = 0 as printed: {t5.hr_bias_pct_paper_form:+.2f} "
        f"%), 95% band covers the truth in {100 * t5.hr_ci95_coverage:.1f}% of samples",
    ]
    return "\n".join(lines)


def _demo_motor_pump(args, run: _Run) -> int:
    from .io import atomic_write_json, check_output_dir, dumps_json
    from .reproduce import reproduce_table5

    check_output_dir(args.out, force=args.force, kind="demo")  # fail fast, create nothing
    with run.computing():
        t5 = reproduce_table5()
        summary = {"table5": t5.as_dict()}
        figures = {}
        stage = run.stage_dir()
        if not args.no_plots:
            import matplotlib

            matplotlib.use("Agg")
            from .plotting import plot_pump_load

            arts = plot_pump_load(t5)
            _save([("fig3_pump_load", arts["figure"])], figures, stage, args.out)
            figures = {"fig3": figures.get("fig3_pump_load")}
        summary["figures"] = figures
        atomic_write_json(stage / "summary.json", summary)
        run.commit("demo", ["summary.json", *figures.values()])
    if args.json:
        print(dumps_json(summary))
    else:
        print(_fmt_table5(t5))
        for name, path in figures.items():
            print(f"saved {name}: {path}")
    return 0


#: Example name -> function(args, run) of ``greybox demo``; add new demos here.
DEMOS = {"tape-drive": _demo_tape_drive, "motor-pump": _demo_motor_pump}


def _demo(args, run: _Run) -> int:
    return DEMOS[args.example](args, run)


def _fmt_update(rep) -> str:
    lines = [rep.message, f"criterion: {rep.criterion}"]
    if rep.effect.kind != "none":
        lines.append(f"effect ({rep.effect.kind}, order {rep.effect.order}): {rep.effect.formula}")
        lines += [f"  {s}" for s in rep.effect.parameter_notes]
    lines.append(f"  {'model':<24}{'order':>6}{'SE [%]':>10}{'PE [%]':>10}{'white':>7}")
    for name, v in rep.table.items():
        lines.append(f"  {name:<24}{v.order:>6}{_pct(v.se.value, '>10.3g'):>10}"
                     f"{_pct(v.pe.value, '>10.3g'):>10}"
                     f"{'yes' if v.whiteness.all_white else 'no':>7}")
    lines += [f"note ({d.stage}): {d}" for d in rep.decisions]
    return "\n".join(lines)


def _report_markdown(rep, figures) -> str:
    """The report an engineer reads in ten seconds: the verdict, one line per effect, the
    before/after table and the figures first; the evidence and the decision trail after."""
    out = ["# greybox update report", "", f"**{rep.message.split('; ')[0]}**", "",
           rep.message, ""]
    effects = [st.effect for st in rep.steps] if len(rep.steps) > 1 else \
        ([rep.effect] if rep.effect.kind != "none" else [])
    if effects:
        out += ["## Effects" + ("" if rep.recommended else " (proposed, not recommended)"), ""]
        out += [f"{i + 1}. {e.kind} (order {e.order}) in {e.channel or '-'}: `{e.formula}`"
                for i, e in enumerate(effects)]
        out += [f"   - {s}" for e in effects for s in e.parameter_notes]
        out.append("")
    out += ["## Validation data: before and after (eq. 42, relative RMS)", "",
            "| model | order | SE [%] | PE [%] | residual white |", "|---|---|---|---|---|"]
    for name, v in rep.table.items():
        out.append(f"| {name} | {v.order} | {_pct(v.se.value, '.3g')} | "
                   f"{_pct(v.pe.value, '.3g')} | "
                   f"{'yes' if v.whiteness.all_white else 'no'} |")
    out += ["", "## Figures", ""] + [f"![{k}]({Path(v).name})" for k, v in figures.items()]
    out += ["", "## Residual of the nominal model (estimation data)", "",
            "| output | Ljung-Box p |", "|---|---|"]
    labels = list(rep.nominal.output_labels)
    out += [f"| {labels[i]} | {p:.3g} |" for i, p in enumerate(rep.residual.pvalue)]
    out += ["", "## Decision trail", "", f"Selection criterion: {rep.criterion}.", ""]
    if rep.candidates:
        out += ["| candidate | kind | order | estimation SE [%] | parameters | status |",
                "|---|---|---|---|---|---|"]
        out += [f"| {c.channel} | {c.kind} | {c.order} | {_pct(c.se_estimation, '.3g')} | "
                f"{c.npar} | {c.status}{': ' + c.reason if c.reason else ''} |"
                for c in rep.candidates]
        out.append("")
    out += [f"- *{d.stage}*{' ' + d.subject if d.subject else ''}: {d.reason}"
            for d in rep.decisions]
    return "\n".join(out) + "\n"


def _warn(msg: str) -> None:
    print(f"greybox: warning: {msg}", file=sys.stderr)


def _update(args, run: _Run) -> int:
    from .io import atomic_write_json, atomic_write_text, check_output_dir, dumps_json
    from .model_io import model_to_dict, read_csv, read_model
    from .workflow import close_the_loop

    # every precondition first: the output folder, then all input files
    run.inputs = (args.model, args.estimation, args.validate)
    check_output_dir(args.out, force=args.force, kind="report", inputs=run.inputs)
    spec = read_model(args.model)
    ins, outs = list(spec.sys.input_labels), list(spec.sys.output_labels)
    y, u = read_csv(args.estimation, inputs=ins, outputs=outs, Ts=spec.Ts)
    yv, uv = read_csv(args.validate, inputs=ins, outputs=outs, Ts=spec.Ts, min_steps=100)
    # close_the_loop warns when the validation data are the estimation data
    with run.computing():
        rep = close_the_loop(spec.sys, y, u, yv, uv, Q=spec.Q, R=spec.R, dt=spec.Ts,
                             channels=spec.channels, progress=run.progress,
                             delta=not args.no_baseline)
        stage = run.stage_dir()
        figures = {}
        if not args.no_plots:
            import matplotlib

            matplotlib.use("Agg")
            from .plotting import (
                plot_dynamic_law,
                plot_law,
                plot_outputs,
                plot_residual_autocorrelation,
                plot_unknown_input,
            )

            rows = [rep.table["nominal"]] + ([rep.table["updated"]] if rep.updated else [])
            figs = [("autocorrelation", plot_residual_autocorrelation(rows)["figure"]),
                    ("outputs", plot_outputs(yv, list(rep.table.values()), dt=spec.Ts)["figure"])]
            if rep.trace is not None and rep.trace.filter_result is not None:
                arts = plot_unknown_input(rep.trace.filter_result, 0)
                figs.append(("d_estimate", arts["figure"]))
            law = getattr(rep.effect, "law", None) if rep.updated else None
            if law is not None and law.output is None and rep.trace is not None:
                # the figure that explains a static law: d^ against the law's variable
                figs.insert(0, ("law", plot_law(rep, u)["figure"]))
            elif rep.updated and rep.effect.kind == "dynamic" and (
                    rep.effect.dynamic_law is not None or rep.effect.subsystem is not None):
                # a dynamic law's: its frequency response with the 95 % band
                figs.insert(0, ("law", plot_dynamic_law(rep)["figure"]))
            _save(figs, figures, stage, args.out)
        summary = rep.as_dict()
        summary["figures"] = figures
        summary["updated_model"] = str(Path(args.out) / "updated_model.json")
        atomic_write_json(stage / "updated_model.json",
                          model_to_dict(rep.model.sys, rep.model.Q, rep.model.R))
        atomic_write_json(stage / "summary.json", summary)
        atomic_write_text(stage / "report.md", _report_markdown(rep, figures))
        out = run.commit("report", ["updated_model.json", "summary.json", "report.md",
                                    *figures.values()])
    if args.json:
        print(dumps_json(summary))
    else:
        print(_fmt_update(rep))
        print(f"report: {out / 'report.md'}")
    return 0 if rep.recommended else NOT_RECOMMENDED


#: Exit code of ``greybox update`` when the update found is worse on the validation data
#: than the nominal model: the report is written, but no model is handed over as better.
NOT_RECOMMENDED = 4


def _fleet(args, run: _Run) -> int:
    from .fleet import EXIT_FAILED, fleet
    from .io import dumps_json

    def show(p):
        print(f"greybox: [{p.k}/{p.K}] {p.stage}", file=sys.stderr, flush=True)

    with run.computing():
        rep = fleet(args.model, args.units, out=args.out, client=args.scheduler,
                    workers=args.workers, force=args.force, timeout=args.timeout,
                    progress=None if args.quiet else show)
    if args.json:
        print(dumps_json(rep.as_dict()))
    else:
        print(rep.answer)
        print(f"report: {Path(rep.out) / 'fleet.md'}")
    return EXIT_FAILED if rep.failed else 0


_FLEET_EPILOG = """\
UNITS_DIR holds one sub-folder per unit (its name is the unit's name) with
estimation.csv and validation.csv, or is a manifest CSV with the header
unit,estimation,validation (paths relative to the manifest). Each unit's
result is written to DIR/units/<unit>.json as it arrives; a rerun skips the
units done before (same files, same model) unless --force, and tries failed
units again; Ctrl-C keeps every unit finished. DIR/fleet.md opens with the
answer. Needs Dask: pip install "greybox[fleet]".

exit codes: 0 every unit done, 3 some units failed (each with its line in
fleet.md), 2 bad input (nothing written), 130 interrupted.
"""


def _common(p: argparse.ArgumentParser, default_out: str, what: str) -> None:
    p.add_argument("--json", action="store_true", help="print the JSON summary only")
    p.add_argument("--out", default=default_out, help=f"{what} (default: %(default)s)")
    p.add_argument("--force", action="store_true",
                   help="replace a previous greybox output in that folder (files you added "
                        "to it are kept; a folder greybox did not write is never used)")
    p.add_argument("--no-plots", action="store_true", help="skip the figures")
    p.add_argument("--quiet", action="store_true",
                   help="no progress on stderr (on a terminal one rewritten line, else a "
                        "line at most every 10 s)")


_UPDATE_EPILOG = """\
MODEL.py (a nonlinear nominal model) is a Python file that defines:
  model     control.nlsys(f, h, states=[...], inputs=[...], outputs=[...]):
            continuous (then Ts is needed) or discrete (dt = Ts); the output
            map must be linear, y = C x + D u (or a control.StateSpace)
  Q, R      process- and measurement-noise covariances (discrete model)
  Ts        sampling period of the data [s]
  channels  optional candidate channels, as in MODEL.json
The file is executed: use only files you trust. A nonlinear model is
discretized with RK4 (inputs held over the sample), residuals come from its
UKF, channels are traced with the unknown-input UKF and static laws only
(d = law(x, u)); the report's rows simulate the nonlinear models, and
updated_model.json holds the updated model's linearization at the stated
operating point (summary.json "nonlinear"), since a Python f cannot be
written as JSON: the law itself is in the effect's formula.
"""


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="greybox", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="reproduce one of the paper's examples")
    demo.add_argument("example", choices=sorted(DEMOS), help="which example")
    _common(demo, "greybox-demo-output", "folder for figures and summary.json")
    demo.set_defaults(func=_demo)
    upd = sub.add_parser(
        "update", help="find, trace and add the effect a model lacks, from measured data",
        description="Find, trace and add the effect a model lacks, from measured data.",
        epilog=_UPDATE_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    upd.add_argument("model", help="MODEL.json (a linear model; schema: greybox.model_io) or "
                                   "MODEL.py (executed: it defines model, a "
                                   "control.NonlinearIOSystem or StateSpace, Q, R and Ts)")
    upd.add_argument("estimation", help="estimation data CSV (header: inputs, outputs, "
                                        "optional time)")
    upd.add_argument("--validate", required=True, metavar="VALIDATION.csv",
                     help="validation data CSV, same columns")
    upd.add_argument("--no-baseline", action="store_true",
                     help="skip the parallel delta baseline (a comparison row of the report; "
                          "its cost is bounded by the trace's time anyway)")
    _common(upd, "greybox-update-report", "report folder")
    upd.set_defaults(func=_update)
    flt = sub.add_parser(
        "fleet", help="close the loop on every unit of a fleet (Dask); report across units",
        description="Close the loop on every unit of a fleet of one design, in parallel on "
                    "Dask, and report which units deviate from the model and how.",
        epilog=_FLEET_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    flt.add_argument("model", metavar="MODEL.json",
                     help="the design's nominal model (MODEL.json, or MODEL.py)")
    flt.add_argument("units", metavar="UNITS_DIR",
                     help="folder with one sub-folder per unit, or a manifest CSV")
    flt.add_argument("--out", default="greybox-fleet-report", metavar="DIR",
                     help="report folder, reused by a rerun (default: %(default)s)")
    flt.add_argument("--workers", type=int, metavar="N",
                     help="worker processes of the local cluster (default: one per core)")
    flt.add_argument("--scheduler", metavar="ADDRESS",
                     help="use the Dask cluster at ADDRESS (tcp://host:8786) instead")
    flt.add_argument("--force", action="store_true", help="compute every unit again")
    flt.add_argument("--timeout", type=float, metavar="S",
                     help="give up on a unit after S seconds (it is reported as failed)")
    flt.add_argument("--json", action="store_true", help="print the JSON report only")
    flt.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    flt.set_defaults(func=_fleet)
    return p


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split()) or type(e).__name__


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``greybox`` command; returns the exit code.

    Parameters
    ----------
    argv : list of str, optional
        Arguments (default: ``sys.argv[1:]``).

    Returns
    -------
    int
        0 on success, 2 on bad input, 3 when ``greybox fleet`` could not do some
        units (the others are reported), 4 when ``greybox update`` found an update
        that predicts the validation data worse than the nominal model ("not
        recommended": the report is written, the nominal model kept), 130 when
        interrupted (Ctrl-C).
    """
    parser = _parser()
    args = parser.parse_args(argv)
    run = _Run(args)
    show = warnings.showwarning

    def _show(message, category, filename, lineno, file=None, line=None):
        _warn(_one_line(message))

    try:
        warnings.showwarning = _show
        return args.func(args, run)
    except KeyboardInterrupt:
        print("greybox: interrupted", file=sys.stderr)
        return 130
    except (GreyboxError, OSError) as e:
        print(f"greybox: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except np.linalg.LinAlgError as e:
        print(f"greybox: error: numerical failure ({_one_line(e)}); check the model's units "
              f"and scaling", file=sys.stderr)
        return 2
    finally:
        warnings.showwarning = show
        run.cleanup()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
