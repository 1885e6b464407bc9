"""Command line of greybox.

``greybox demo tape-drive [--json] [--out DIR] [--force]``

The command line only parses arguments, calls public functions and prints or
saves their records. Bad input ends with one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import json
import sys

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
    lines.append(f"  greybox selects: {t3.selected} (BIC over subsystem orders 0..3)")
    return "\n".join(lines)


def _demo_tape_drive(args) -> int:
    from .io import atomic_write_json, prepare_output_dir, save_figure
    from .reproduce import reproduce_table2, reproduce_table3

    out = prepare_output_dir(args.out, force=args.force, kind="demo")
    t2 = reproduce_table2()
    t3 = reproduce_table3(t2)
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
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        print(_fmt_table2(t2))
        print()
        print(_fmt_table3(t3))
        for name, path in figures.items():
            print(f"saved {name}: {path}")
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
