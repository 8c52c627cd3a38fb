"""Fuzz test over the file inputs of every verb that reads one, through ``afmctl.cli.main``
in-process: a seeded corpus of damaged files (random bytes, UTF-16, a UTF-8 byte-order mark,
truncation, huge numbers, NaN, over-long integers) in place of a valid one.

A damaged file that cannot be valid must end with exit status 2 and exactly one
``afmctl: error:`` line naming the file (and, for a bad number, the field, column or row),
never a traceback and never a silent success. A damage that may leave the file valid (a BOM,
a cut at a line end) may succeed, but still never with a traceback.

``demo`` and ``schema`` read no input files and are not here; ``run``'s trajectory files are
covered by the loop's own tests.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from afmctl.cli import main
from afmctl.control.runlog import DRIFT_DTYPE, SETPOINT_DTYPE, RunLogWriter

N = "{N}"          # the number each numeric mutation replaces

CSV_TUY = "t,u,y\n" + "".join(f"{i * 1e-3!r},{u!r},{80 * u + 3 * np.sin(i)!r}\n"
                                 for i, u in enumerate(np.abs(np.linspace(-60, 60, 120)) + 10)).replace(
    "0.002,", "0.002,", 1)
CSV_TUY = CSV_TUY.replace(CSV_TUY.splitlines()[3].split(",")[1], N, 1)       # u of row 4
CSV_TY = "t,y\n0,0\n0.001,100\n0.002,{N}\n0.003,300\n"
CSV_TT = "t,T\n0,20\n1,20.5\n2,{N}\n3,21.5\n"
CSV_TUXYZ = "t,ux,uy,uz\n0,0,0,0\n0.01,1,1,1\n0.02,{N},2,2\n0.03,3,3,3\n"
CSV_TU = "t,u\n0,0\n0.01,1\n0.02,{N}\n0.03,3\n"
CSV_TX = "t,x\n0,0\n1,0.5\n2,{N}\n3,1.5\n"
PI_JSON = '{"kind": "pi", "thresholds": [0.0, 10.0], "weights": [{N}, 5.0], "u_range_V": [0.0, 150.0]}'
RUN_TOML = '[amplifier]\ndriver = "mdt693b"\nport = "/nonexistent/tty"\n[loop]\nrate_Hz = {N}\n'
SIM_TOML = '[sim]\ntick_s = 0.01\npublish_rate_Hz = {N}\n'
VALUES = {CSV_TUY: None, CSV_TY: "200", CSV_TT: "21", CSV_TUXYZ: "2", CSV_TU: "2", CSV_TX: "1", PI_JSON: "80.0",
          RUN_TOML: "100", SIM_TOML: "100"}
NAN = {"csv": "nan", "json": "NaN", "toml": "nan"}


def _drift_json() -> str:
    from afmctl.compensators.drift import DriftParams
    text = json.dumps(DriftParams.named("physical_tube").model_dump(mode="json"))
    head, sep, tail = text.partition('"K": ')                  # the first path gain
    number, _, rest = tail.partition(",")
    return head + sep + N + "," + rest, number


# (verb arguments with {f} for the damaged file and {o} for an output path, format, template,
#  field/column the numeric mutation hits)
CASES = {
    "identify --data": (["identify", "--model", "pi", "--data", "{f}", "--out", "{o}"], "csv", CSV_TUY, "u"),
    "compensate --model": (["compensate", "--model", "{f}", "--target", "{ty}", "--out", "{o}"], "json", PI_JSON,
                           "weights"),
    "compensate --target": (["compensate", "--model", "{pi}", "--target", "{f}", "--out", "{o}"], "csv", CSV_TY,
                            "y"),
    "model show": (["model", "show", "--model", "{f}"], "json", PI_JSON, "weights"),
    "model invert": (["model", "invert", "--model", "{f}", "--out", "{o}"], "json", PI_JSON, "weights"),
    "drift predict --temperature": (["drift", "predict", "--temperature", "{f}", "--out", "{o}"], "csv", CSV_TT,
                                    "T"),
    "drift predict --voltages": (["drift", "predict", "--temperature", "{tt}", "--voltages", "{f}", "--out", "{o}"],
                                 "csv", CSV_TUXYZ, "ux"),
    "drift predict --params": (["drift", "predict", "--temperature", "{tt}", "--params", "{f}", "--out", "{o}"],
                               "json", "DRIFT", "K"),
    "drift fit --drift": (["drift", "fit", "--temperature", "{tt}", "--drift", "{f}", "--out", "{o}"], "csv", CSV_TX,
                          "x"),
    "amp stream --file": (["amp", "--driver", "mdt693b", "--port", "/nonexistent/tty", "stream", "--file", "{f}"],
                          "csv", CSV_TU, "u"),
    "run --config": (["run", "--config", "{f}", "--seconds", "0.1"], "toml", RUN_TOML, "rate_Hz"),
    "sim --config": (["sim", "--config", "{f}", "--duration", "0.1"], "toml", SIM_TOML, "publish_rate_Hz"),
}


def _template(case: str) -> tuple[str, str]:
    template = CASES[case][2]
    if template == "DRIFT":
        return _drift_json()
    value = VALUES[template]
    if value is None:                       # CSV_TUY: the value the placeholder replaced
        value = "10.0"
    return template, value


def mutations(case: str, seed: int) -> list[tuple[str, bytes, bool]]:
    """``(name, content, must_fail)`` for one case."""
    fmt = CASES[case][1]
    template, value = _template(case)
    valid = template.replace(N, value).encode()
    rng = np.random.default_rng(seed)
    cut = int(rng.integers(1, len(valid) - 1))
    while valid[cut - 1:cut] in (b"\n",):
        cut += 1
    return [
        ("random bytes", rng.integers(0, 256, int(rng.integers(1, 400)), dtype=np.uint8).tobytes(), True),
        ("random bytes after a valid start", valid[:cut] + rng.integers(128, 256, 50, dtype=np.uint8).tobytes(),
         True),
        ("UTF-16", valid.decode().encode("utf-16"), True),
        ("UTF-16 big-endian with BOM", b"\xfe\xff" + valid.decode().encode("utf-16-be"), True),
        ("NUL bytes", valid[:cut] + b"\x00" * 8 + valid[cut:], True),
        ("empty", b"", fmt != "toml"),      # an empty TOML file is all defaults
        ("huge number", template.replace(N, "1e999").encode(), True),
        ("NaN", template.replace(N, NAN[fmt]).encode(), True),
        ("over-long integer", template.replace(N, "9" * 5000).encode(), True),
        ("UTF-8 BOM", b"\xef\xbb\xbf" + valid, False),
        ("truncated", valid[:cut], False),
    ]


@pytest.fixture
def helpers(tmp_path):
    """Valid companion files the verbs need beside the damaged one."""
    ty = tmp_path / "ty.csv"
    ty.write_text(CSV_TY.replace(N, "200"))
    tt = tmp_path / "tt.csv"
    tt.write_text(CSV_TT.replace(N, "21"))
    pi = tmp_path / "pi.json"
    pi.write_text(PI_JSON.replace(N, "80.0"))
    return {"ty": str(ty), "tt": str(tt), "pi": str(pi)}


def _check(case: str, name: str, content: bytes, must_fail: bool, tmp_path: Path, helpers, capsys) -> None:
    argv_t, fmt, _, field = CASES[case]
    f = tmp_path / f"damaged.{fmt}"
    f.write_bytes(content)
    out = tmp_path / "out.file"
    out.unlink(missing_ok=True)
    argv = [a.format(f=f, o=out, **helpers) for a in argv_t]
    capsys.readouterr()
    try:
        rc = main(argv)
    except SystemExit as exc:               # argparse
        rc = exc.code
    cap = capsys.readouterr()
    where = f"{case} / {name}: rc={rc} stderr={cap.err!r}"
    assert "Traceback" not in cap.err, where
    assert rc in (0, 2), where
    if rc == 2:
        errors = [ln for ln in cap.err.splitlines() if ln.startswith("afmctl: error:")]
        assert len(errors) == 1, where
    if not must_fail:
        return
    assert rc == 2, f"silent success: {where}"
    line = errors[0]
    assert str(f) in line or f.name in line, f"the file is not named: {where}"
    if name in ("huge number", "NaN", "over-long integer") and "too long" not in line:
        assert field in line or "row" in line or "column" in line, f"the field is not named: {where}"


@pytest.mark.parametrize("case", sorted(CASES))
@pytest.mark.parametrize("seed", [1, 2])
def test_damaged_file_inputs(case, seed, tmp_path, helpers, capsys):
    for name, content, must_fail in mutations(case, seed):
        if seed == 2 and not name.startswith(("random", "truncated", "NUL")):
            continue                         # the deterministic damages once is enough
        _check(case, name, content, must_fail, tmp_path, helpers, capsys)


def _run_log(path: Path) -> bytes:
    n = 200
    sp = np.zeros(n, SETPOINT_DTYPE)
    sp["seq"] = np.arange(n)
    sp["t_s"] = np.arange(n) * 1e-3
    sp["target_nm"][:, 0] = np.linspace(0, 1000, n)
    sp["corrected_nm"] = sp["target_nm"]
    sp["u_V"][:, 0] = sp["target_nm"][:, 0] / 80
    dr = np.zeros(4, DRIFT_DTYPE)
    with RunLogWriter(path, {"scanner": "s1"}, fsync=False) as w:
        w.write_event({"seq": 0, "t_s": 0.0, "state": "running", "event": "start"})
        w.write_setpoints(sp[:100])
        w.write_drift(dr)
        w.write_setpoints(sp[100:])
    return path.read_bytes()


@pytest.mark.parametrize("argv", [["log", "show", "{f}"], ["report", "{f}", "--out", "{o}"],
                                  ["identify", "--model", "pi", "--from-images", "{f}", "--out", "{o}"]])
def test_damaged_binary_files(argv, tmp_path, capsys):
    """Run logs for log and report, scan archives (.npz) for identify --from-images."""
    valid = _run_log(tmp_path / "valid.afmlog")
    rng = np.random.default_rng(7)
    damaged = [("random bytes", rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), True),
               ("empty", b"", True),
               ("UTF-16 text", "t,u\n0,1\n".encode("utf-16"), True)]
    for cut in sorted(rng.integers(1, len(valid) - 1, 6)):
        damaged.append((f"truncated at {cut}", valid[:cut], False))     # read up to the last intact chunk
    flipped = bytearray(valid)
    for i in rng.integers(0, len(valid), 5):
        flipped[i] ^= 0xFF
    damaged.append(("bytes flipped", bytes(flipped), False))
    for name, content, must_fail in damaged:
        f = tmp_path / "run.afmlog"
        f.write_bytes(content)
        out = tmp_path / "rep"
        args = [a.format(f=f, o=out) for a in argv]
        capsys.readouterr()
        rc = main(args)
        cap = capsys.readouterr()
        _assert_read_or_one_error_line(rc, cap.err, f, must_fail, f"{argv[0]} / {name}")


def test_damaged_asylum_ibw_files(tmp_path, capsys):
    """Asylum .ibw frames (written by igorwriter) truncated, flipped or replaced: drift measure
    either reads them or stops with one error line naming the file, never a traceback."""
    from igorwriter import IgorWave

    rng = np.random.default_rng(11)
    good = tmp_path / "good.ibw"
    wave = IgorWave(np.ascontiguousarray(rng.normal(0, 1e-9, (64, 32, 2))), name="img")
    wave.set_dimlabel(2, 0, "HeightTrace")
    wave.set_dimlabel(2, 1, "HeightRetrace")
    wave.set_note("ScanSize: 5e-06\rScanRate: 1\r")
    wave.save(str(good))
    valid = good.read_bytes()
    damaged = [("random bytes", rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), True),
               ("empty", b"", True)]
    for cut in sorted(rng.integers(1, len(valid) - 1, 6)):
        damaged.append((f"truncated at {cut}", valid[:cut], False))
    flipped = bytearray(valid)
    for i in rng.integers(0, 400, 5):     # the headers and the start of the data
        flipped[i] ^= 0xFF
    damaged.append(("bytes flipped", bytes(flipped), False))
    for name, content, must_fail in damaged:
        f = tmp_path / "bad.ibw"
        f.write_bytes(content)
        capsys.readouterr()
        rc = main(["drift", "measure", str(good), str(f), "--out", str(tmp_path / "d.csv")])
        cap = capsys.readouterr()
        _assert_read_or_one_error_line(rc, cap.err, f, must_fail, name)


def test_damaged_nanoscope_files(tmp_path, capsys):
    """Bruker Nanoscope frames (the real sample file, tests/data/jmarini-nanoscope) truncated
    anywhere, with bytes flipped in the header, altered header numbers or replaced: drift measure
    either reads them or stops with one error line naming the file, never a traceback. A cut
    anywhere leaves the data incomplete and must be refused."""
    good = Path(__file__).parent / "data" / "jmarini-nanoscope" / "full_multiple_images.000"
    valid = good.read_bytes()
    rng = np.random.default_rng(13)
    damaged = [("random bytes", rng.integers(0, 256, 300, dtype=np.uint8).tobytes(), True),
               ("empty", b"", True),
               ("header only", valid[:40960], True),
               ("UTF-16 header", valid[:2000].decode("latin-1").encode("utf-16"), True)]
    for cut in sorted(rng.integers(1, len(valid) - 1, 6)):
        damaged.append((f"truncated at {cut}", valid[:cut], True))
    flipped = bytearray(valid)
    for i in rng.integers(0, 40960, 8):       # the text header
        flipped[i] ^= 0xFF
    damaged.append(("header bytes flipped", bytes(flipped), False))
    # header fields altered in place (same length: the data offsets stay valid)
    for field, bad, must_fail in ((b"Scan rate: 1.99943", b"Scan rate: nan    ", True),
                                  (b"Scan rate: 1.99943", b"Scan rate: -2.0000", True),
                                  (b"Samps/line: 512\r\n\\Number", b"Samps/line: 0  \r\n\\Number", True),
                                  (b"Data offset: 40960", b"Data offset:940960", True),       # beyond the end
                                  # an offset still inside the file reads other bytes: not told from a valid file
                                  (b"Data offset: 40960", b"Data offset: 99999", False)):
        assert len(field) == len(bad) and field in valid
        damaged.append((f"{bad!r}", valid.replace(field, bad, 1), must_fail))
    for name, content, must_fail in damaged:
        f = tmp_path / "bad.001"
        f.write_bytes(content)
        capsys.readouterr()
        rc = main(["drift", "measure", str(good), str(f), "--out", str(tmp_path / "d.csv")])
        cap = capsys.readouterr()
        _assert_read_or_one_error_line(rc, cap.err, f, must_fail, name)


def _assert_read_or_one_error_line(rc: int, err: str, f, must_fail: bool, what: str) -> None:
    """A damaged input file is either read (exit 0) or refused with exit 2 and exactly one
    error line naming it; never a traceback; ``must_fail`` inputs must be refused."""
    where = f"{what}: rc={rc} stderr={err!r}"
    assert "Traceback" not in err and rc in (0, 2), where
    if rc == 2:
        errors = [ln for ln in err.splitlines() if ln.startswith("afmctl: error:")]
        assert len(errors) == 1 and str(f) in errors[0], where
    if must_fail:
        assert rc == 2, f"silent success: {where}"
