"""Command line of greybox.

``greybox demo tape-drive [--json] [--out DIR] [--force]``
``greybox update MODEL.json ESTIMATION.csv --validate VALIDATION.csv [--out DIR] [--json] [--force]``

The command line only parses arguments, calls public functions and prints or
saves their records. Bad input ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from .exceptions import GreyboxError

__all__ = ["main"]


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
        lines.append(f"  {name:<26}{v.order:>6}{v.se.value:>9.2f}{v.pe.value:>9.2f}{ref_s:>22}")
    lines.append(f"  greybox selects: {t3.selected} (orders 0..2, see identify_subsystem)")
    lines += [f"  {note}" for note in t3.notes]
    return "\n".join(lines)


def _demo_tape_drive(args) -> int:
    from .io import atomic_write_json, check_output_dir, prepare_output_dir, record_outputs
    from .io import save_figure
    from .reproduce import reproduce_table2, reproduce_table3

    check_output_dir(args.out, force=args.force, kind="demo")  # fail fast, create nothing
    t2 = reproduce_table2()
    t3 = reproduce_table3(t2)
    out = prepare_output_dir(args.out, force=args.force, kind="demo")
    summary = {"table2": t2.as_dict(), "table3": t3.as_dict()}
    figures = {}
    if not args.no_plots:
        import matplotlib

        matplotlib.use("Agg")
        from .plotting import plot_unknown_input

        arts = plot_unknown_input(t2.uif, "T", d_true=t2.tension, window=(1750, 2250))
        arts["ax"].set_title("Fig. 1: true and estimated tape tension")
        arts["ax"].set_ylabel("tape tension T [N]")
        path = out / "fig1_tension.png"
        save_figure(arts["figure"], path)
        figures["fig1"] = str(path)
        import matplotlib.pyplot as plt

        plt.close(arts["figure"])
        from .plotting import plot_residual_autocorrelation

        arts = plot_residual_autocorrelation([t3.rows["initial"], t3.rows[t3.selected]])
        path = out / "fig2_autocorrelation.png"
        save_figure(arts["figure"], path)
        figures["fig2"] = str(path)
        plt.close(arts["figure"])
    summary["figures"] = figures
    atomic_write_json(out / "summary.json", summary)
    record_outputs(out, "demo", ["summary.json", *figures.values()])
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_fmt_table2(t2))
        print()
        print(_fmt_table3(t3))
        for name, path in figures.items():
            print(f"saved {name}: {path}")
    return 0


def _fmt_update(rep) -> str:
    lines = [rep.message, f"criterion: {rep.criterion}"]
    if rep.effect.kind != "none":
        lines.append(f"effect ({rep.effect.kind}, order {rep.effect.order}): {rep.effect.formula}")
        lines += [f"  {s}" for s in rep.effect.parameter_notes]
    lines.append(f"  {'model':<24}{'order':>6}{'SE [%]':>10}{'PE [%]':>10}{'white':>7}")
    for name, v in rep.table.items():
        lines.append(f"  {name:<24}{v.order:>6}{v.se.value:>10.3g}{v.pe.value:>10.3g}"
                     f"{'yes' if v.whiteness.all_white else 'no':>7}")
    lines += [f"  {s}" for s in rep.notes if s.startswith("parallel model")]
    return "\n".join(lines)


def _report_markdown(rep, figures) -> str:
    out = ["# greybox update report", "", rep.message, "",
           f"Selection criterion: {rep.criterion}.", "",
           "## Residual of the nominal model (estimation data)", "",
           "| output | Ljung-Box p |", "|---|---|"]
    labels = list(rep.nominal.output_labels)
    out += [f"| {labels[i]} | {p:.3g} |" for i, p in enumerate(rep.residual.pvalue)]
    out += ["", "## Effect", "", f"- kind: {rep.effect.kind}, order {rep.effect.order}",
            f"- channel: {rep.effect.channel or '-'}", f"- formula: `{rep.effect.formula}`"]
    out += [f"- {s}" for s in rep.effect.parameter_notes]
    out += [f"- note: {s}" for s in rep.notes]
    out += ["", "## Validation data: before and after (eq. 42, relative RMS)", "",
            "| model | order | SE [%] | PE [%] | residual white |", "|---|---|---|---|---|"]
    for name, v in rep.table.items():
        out.append(f"| {name} | {v.order} | {v.se.value:.3g} | {v.pe.value:.3g} | "
                   f"{'yes' if v.whiteness.all_white else 'no'} |")
    out += ["", "## Figures", ""] + [f"![{k}]({Path(v).name})" for k, v in figures.items()]
    return "\n".join(out) + "\n"


def _update(args) -> int:
    from .io import (
        atomic_write_json,
        atomic_write_text,
        check_output_dir,
        prepare_output_dir,
        record_outputs,
        save_figure,
    )
    from .model_io import model_to_dict, read_csv, read_model
    from .workflow import close_the_loop

    check_output_dir(args.out, force=args.force, kind="report")  # fail fast, create nothing
    spec = read_model(args.model)
    ins, outs = list(spec.sys.input_labels), list(spec.sys.output_labels)
    y, u = read_csv(args.estimation, inputs=ins, outputs=outs, Ts=spec.Ts)
    yv, uv = read_csv(args.validate, inputs=ins, outputs=outs, Ts=spec.Ts, min_steps=100)
    rep = close_the_loop(spec.sys, y, u, yv, uv, Q=spec.Q, R=spec.R, dt=spec.Ts,
                         channels=spec.channels)
    out = prepare_output_dir(args.out, force=args.force, kind="report")
    figures = {}
    if not args.no_plots:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        from .plotting import plot_outputs, plot_residual_autocorrelation, plot_unknown_input

        rows = [rep.table["nominal"]] + ([rep.table["updated"]] if rep.updated else [])
        arts = plot_residual_autocorrelation(rows)
        figures["autocorrelation"] = out / "autocorrelation.png"
        save_figure(arts["figure"], figures["autocorrelation"])
        plt.close(arts["figure"])
        arts = plot_outputs(yv, list(rep.table.values()), dt=spec.Ts)
        figures["outputs"] = out / "outputs.png"
        save_figure(arts["figure"], figures["outputs"])
        plt.close(arts["figure"])
        if rep.trace is not None and rep.trace.filter_result is not None:
            arts = plot_unknown_input(rep.trace.filter_result, 0)
            figures["d_estimate"] = out / "d_estimate.png"
            save_figure(arts["figure"], figures["d_estimate"])
            plt.close(arts["figure"])
    summary = rep.as_dict()
    summary["figures"] = {k: str(v) for k, v in figures.items()}
    summary["updated_model"] = str(out / "updated_model.json")
    atomic_write_json(out / "updated_model.json",
                      model_to_dict(rep.model.sys, rep.model.Q, rep.model.R))
    atomic_write_json(out / "summary.json", summary)
    atomic_write_text(out / "report.md", _report_markdown(rep, figures))
    record_outputs(out, "report", ["updated_model.json", "summary.json", "report.md",
                                   *figures.values()])
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_fmt_update(rep))
        print(f"report: {out / 'report.md'}")
    return 0


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="greybox", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="reproduce one of the paper's examples")
    demo.add_argument("example", choices=["tape-drive"], help="which example")
    demo.add_argument("--json", action="store_true", help="print a JSON summary only")
    demo.add_argument("--out", default="greybox-demo-output",
                      help="folder for figures and summary.json (default: %(default)s)")
    demo.add_argument("--force", action="store_true",
                      help="write into --out even if it holds files greybox did not write")
    demo.add_argument("--no-plots", action="store_true", help="skip the figures")
    demo.set_defaults(func=_demo_tape_drive)
    upd = sub.add_parser("update", help="find, trace and add the effect a model lacks, "
                                        "from measured data")
    upd.add_argument("model", help="MODEL.json (schema: greybox.model_io)")
    upd.add_argument("estimation", help="estimation data CSV (header: inputs, outputs, "
                                        "optional time)")
    upd.add_argument("--validate", required=True, metavar="VALIDATION.csv",
                     help="validation data CSV, same columns")
    upd.add_argument("--out", default="greybox-update-report",
                     help="report folder (default: %(default)s)")
    upd.add_argument("--json", action="store_true", help="print the JSON summary")
    upd.add_argument("--force", action="store_true", help="overwrite an existing report")
    upd.add_argument("--no-plots", action="store_true", help="skip the figures")
    upd.set_defaults(func=_update)
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``greybox`` command; returns the exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (GreyboxError, OSError) as e:
        print(f"greybox: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
