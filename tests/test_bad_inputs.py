"""Every bad input tried on ``greybox update``, one parametrized row each (issue 13).

Each row mutates a small, valid case (a damped two-state oscillator, 400
samples, the right model) and states the outcome: exit code 2 with one line
on stderr naming the problem and nothing written, or exit code 0 with a
clearly worded warning where the input is legal but suspicious. The table
may only grow.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import greybox as gb
from greybox._validation import check_records
from greybox.cli import main
from greybox.model_io import model_to_dict
from greybox.system import named_ss

TS = 0.05
N = 400


def _model_dict():
    A = np.array([[0.0, 1.0], [-4.0, -0.8]])
    B = np.array([[0.0], [1.0]])
    sys = named_ss(A, B, np.eye(2), np.zeros((2, 1)), 0, states=["x", "v"], inputs=["F"],
                   outputs=["x", "v"], name="osc")
    return model_to_dict(sys, np.diag([1e-10, 1e-8]), 1e-4 * np.eye(2), Ts=TS)


def _data(seed, n=N, unstable=False):
    """Noisy response of the oscillator (ZOH, exact) to a random staircase input."""
    import scipy.linalg as sla

    A = np.array([[0.0, 1.0], [4.0 if unstable else -4.0, -0.8]])
    M = sla.expm(np.block([[A, np.array([[0.0], [1.0]])], [np.zeros((1, 3))]]) * TS)
    Ad, Bd = M[:2, :2], M[:2, 2:]
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.standard_normal((1, n // 10 + 1)), 10, axis=1)[:, :n]
    x = np.zeros(2)
    y = np.empty((2, n))
    K = np.array([[12.0, 4.0]]) if unstable else np.zeros((1, 2))
    for k in range(n):
        y[:, k] = x + 1e-2 * rng.standard_normal(2)
        if unstable:  # closed loop around the unstable plant
            u[:, k] = u[:, k] - K @ y[:, k]
        x = Ad @ x + Bd @ u[:, k]
    return y, u


def _csv_text(y, u, *, time=True, names=("F", "x", "v")):
    cols = (["time"] if time else []) + list(names)
    data = np.vstack(([np.arange(y.shape[1]) * TS] if time else []) + [u, y])
    return "\n".join([",".join(cols)] + [",".join(f"{v:.10g}" for v in r) for r in data.T]) + "\n"


class Case:
    """Paths of a valid case; rows mutate its files before the run."""

    def __init__(self, tmp_path: Path):
        self.dir = tmp_path
        self.model = tmp_path / "model.json"
        self.est = tmp_path / "est.csv"
        self.val = tmp_path / "val.csv"
        self.out = tmp_path / "report"
        self.d = _model_dict()
        self.model.write_text(json.dumps(self.d))
        y, u = _data(1)
        yv, uv = _data(2)
        self.est.write_text(_csv_text(y, u))
        self.val.write_text(_csv_text(yv, uv))
        self.extra_args: list[str] = []
        self.cwd: Path | None = None  # the working folder of the run (default: unchanged)

    def set(self, **kw):
        d = dict(self.d)
        for k, v in kw.items():
            if v is _DROP:
                d.pop(k)
            else:
                d[k] = v
        self.model.write_text(json.dumps(d))

    def lines(self, which="est"):
        return (self.est if which == "est" else self.val).read_text().splitlines()

    def put(self, lines, which="est"):
        (self.est if which == "est" else self.val).write_text("\n".join(lines) + "\n")

    def argv(self):
        return ["update", str(self.model), str(self.est), "--validate", str(self.val),
                "--out", str(self.out), "--no-plots", *self.extra_args]


_DROP = object()


def _cell(c: Case, row: int, col: int, value: str, which="est"):
    lines = c.lines(which)
    cells = lines[row].split(",")
    cells[col] = value
    lines[row] = ",".join(cells)
    c.put(lines, which)


def _raw_model(c: Case, text: str | bytes):
    if isinstance(text, bytes):
        c.model.write_bytes(text)
    else:
        c.model.write_text(text)


def _channels(c: Case, chans):
    c.set(channels=chans)


def _out_file(c: Case):
    c.out.write_text("not a folder")


def _out_foreign(c: Case):
    c.out.mkdir()
    (c.out / "thesis.tex").write_text("mine")


def _out_under_file(c: Case):
    (c.dir / "afile").write_text("x")
    c.out = c.dir / "afile" / "report"


def _no_inputs(c: Case):
    A = np.array(c.d["A"])
    sys = named_ss(A, np.zeros((2, 0)), np.eye(2), np.zeros((2, 0)), 0, states=["x", "v"],
                   inputs=[], outputs=["x", "v"])
    d = model_to_dict(sys, np.diag([1e-10, 1e-8]), 1e-4 * np.eye(2), Ts=TS)
    del d["B"], d["D"]
    c.model.write_text(json.dumps(d))
    rng = np.random.default_rng(5)
    for path in (c.est, c.val):  # a free response plus noise: no input column
        y = np.empty((2, N))
        x = np.array([1.0, 0.0])
        import scipy.linalg as sla

        Ad = sla.expm(A * TS)
        for k in range(N):
            y[:, k] = x + 1e-2 * rng.standard_normal(2)
            x = Ad @ x
        path.write_text(_csv_text(y, np.zeros((0, N)), names=("x", "v")))


def _unstable(c: Case):
    d = dict(c.d)
    d["A"] = [[0.0, 1.0], [4.0, -0.8]]
    c.model.write_text(json.dumps(d))
    y, u = _data(1, unstable=True)
    yv, uv = _data(2, unstable=True)
    c.est.write_text(_csv_text(y, u))
    c.val.write_text(_csv_text(yv, uv))


# --- issue 28: hostile inputs, round two ------------------------------------------------

_MODEL_PY = """import control as ct
import numpy as np
model = ct.ss([[0.0, 1.0], [-4.0, -0.8]], [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)),
              states=["x", "v"], inputs=["F"], outputs=["x", "v"], name="osc")
Q = np.diag([1e-10, 1e-8])
R = 1e-4 * np.eye(2)
Ts = 0.05
"""

_NL_WRONG_F = _MODEL_PY.replace(
    'model = ct.ss([[0.0, 1.0], [-4.0, -0.8]], [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)),',
    "model = ct.nlsys(lambda t, x, u, p: np.array([x[1]]), lambda t, x, u, p: x,")


def _model_py(c: Case, extra: str = "", text: str = _MODEL_PY):
    """MODEL.py in place of MODEL.json (a StateSpace: the linear pipeline, fast)."""
    c.model = c.dir / "model.py"
    c.model.write_text(text + extra)


def _model_py_chdir(c: Case):
    """A MODEL.py that leaves the working folder, with every path relative to it."""
    _model_py(c, "import os\nos.chdir('/')\n")
    c.cwd = c.dir
    c.model, c.est, c.val, c.out = (Path(p.name) for p in (c.model, c.est, c.val, c.out))


def _greybox_folder(path: Path, kind: str, names=("summary.json",), foreign=()):
    """A folder as greybox leaves it (marker, listed files), plus a user's files."""
    path.mkdir()
    (path / ".greybox-output").write_text("\n".join([kind, *names]) + "\n")
    for n in (*names, *foreign):
        (path / n).write_text("x")


def _out_link_to_foreign(c: Case):
    (c.dir / "thesis").mkdir()
    (c.dir / "thesis" / "thesis.tex").write_text("mine")
    os.symlink(c.dir / "thesis", c.out)
    c.extra_args.append("--force")


def _out_loop(c: Case):
    os.symlink(c.dir / "loop2", c.out)
    os.symlink(c.out, c.dir / "loop2")


def _out_cwd(c: Case, force: bool):
    c.cwd, c.out = c.dir, Path(".")
    c.extra_args += ["--force"] if force else []


def _out_cwd_greybox_with_user_file(c: Case):
    _greybox_folder(c.out, "report", ("summary.json", "report.md"), foreign=("notes.txt",))
    c.cwd, c.out = c.out, Path(".")
    c.extra_args.append("--force")


def _out_inputs_folder(c: Case):
    c.out = c.dir
    c.extra_args.append("--force")


def _scale_data(c: Case, factor: float):
    for which in ("est", "val"):
        lines = c.lines(which)
        c.put([lines[0]] + [",".join([r.split(",")[0]] + [repr(float(v) * factor)
                                                          for v in r.split(",")[1:]])
                            for r in lines[1:]], which)


def _time_column(c: Case, t):
    lines = c.lines()
    c.put([lines[0]] + [",".join([repr(float(t(i)))] + r.split(",")[1:])
                        for i, r in enumerate(lines[1:])])


def _jitter(c: Case, fraction: float):
    rng = np.random.default_rng(3)
    _time_column(c, lambda i: i * TS + fraction * TS * rng.uniform(-1, 1))


def _separator(c: Case, sep: str):
    c.put([r.replace(",", sep) for r in c.lines()])


def _index_column(c: Case):
    lines = c.lines()
    c.put(["," + lines[0]] + [f"{i},{r}" for i, r in enumerate(lines[1:])])


def _nfd_header(c: Case):
    """The model names its input 'Fé' composed (NFC), the CSVs decomposed (NFD)."""
    import unicodedata

    c.set(inputs=[unicodedata.normalize("NFC", "Fé")])
    for which in ("est", "val"):
        lines = c.lines(which)
        c.put([lines[0].replace("F", unicodedata.normalize("NFD", "Fé"), 1)] + lines[1:],
              which)


def _noise_only_zero_input(c: Case):
    """A plant at rest, the input zero throughout: measurement noise only."""
    rng = np.random.default_rng(9)
    c.est.write_text(_csv_text(1e-2 * rng.standard_normal((2, N)), np.zeros((1, N))))


def _constant_validation_output(c: Case):
    lines = c.lines("val")
    c.put([lines[0]] + [",".join(r.split(",")[:3] + ["0.25"]) for r in lines[1:]], "val")


def _fifo(c: Case, which: str):
    path = c.dir / f"pipe-{which}"
    os.mkfifo(path)
    setattr(c, which, path)


# (id, mutation, exit code, text that stderr must contain)
ROWS = [
    # --- MODEL.json: syntax and encoding
    ("model: malformed JSON", lambda c: _raw_model(c, "{not json"), 2, "not valid JSON"),
    ("model: empty file", lambda c: _raw_model(c, ""), 2, "not valid JSON"),
    ("model: a list, not an object", lambda c: _raw_model(c, "[1, 2]"), 2, "JSON object"),
    ("model: repeated key", lambda c: _raw_model(
        c, json.dumps(c.d)[:-1] + ', "Ts": 0.05}'), 2, "appears twice"),
    ("model: UTF-16 file", lambda c: _raw_model(c, json.dumps(c.d).encode("utf-16")), 2,
     "UTF-16"),
    ("model: UTF-16 without BOM", lambda c: _raw_model(c, json.dumps(c.d).encode("utf-16-le")),
     2, "UTF-16"),
    ("model: Latin-1 byte", lambda c: _raw_model(
        c, json.dumps(c.d).replace('"osc"', '"os\\u00e7"').encode().replace(
            b"\\u00e7", b"\xe7")), 2, "not UTF-8"),
    ("model: file missing", lambda c: c.model.unlink(), 2, "cannot read"),
    ("model: path is a folder", lambda c: (c.model.unlink(), c.model.mkdir()), 2, "cannot read"),
    ("model: nesting too deep", lambda c: _raw_model(c, "[" * 100000 + "]" * 100000), 2,
     "model"),
    # --- MODEL.json: keys and names
    ("model: unknown key (typo chanels)", lambda c: c.set(chanels={"x": [0, 1]}), 2,
     "did you mean 'channels'"),
    ("model: unknown key", lambda c: c.set(comment="hi"), 2, "unknown key 'comment'"),
    ("model: missing A", lambda c: c.set(A=_DROP), 2, "missing keys ['A']"),
    ("model: missing Q", lambda c: c.set(Q=_DROP), 2, "missing keys ['Q']"),
    ("model: missing B with inputs", lambda c: c.set(B=_DROP), 2, "missing key 'B'"),
    ("model: empty state name", lambda c: c.set(states=["x", ""]), 2, "empty name"),
    ("model: blank output name", lambda c: c.set(outputs=["x", "  "]), 2, "empty name"),
    ("model: repeated state names", lambda c: c.set(states=["x", "x"]), 2, "repeated names"),
    ("model: names not strings", lambda c: c.set(states=["x", 2]), 2, "list of names"),
    ("model: no states", lambda c: c.set(states=[]), 2, "'states' is empty"),
    ("model: no outputs", lambda c: c.set(outputs=[]), 2, "'outputs' is empty"),
    ("model: input named as output", lambda c: c.set(inputs=["x"], outputs=["x", "v"]), 2,
     "both as input and as output"),
    ("model: signal named time", lambda c: c.set(inputs=["time"]), 2, "reserved"),
    ("model: name not a string", lambda c: c.set(name=3), 2, "'name' must be a string"),
    ("model: time misspelt", lambda c: c.set(time="cont"), 2, "'continuous' or 'discrete'"),
    # --- MODEL.json: Ts
    ("model: Ts a string", lambda c: c.set(Ts="0.05"), 2, "'Ts' must be a number"),
    ("model: Ts boolean", lambda c: c.set(Ts=True), 2, "'Ts' must be a number"),
    ("model: Ts null", lambda c: c.set(Ts=None), 2, "'Ts' must be a number"),
    ("model: Ts negative", lambda c: c.set(Ts=-0.05), 2, "'Ts' must be > 0"),
    ("model: Ts zero", lambda c: c.set(Ts=0), 2, "'Ts' must be > 0"),
    ("model: Ts NaN", lambda c: _raw_model(c, json.dumps(c.d).replace('"Ts": 0.05', '"Ts": NaN')),
     2, "'Ts' must be > 0"),
    ("model: Ts 1e6 s", lambda c: c.set(Ts=1e6), 2, "slowest time constant"),
    ("model: Ts 1e-300 s", lambda c: c.set(Ts=1e-300), 2, "fastest time constant"),
    # --- MODEL.json: matrices
    ("model: A wrong shape", lambda c: c.set(A=[[0.0, 1.0]]), 2, "A has shape"),
    ("model: A not numeric", lambda c: c.set(A=[[0, "a"], [1, 2]]), 2, "numeric"),
    ("model: A ragged", lambda c: c.set(A=[[0, 1], [1]]), 2, "numeric"),
    ("model: A NaN", lambda c: _raw_model(c, json.dumps(c.d).replace("-4.0", "NaN")), 2,
     "NaN or inf"),
    ("model: A huge", lambda c: c.set(A=[[0, 1], [-1e200, -0.8]]), 2, "overflow"),
    ("model: B wrong shape", lambda c: c.set(B=[[0, 1, 2]]), 2, "B has shape"),
    ("model: C wrong shape", lambda c: c.set(C=[[1, 0]]), 2, "C has shape"),
    ("model: D wrong shape", lambda c: c.set(D=[[0, 0, 0]]), 2, "D has shape"),
    ("model: Q not symmetric", lambda c: c.set(Q=[[1e-8, 1e-9], [0, 1e-8]]), 2,
     "not symmetric"),
    ("model: Q negative", lambda c: c.set(Q=[-1e-8, 1e-8]), 2, "semidefinite"),
    ("model: R zero", lambda c: c.set(R=[0, 1e-4]), 2, "positive definite"),
    ("model: R singular", lambda c: c.set(R=[[1e-4, 1e-4], [1e-4, 1e-4]]), 2,
     "positive definite"),
    ("model: R wrong shape", lambda c: c.set(R=[1e-4]), 2, "R has shape"),
    # --- MODEL.json: channels
    ("model: channels not an object", lambda c: _channels(c, [0, 1]), 2, "'channels' must be"),
    ("model: channels empty", lambda c: _channels(c, {}), 2, "'channels' is empty"),
    ("model: all-zero channel", lambda c: _channels(c, {"force": [0, 0]}), 2, "all zero"),
    ("model: channel wrong length", lambda c: _channels(c, {"force": [0, 1, 2]}), 2,
     "channel 'force'"),
    ("model: channel unknown state", lambda c: _channels(c, {"k": ["x", "w"]}), 2,
     "unknown states ['w']"),
    ("model: channel repeats a state", lambda c: _channels(c, {"k": ["x", "x"]}), 2,
     "repeats a state"),
    ("model: channel NaN", lambda c: _raw_model(c, json.dumps(
        dict(c.d, channels={"k": [0, 1]})).replace('[0, 1]}', '[0, NaN]}')), 2, "NaN"),
    ("model: channel with empty name", lambda c: _channels(c, {"": [0, 1]}), 2, "empty name"),
    # --- CSV files
    ("csv: missing column", lambda c: c.put([",".join(r.split(",")[:-1]) for r in c.lines()]),
     2, "missing"),
    ("csv: extra column", lambda c: c.put([r + (",extra" if i == 0 else ",1")
                                           for i, r in enumerate(c.lines())]), 2, "unexpected"),
    ("csv: duplicate column", lambda c: c.put([r + (",x" if i == 0 else ",1")
                                               for i, r in enumerate(c.lines())]), 2, "columns"),
    ("csv: two time columns", lambda c: c.put([r + (",t" if i == 0 else ",1")
                                               for i, r in enumerate(c.lines())]), 2, "columns"),
    ("csv: non-numeric cell", lambda c: _cell(c, 5, 2, "abc"), 2, "row 6, column 'x'"),
    ("csv: empty cell", lambda c: _cell(c, 7, 3, ""), 2, "row 8, column 'v'"),
    ("csv: hexadecimal", lambda c: _cell(c, 9, 1, "0x1"), 2, "not a number"),
    ("csv: NaN cell", lambda c: _cell(c, 7, 2, "nan"), 2, "NaN"),
    ("csv: inf cell", lambda c: _cell(c, 7, 2, "inf"), 2, "NaN or inf"),
    ("csv: value 1e200", lambda c: _cell(c, 7, 2, "1e200"), 2, "rescale"),
    ("csv: value 1e999", lambda c: _cell(c, 7, 2, "1e999"), 2, "inf"),
    ("csv: short row", lambda c: c.put(c.lines()[:10] + ["1,2"] + c.lines()[10:]), 2,
     "row 11: 2 cells"),
    ("csv: long row", lambda c: c.put(c.lines()[:10] + ["1,2,3,4,5"] + c.lines()[10:]), 2,
     "row 11: 5 cells"),
    ("csv: time disagrees with Ts", lambda c: c.put(
        [c.lines()[0]] + [",".join([f"{2 * i * TS:.10g}"] + r.split(",")[1:])
                          for i, r in enumerate(c.lines()[1:])]), 2, "Ts"),
    ("csv: too short", lambda c: c.put(c.lines()[:50]), 2, "samples"),
    ("csv: validation too short", lambda c: c.put(c.lines("val")[:60], "val"), 2, "samples"),
    ("csv: empty file", lambda c: c.est.write_text(""), 2, "empty"),
    ("csv: header only", lambda c: c.put(c.lines()[:1]), 2, "samples"),
    ("csv: UTF-16", lambda c: c.est.write_bytes(c.est.read_text().encode("utf-16")), 2,
     "UTF-16"),
    ("csv: Latin-1 byte", lambda c: c.est.write_bytes(
        c.est.read_bytes().replace(b"F,", b"F\xe9,", 1)), 2, "not UTF-8"),
    ("csv: Latin-1 byte in data", lambda c: c.est.write_bytes(
        c.est.read_bytes()[:200] + b"\xe9" + c.est.read_bytes()[200:]), 2, "not UTF-8"),
    ("csv: file missing", lambda c: c.est.unlink(), 2, "cannot read"),
    ("csv: validation file missing", lambda c: c.val.unlink(), 2, "cannot read"),
    ("csv: path is a folder", lambda c: (c.est.unlink(), c.est.mkdir()), 2, "cannot read"),
    # --- output folder
    ("out: is a file", _out_file, 2, "not a folder"),
    ("out: holds foreign files", _out_foreign, 2, "--force"),
    ("out: below a file", _out_under_file, 2, "not a folder"),
    # --- legal but suspicious: a warning, then a normal run
    ("warn: same file for estimation and validation",
     lambda c: setattr(c, "val", c.est), 0, "warning: the estimation and validation data are "
                                             "the same"),
    ("warn: Ts heavily oversampled", lambda c: _rescale_time(c, 1e-7), 0, "oversampled"),
    # --- legal
    ("ok: UTF-8 byte-order mark in MODEL.json", lambda c: c.model.write_bytes(
        b"\xef\xbb\xbf" + c.model.read_bytes()), 0, ""),
    ("ok: Excel CSV (BOM, CRLF)", lambda c: c.est.write_bytes(
        b"\xef\xbb\xbf" + c.est.read_bytes().replace(b"\n", b"\r\n")), 0, ""),
    ("ok: blank lines in CSV", lambda c: c.put(c.lines()[:20] + ["", " , , , "]
                                               + c.lines()[20:]), 0, ""),
    ("ok: model without inputs", _no_inputs, 0, ""),
    ("ok: unstable model", _unstable, 0, ""),  # SE n/a: see test_unstable_model_row
    # --- issue 28: files that are not ours, mixed reports (before computing anything)
    ("out: link to a folder of the user's files, --force", _out_link_to_foreign, 2,
     "greybox did not write (thesis.tex)"),
    ("out: holds a greybox demo, no --force", lambda c: _greybox_folder(c.out, "demo"), 2,
     "holds a greybox demo, not a report"),
    ("out: a loop of links", _out_loop, 2, "loop"),
    ("out: a link to nothing", lambda c: os.symlink(c.dir / "nowhere", c.out), 2,
     "does not exist"),
    ("out: empty name", lambda c: setattr(c, "out", ""), 2, "--out is empty"),
    ("out: the current folder", lambda c: _out_cwd(c, False), 2, "greybox did not write"),
    ("out: the current folder, --force", lambda c: _out_cwd(c, True), 2,
     "greybox did not write"),
    ("out: the inputs' folder, --force", _out_inputs_folder, 2, "greybox did not write"),
    ("out: current greybox folder with a user's file, --force",
     _out_cwd_greybox_with_user_file, 2, "is the current folder"),
    # --- issue 28: what raised a traceback
    ("model: '.' in a state name", lambda c: c.set(states=["motor.x", "v"]), 2,
     "contains '.'"),
    ("model: '.' in an output name", lambda c: c.set(outputs=["x", "v.m"]), 2,
     "contains '.'"),
    ("model: '.' in the model's name", lambda c: c.set(name="osc.v1"), 2, "contains '.'"),
    ("model: 400-digit integer Ts", lambda c: _raw_model(c, json.dumps(c.d).replace(
        '"Ts": 0.05', '"Ts": 1' + "0" * 400)), 2, "(401 digits) is beyond 1e+150"),
    ("model: 400-digit integer in A", lambda c: _raw_model(c, json.dumps(c.d).replace(
        "-4.0", "-4" + "0" * 400)), 2, "digits) is beyond 1e+150"),
    ("model: /dev/zero", lambda c: setattr(c, "model", Path("/dev/zero")), 2,
     "character device, not a regular file"),
    ("model: a FIFO without writer", lambda c: _fifo(c, "model"), 2, "named pipe (FIFO)"),
    ("csv: /dev/zero", lambda c: setattr(c, "est", Path("/dev/zero")), 2,
     "character device, not a regular file"),
    ("csv: validation a FIFO without writer", lambda c: _fifo(c, "val"), 2,
     "named pipe (FIFO)"),
    ("model.py: calls sys.exit(0)", lambda c: _model_py(c, "import sys\nsys.exit(0)\n"), 2,
     "called sys.exit(0)"),
    ("model.py: raises a BaseException", lambda c: _model_py(
        c, "class Stop(BaseException):\n    pass\nraise Stop('halt')\n"), 2,
     "raised Stop while being executed: halt"),
    ("model.py: '.' in a state name", lambda c: _model_py(c, text=_MODEL_PY.replace(
        'states=["x", "v"]', 'states=["motor.x", "v"]')), 2, "contains '.'"),
    ("model.py: f returns one value for two states", lambda c: _model_py(c, text=_NL_WRONG_F),
     2, "f returns 1 value(s) (shape (1,)) for 2 states"),
    # --- issue 28: what gave a silent wrong answer
    ("csv: 1_000 cell", lambda c: _cell(c, 9, 1, "1_000"), 2, "'_' as a digit separator"),
    ("csv: data scaled by 1e140", lambda c: _scale_data(c, 1e140), 2,
     "above 1e+50 the cubic law terms"),
    ("csv: data scaled by 1e-300", lambda c: _scale_data(c, 1e-300), 2, "underflow"),
    ("csv: data scaled by 1e-45, R not", lambda c: _scale_data(c, 1e-45), 2,
     "the data and R are in different units"),
    ("model: time discrete, A continuous", lambda c: c.set(time="discrete"), 2,
     "looks like a continuous-time matrix"),
    # --- issue 28: unclear messages
    ("csv: time goes backwards", lambda c: _time_column(
        c, lambda i: (i if i != 10 else 8) * TS), 2, "goes backwards at data row 11"),
    ("csv: time repeats", lambda c: _time_column(c, lambda i: (i if i != 10 else 9) * TS), 2,
     "repeats a time at data row 11"),
    ("csv: a sample missing", lambda c: _time_column(c, lambda i: (i if i < 10 else i + 1) * TS),
     2, "1 sample(s) missing before data row 11"),
    ("csv: time jitter 0.5 %", lambda c: _jitter(c, 0.005), 2, "tolerance 0.1 %"),
    ("csv: semicolon-separated", lambda c: _separator(c, ";"), 2,
     "separated by semicolons; the separator must be a comma"),
    ("csv: tab-separated", lambda c: _separator(c, "\t"), 2, "separated by tabs"),
    ("csv: trailing comma on every line", lambda c: c.put([r + "," for r in c.lines()]), 2,
     "a comma at the end of every line"),
    ("csv: pandas index column", _index_column, 2, "index column"),
    ("csv: Unicode minus", lambda c: _cell(c, 9, 2, "\u22120.0123"), 2,
     "Unicode minus sign U+2212"),
    ("csv: CR-only line endings", lambda c: c.est.write_bytes(
        c.est.read_bytes().replace(b"\n", b"\r")), 2, "carriage return alone"),
    ("csv: NUL bytes", lambda c: c.est.write_bytes(b"\0" * 64), 2, "NUL"),
    ("csv: column name differs in case", lambda c: c.put(
        [c.lines()[0].replace("F", "f")] + c.lines()[1:]), 2, "only in case"),
    ("model: leading space in a name", lambda c: c.set(states=[" x", "v"]), 2,
     "begins or ends with a space"),
    ("model: names equal once normalized", lambda c: c.set(states=["caf\u00e9", "cafe\u0301"]),
     2, "different Unicode code points"),
    # --- issue 28: legal but suspicious (a warning), and legal
    ("warn: input zero throughout", _noise_only_zero_input, 0,
     "warning: input(s) ['F'] are zero throughout"),
    ("warn: constant validation output", _constant_validation_output, 0,
     "warning: validation output(s) ['v'] are constant"),
    ("ok: model.py changes the working folder", _model_py_chdir, 0, ""),
    ("ok: header NFD, model NFC", _nfd_header, 0, ""),
    ("ok: link to a greybox report, --force", lambda c: (
        _greybox_folder(c.dir / "real", "report"), os.symlink(c.dir / "real", c.out),
        c.extra_args.append("--force")), 0, ""),
    ("ok: report over a demo, --force", lambda c: (
        _greybox_folder(c.out, "demo", ("summary.json", "fig1_tension.png")),
        c.extra_args.append("--force")), 0, ""),
]


def _rescale_time(c: Case, factor: float):
    """Time constants ``factor`` times shorter in Ts: A scaled, data unchanged (a warning)."""
    c.set(A=(np.array(c.d["A"]) * factor).tolist(), Ts=TS)


def _tree(root: Path) -> list[str]:
    """Every path below ``root`` (links not followed), with file sizes."""
    out = []
    for d, dirs, files in os.walk(root):
        for f in dirs + files:
            p = Path(d) / f
            size = p.lstat().st_size if p.is_file() and not p.is_symlink() else -1
            out.append(f"{p.relative_to(root)}:{size}")
    return sorted(out)


@pytest.mark.parametrize("name, mutate, code, match", ROWS, ids=[r[0] for r in ROWS])
def test_bad_input_table(tmp_path, capsys, monkeypatch, name, mutate, code, match):
    c = Case(tmp_path)
    mutate(c)
    if c.cwd is not None:
        monkeypatch.chdir(c.cwd)
    before = _tree(tmp_path)
    assert main(c.argv()) == code
    cap = capsys.readouterr()
    err = [ln for ln in cap.err.splitlines() if ln.strip()]
    if code == 2:
        assert len(err) == 1, err
        assert err[0].startswith("greybox: error: ") and match in err[0], err
        # nothing written, moved or removed: no report, no temporary folder
        assert _tree(tmp_path) == before
    else:
        assert all(ln.startswith("greybox: warning: ") for ln in err), err
        assert match in cap.err
        assert (c.out / "summary.json").exists()


def test_table_size():
    """The tables only grow (issue 13 started with 80 rows, issue 28 brought 135 and 18)."""
    assert len(ROWS) >= 135 and len(API_ROWS) >= 18
    assert len({r[0] for r in ROWS}) == len(ROWS)
    assert len({r[0] for r in API_ROWS}) == len(API_ROWS)


@pytest.mark.parametrize("argv", [
    ["update"], ["update", "m.json", "e.csv"], ["update", "m.json", "e.csv", "--validate"],
    ["update", "m.json", "e.csv", "--validate", "v.csv", "--bogus"], ["demo", "motor"],
    ["frobnicate"], [],
])
def test_bad_arguments_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    assert "error" in capsys.readouterr().err


def test_out_not_writable_checked_before_computing(tmp_path, capsys, monkeypatch):
    import greybox.io as gio
    import greybox.workflow as wf

    c = Case(tmp_path)
    real = os.access
    monkeypatch.setattr(gio.os, "access", lambda p, mode: False if Path(p) == tmp_path
                        else real(p, mode))
    monkeypatch.setattr(wf, "close_the_loop", lambda *a, **k: pytest.fail("computed first"))
    assert main(c.argv()) == 2
    err = capsys.readouterr().err
    assert "no write permission" in err and err.count("\n") == 1


def test_unstable_model_row(tmp_path, capsys):
    """The unstable row: SE is n/a in the table and null with a reason in summary.json."""
    c = Case(tmp_path)
    _unstable(c)
    assert main(c.argv()) == 0
    out = capsys.readouterr().out
    assert "n/a" in out and "unstable" in out
    s = json.loads((c.out / "summary.json").read_text())
    row = s["table"]["nominal"]
    assert row["se"] is None and "unstable" in row["se_reason"]
    assert np.isfinite(row["pe"])


# --- issue 28: the Python API, one row per call --------------------------------------------

_OSC = named_ss([[0.0, 1.0], [-4.0, -0.8]], [[0.0], [1.0]], np.eye(2), np.zeros((2, 1)), 0,
                states=["x", "v"], inputs=["F"], outputs=["x", "v"], name="osc")
_Y, _U = _data(1)
_YV, _UV = _data(2)
_QN, _RN = np.diag([1e-10, 1e-8]), 1e-4 * np.eye(2)


class _Frame:
    """What greybox sees of a pandas DataFrame (pandas is not a dependency)."""

    def __init__(self, values, columns, index=None):
        self.values = np.asarray(values, dtype=float)
        self.columns = list(columns)
        self.index = list(range(self.values.shape[0]) if index is None else index)

    def to_numpy(self):
        return self.values

    def __array__(self, dtype=None, copy=None):
        return self.values

    @property
    def T(self):
        return _Frame(self.values.T, self.index, self.columns)


def _loop(**kw):
    args = dict(sys=_OSC, y=_Y, u=_U, y_val=_YV, u_val=_UV, Q=_QN, R=_RN, dt=TS, delta=False)
    args.update(kw)
    return gb.close_the_loop(**args)


def _masked(a, at=(0, 50)):
    m = np.ma.masked_array(a, mask=np.zeros(np.shape(a), bool))
    m[at] = np.ma.masked
    return m


def _records(**kw):
    args = dict(y=_Y, u=_U, y_val=_YV, u_val=_UV)
    args.update(kw)
    return check_records(_OSC, args["y"], args["u"], args["y_val"], args["u_val"], _RN,
                         min_steps=200, min_val_steps=100)


def _same_records(res) -> bool:
    return all(np.array_equal(a, b) for a, b in zip(res, (_Y, _U, _YV, _UV)))


def _same_table(rep) -> bool:
    base = _loop()
    return all(rep.table[k].se.value == base.table[k].se.value for k in base.table)


_NOISE = 1e-2 * np.random.default_rng(9).standard_normal((2, N))
_FLAT = np.vstack([_YV[0], np.full(N, 0.25)])

# (id, call, outcome: an error class, GreyboxWarning, or a check of the result, text to match)
API_ROWS = [
    ("masked sample in y_val", lambda: _loop(y_val=_masked(_YV)), gb.DataError,
     "y_val is a masked array with 1 masked sample(s) (first at signal 0, sample 50)"),
    ("masked sample in u", lambda: _loop(u=_masked(_U)), gb.DataError, "u is a masked array"),
    ("masked sample into kalman_filter", lambda: gb.kalman_filter(
        gb.discretize(_OSC, TS), _masked(_YV), _UV, Q=_QN, R=_RN), gb.DataError,
     "y is a masked array"),
    ("masked entry in Q", lambda: _loop(Q=_masked(_QN, (0, 0))), gb.DimensionError,
     "masked entries"),
    ("masked array without a masked sample", lambda: _records(y=np.ma.masked_array(_Y)),
     _same_records, ""),
    ("DataFrame, columns in another order", lambda: _records(
        y=_Frame(_Y[::-1].T, ["v", "x"]), y_val=_Frame(_YV.T, ["x", "v"])), _same_records, ""),
    ("DataFrame transposed (signals as index)", lambda: _records(
        y=_Frame(_Y[::-1].T, ["v", "x"]).T, u=_Frame(_U.T, ["F"]).T), _same_records, ""),
    ("DataFrames through close_the_loop", lambda: _loop(
        y=_Frame(_Y[::-1].T, ["v", "x"]), u=_Frame(_U.T, ["F"]),
        y_val=_Frame(_YV.T, ["x", "v"]).T), _same_table, ""),
    ("DataFrame with other labels", lambda: _loop(y=_Frame(_Y.T, ["a", "b"])),
     gb.DimensionError, "y is a DataFrame labelled ['a', 'b']"),
    ("DataFrame into kalman_filter", lambda: gb.kalman_filter(
        gb.discretize(_OSC, TS), _Frame(_YV.T, ["x", "v"]).T, _UV, Q=_QN, R=_RN),
     gb.DimensionError, "pandas DataFrame"),
    ("channel all zero", lambda: _loop(channels={"x": [0, 0]}), gb.DimensionError,
     "channels['x'] is all zero"),
    ("channel with a zero column", lambda: _loop(channels={"k": [[0, 1], [0, 1]]}),
     gb.DimensionError, "channels['k'] is all zero in column 0"),
    ("y_val is y", lambda: _loop(y_val=_Y, u_val=_U), gb.GreyboxWarning,
     "the estimation and validation data are the same"),
    ("input zero throughout", lambda: _loop(y=_NOISE, u=np.zeros((1, N))), gb.GreyboxWarning,
     "input(s) ['F'] are zero throughout the estimation record"),
    ("constant validation output", lambda: _loop(y_val=_FLAT), gb.GreyboxWarning,
     "validation output(s) ['v'] are constant: there is nothing to compare"),
    ("data scaled by 1e140", lambda: _loop(y=1e140 * _Y, u=1e140 * _U), gb.DataError,
     "the estimation output 'x' (y) reaches"),
    ("data scaled by 1e-300", lambda: _loop(y=1e-300 * _Y, u=1e-300 * _U), gb.DataError,
     "underflow"),
    ("relative_error of data scaled by 1e-300", lambda: gb.relative_error(
        1e-300 * _Y, 0.9e-300 * _Y), lambda r: np.isclose(r.value, 10.0), ""),
]


@pytest.mark.parametrize("name, call, outcome, match", API_ROWS, ids=[r[0] for r in API_ROWS])
def test_api_bad_input_table(name, call, outcome, match):
    import re

    if outcome is gb.GreyboxWarning:
        with pytest.warns(gb.GreyboxWarning, match=re.escape(match)):
            call()
    elif isinstance(outcome, type):
        with pytest.raises(outcome, match=re.escape(match)):
            call()
    else:
        assert outcome(call())


# --- issue 28: single tests of the command line ----------------------------------------------

def test_model_py_prints_on_stderr_json_stdout_parses(tmp_path, capsys):
    c = Case(tmp_path)
    _model_py(c, "print('hello from the model')\n")
    assert main(c.argv() + ["--json"]) == 0
    cap = capsys.readouterr()
    json.loads(cap.out)  # the document alone
    assert "hello from the model" in cap.err


def test_report_over_a_demo_keeps_only_the_users_files(tmp_path, capsys):
    c = Case(tmp_path)
    _greybox_folder(c.out, "demo", ("summary.json", "fig1_tension.png"), foreign=("notes.txt",))
    assert main(c.argv() + ["--force"]) == 0
    capsys.readouterr()
    names = sorted(p.name for p in c.out.iterdir())
    assert "fig1_tension.png" not in names and "notes.txt" in names  # demo's figure gone
    assert (c.out / ".greybox-output").read_text().splitlines()[0] == "report"


def test_link_to_a_greybox_folder_is_followed(tmp_path, capsys):
    c = Case(tmp_path)
    real = tmp_path / "real"
    _greybox_folder(real, "report", foreign=("notes.txt",))
    os.symlink(real, c.out)
    assert main(c.argv() + ["--force"]) == 0
    capsys.readouterr()
    assert c.out.is_symlink() and (real / "summary.json").stat().st_size > 1
    assert (real / "notes.txt").read_text() == "x"


def _entry_module():
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "greybox_cli_t", Path(__file__).resolve().parents[1] / "greybox_cli" / "__init__.py")
    entry = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(entry)
    return entry


def test_ctrl_c_while_greybox_imports(monkeypatch, capsys):
    """The entry module catches Ctrl-C around the import of the package."""
    import sys

    entry = _entry_module()

    class Interrupting:
        def find_spec(self, name, path=None, target=None):
            if name == "greybox.cli":
                raise KeyboardInterrupt
            return None

    monkeypatch.delitem(sys.modules, "greybox.cli")
    monkeypatch.setattr(sys, "meta_path", [Interrupting(), *sys.meta_path])
    assert entry.main(["demo", "tape-drive"]) == 130
    assert capsys.readouterr().err == "greybox: interrupted\n"


def test_ctrl_c_turned_into_an_import_error_is_still_an_interrupt(monkeypatch, capsys):
    """A C extension's init turns the interrupt into ImportError (seen in CI): exit 130."""
    import signal
    import sys

    entry = _entry_module()

    class CExtensionInit:
        def find_spec(self, name, path=None, target=None):
            if name == "greybox.cli":
                try:
                    signal.getsignal(signal.SIGINT)(signal.SIGINT, None)  # the SIGINT lands
                except KeyboardInterrupt:
                    raise ImportError("initialization failed")
            return None

    monkeypatch.delitem(sys.modules, "greybox.cli")
    monkeypatch.setattr(sys, "meta_path", [CExtensionInit(), *sys.meta_path])
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal
    try:
        assert entry.main(["demo", "tape-drive"]) == 130
    finally:
        signal.signal(signal.SIGINT, previous)
    assert capsys.readouterr().err == "greybox: interrupted\n"


def test_an_ignored_sigint_stays_ignored(monkeypatch):
    """A background job's SIG_IGN is kept during the import, as Python keeps it at start."""
    import signal
    import sys

    entry = _entry_module()
    seen = []

    class Look:
        def find_spec(self, name, path=None, target=None):
            if name == "greybox.cli":
                seen.append(signal.getsignal(signal.SIGINT))
                raise ImportError("stop here")
            return None

    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        monkeypatch.delitem(sys.modules, "greybox.cli")
        monkeypatch.setattr(sys, "meta_path", [Look(), *sys.meta_path])
        with pytest.raises(ImportError, match="stop here"):  # not an interrupt: no SIGINT came
            entry.main(["demo", "tape-drive"])
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)
    assert seen == [signal.SIG_IGN]


def test_ctrl_c_while_greybox_imports_in_a_process(tmp_path):
    """SIGINT a fraction of a second after start: one line, exit code 130."""
    import signal
    import subprocess
    import sys
    import time

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, PYTHONPATH=str(root))
    code = ("import sys; sys.stderr.write('ready\\n'); sys.stderr.flush(); import greybox_cli; "
            f"sys.exit(greybox_cli.main(['demo', 'tape-drive', '--out', {str(tmp_path / 'o')!r}]))")
    # SIGINT at its default in the child, as a terminal's Ctrl-C finds it: a test run started
    # as a background job of a script (``... &``) has it ignored, and Python, then greybox_cli,
    # keep an inherited SIG_IGN (the cause of the lost signal in two clean-clone runs)
    proc = subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True,
                            env=env, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.stderr.readline() == "ready\n"
    time.sleep(0.2)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err == "greybox: interrupted\n", err


def test_progress_lines_when_stderr_is_not_a_terminal():
    import io

    from greybox.cli import _parser, _Run
    from greybox.progress import LogProgress, Progress

    args = _parser().parse_args(["demo", "tape-drive"])
    assert isinstance(_Run(args).progress, LogProgress)  # pytest's stderr is no terminal
    args.quiet = True
    assert _Run(args).progress is None
    s = io.StringIO()
    log = LogProgress(s, interval=10.0)
    for t, stage, k in [(1, "a", 0), (11, "a", 0), (12, "b", 0), (25, "b", 0), (26, "b", 1),
                        (40, "c", 0)]:
        log(Progress(stage, k, 2, float(t)))
    lines = s.getvalue().splitlines()
    assert lines == ["greybox: progress: 11 s, a (0 of 2)", "greybox: progress: 25 s, b (0 of 2)",
                     "greybox: progress: 40 s, c (0 of 2)"]  # none in the first 10 s, then 10 s apart


# --- issue 28: CSV text as a hostile spreadsheet may write it ----------------------------

_TABLE = np.column_stack([np.arange(12) * TS,
                          np.random.default_rng(4).standard_normal((12, 3)).round(4)])
_DIGITS = {"ASCII": "0123456789", "Arabic-Indic": "٠١٢٣٤٥٦٧٨٩",
           "fullwidth": "０１２３４５６７８９", "Devanagari": "०१२३४५६७८९"}


def _csv_variant(sep, quoting, digits, minus, eol, bom, pad) -> bytes:
    """The table as text: separator, quoted cells, digits, minus signs, line ends, BOM."""
    rng = np.random.default_rng(quoting)
    to = str.maketrans("0123456789-", _DIGITS[digits] + minus)

    def cell(text: str, number: bool) -> str:
        text = text.translate(to) if number else text
        if quoting and rng.random() < 0.5:
            return f'"{text}"'
        return f" {text} " if pad else text

    lines = [sep.join(cell(h, False) for h in ("time", "F", "x", "v"))]
    lines += [sep.join(cell(f"{v:.6g}", True) for v in row) for row in _TABLE]
    text = eol.join(lines) + eol
    if bom == "UTF-16":
        return text.encode("utf-16")
    return {"": b"", "UTF-8": b"\xef\xbb\xbf", "UTF-8 twice": b"\xef\xbb\xbf" * 2}[bom] + \
        text.encode("utf-8")


@settings(max_examples=60, deadline=None, derandomize=True,  # the same examples in CI
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(sep=st.sampled_from([",", ";", "\t", " "]), quoting=st.integers(0, 3),
       digits=st.sampled_from(sorted(_DIGITS)), minus=st.sampled_from(["-", "\u2212", "\u2013"]),
       eol=st.sampled_from(["\n", "\r\n", "\r"]),
       bom=st.sampled_from(["", "UTF-8", "UTF-8 twice", "UTF-16"]), pad=st.booleans())
def test_csv_text_gives_the_clean_numbers_or_one_clear_error(tmp_path, sep, quoting, digits,
                                                             minus, eol, bom, pad):
    from greybox.model_io import read_csv

    path = tmp_path / "variant.csv"
    path.write_bytes(_csv_variant(sep, quoting, digits, minus, eol, bom, pad))
    legal = sep == "," and minus == "-" and eol != "\r" and bom != "UTF-16"
    try:
        y, u = read_csv(path, inputs=["F"], outputs=["x", "v"], Ts=TS, min_steps=5)
    except gb.GreyboxError as e:
        assert not legal, e
        assert "\n" not in str(e) and str(path) in str(e)
        return
    clean = np.array([[float(f"{v:.6g}") for v in row] for row in _TABLE])
    assert np.array_equal(u, clean[:, 1:2].T) and np.array_equal(y, clean[:, 2:].T)
