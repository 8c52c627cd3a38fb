"""Samples whose position was not measured (column ``measured`` 0: the holds ``afmctl
calibrate`` puts between recorded pieces, their ``y`` interpolated) are left out of every
fit and every held-out score, while the models' memory and creep run through them."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

import afmctl
from afmctl.compensators.chain import block_all
from afmctl.control.calibrate_pieces import PieceRecord, join
from afmctl.data.datafiles import write_csv
from plants import CreepingPlant, RelayPreisachPlant, decaying_triangle

DT = 1e-3
#: where the record holds its voltage and its position is not measured: (row, samples)
HOLDS = ((3000, 1500), (9000, 2500), (15000, 1500))


def held_record(per_ms: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Nested 1 Hz triangles through a creeping Preisach plant, with :data:`HOLDS` inserted
    (the voltage held, the plant creeping on), ``per_ms`` samples a millisecond. Returns
    ``t, u, y (true), y as joined (interpolated over the holds and off by 2 µm there: what
    no fit may see), measured``."""
    dt = DT / per_ms
    _, tri = decaying_triangle(dt, 20, 0.0, 150.0, samples_per_cycle=1000 * per_ms)
    holds = [(row * per_ms, n * per_ms) for row, n in HOLDS]
    parts, at = [], 0
    for row, n in holds:
        parts += [tri[at:row], np.full(n, tri[row - 1])]
        at = row
    u = np.concatenate(parts + [tri[at:]])
    y = CreepingPlant(RelayPreisachPlant(noise_nm=0.0, seed=5), dt_s=dt).run(u)
    measured = np.ones(u.size, dtype=bool)
    joined = y.copy()
    start = 0
    for row, n in holds:
        a = row + start                     # the hold's first row in the record
        joined[a:a + n] = np.linspace(y[a - 1], y[a + n], n + 2)[1:-1] + 2000.0
        measured[a:a + n] = False
        start += n
    return np.arange(u.size) * dt, u, y, joined, measured


def measured_error_nm(fit: afmctl.Identified, u: np.ndarray, y: np.ndarray, measured: np.ndarray,
                      dt: float = DT) -> float:
    """RMS of prediction − true position [nm] over the measured samples after the burn-in."""
    pred = fit.model.forward(dt).block(np.ascontiguousarray(u))
    k = int(np.searchsorted(np.arange(u.size) * dt, fit.fit_from_s or 0.0))
    return float(np.sqrt(np.mean((pred - y)[k:][measured[k:]] ** 2)))


@pytest.mark.parametrize("kind", ["pi", "pi+creep", "preisach+creep", "amplifier+pi+creep"])
def test_a_fit_leaves_the_samples_not_measured_out(kind):
    """With the mask the fit is the one the true positions give (the holds' rows are not in
    it); without it the 2 µm the holds are off bend the model (which shows the test can fail).
    A chain with an amplifier stage (fitted here to a piezo voltage equal to the command)
    passes the mask on to the stages behind it."""
    t, u, y, joined, measured = held_record()
    opts: dict = {"n_operators": 12} if "pi" in kind else {"n_operators": 16}
    if kind.startswith("amplifier"):
        opts["v_V"] = u
    clean_fit = afmctl.identify(kind, t_s=t, u_V=u, y_nm=y, **opts)
    masked_fit = afmctl.identify(kind, t_s=t, u_V=u, y_nm=joined, measured=measured.astype(float), **opts)
    blind_fit = afmctl.identify(kind, t_s=t, u_V=u, y_nm=joined, **opts)
    clean, masked, blind = (measured_error_nm(f, u, y, measured) for f in (clean_fit, masked_fit, blind_fit))
    assert masked <= 1.5 * clean + 5.0, (masked, clean)
    assert blind > 2.0 * masked + 50.0, (blind, masked)
    # the residual it reports is over the measured samples: not the 2 µm of the holds
    assert masked_fit.rms_nm <= 1.5 * clean_fit.rms_nm + 5.0 < blind_fit.rms_nm, (masked_fit.rms_nm, clean_fit.rms_nm)


def test_a_chain_fitted_on_block_means_leaves_out_every_block_with_a_sample_not_measured():
    """At 5 kHz a PI chain's static stages are fitted on 2-sample means
    (:func:`~afmctl.compensators.chain.record_for_static`): the mask goes with them."""
    t, u, y, joined, measured = held_record(per_ms=5)
    dt = DT / 5
    fits = [afmctl.identify("pi+creep", t_s=t, u_V=u, y_nm=yy, n_operators=12, **kw)
            for yy, kw in ((y, {}), (joined, {"measured": measured.astype(float)}), (joined, {}))]
    clean, masked, blind = (measured_error_nm(f, u, y, measured, dt) for f in fits)
    assert masked <= 1.5 * clean + 5.0 and blind > 2.0 * masked + 50.0, (clean, masked, blind)
    assert block_all(np.array([1, 1, 1, 0, 1, 1, 1], bool), 3).tolist() == [True, False, True]
    assert block_all(np.array([1, 0], bool), 2).tolist() == [True, False]


def test_auto_scores_and_fits_only_what_was_measured():
    """``auto``: every candidate fitted and scored without the holds; the selected model
    predicts the measured samples as a fit of the true record does."""
    t, u, y, joined, measured = held_record()
    cands = ["pi+creep", "preisach+creep"]
    clean = afmctl.identify("auto", t_s=t, u_V=u, y_nm=y, candidates=cands, with_dynamics=False)
    masked = afmctl.identify("auto", t_s=t, u_V=u, y_nm=joined, measured=measured.astype(float), candidates=cands,
                             with_dynamics=False)
    assert masked.model.structure == clean.model.structure
    e_clean, e_masked = (measured_error_nm(f, u, y, measured) for f in (clean, masked))
    assert e_masked <= 1.5 * e_clean + 5.0, (e_masked, e_clean)
    rows = {r["structure"]: r for r in masked.table}
    ref = {r["structure"]: r for r in clean.table}
    for s in cands:          # the held-out errors are the true record's, not the 2 µm of the holds
        assert rows[s]["heldout_max_nm"] <= 1.5 * ref[s]["heldout_max_nm"] + 5.0, (s, rows[s], ref[s])


def test_a_joined_calibration_recording_carries_the_column_and_identify_reads_it(tmp_path):
    """``join`` writes ``measured`` 0 on the holds it inserts; ``afmctl identify`` on that
    CSV leaves them out as the arrays do."""
    t, u, y, _, _ = held_record()
    cut = 9000
    pieces = [PieceRecord(0, u[:cut], y[:cut], None, 0.0), PieceRecord(cut, u[cut:], y[cut:], None, cut * DT + 2.0)]
    rec = join(pieces, DT)
    cols = rec.columns()
    assert list(cols) == ["t", "u", "y", "measured"]
    assert np.flatnonzero(cols["measured"] == 0).tolist() == list(range(cut, cut + 2000))
    csv = tmp_path / "rec.csv"
    write_csv(csv, cols)
    from_file = afmctl.identify("pi", csv, n_operators=12)
    from_arrays = afmctl.identify("pi", t_s=cols["t"], u_V=cols["u"], y_nm=cols["y"], measured=cols["measured"],
                                  n_operators=12)
    assert from_file.model.weights == from_arrays.model.weights
    assert np.count_nonzero(np.isfinite(from_file.y_fit_nm)) == cols["t"].size
    assert all(p.v_V is None for p in pieces)
    no_holds = join(pieces, DT, with_holds=False).columns()
    assert "measured" not in no_holds


@pytest.mark.parametrize("cell, why", [("0.5", "row 3 holds 0.5"), ("2", "row 3 holds 2")])
def test_a_bad_measured_column_is_one_line_naming_file_and_column(tmp_path, cell, why):
    t, u, y, _, measured = held_record()
    rows = ["t,u,y,measured"] + [f"{a!r},{b!r},{c!r},{int(m)}" for a, b, c, m in
                                  zip(t.tolist(), u.tolist(), y.tolist(), measured)]
    rows[3] = rows[3].rsplit(",", 1)[0] + "," + cell
    csv = tmp_path / "bad.csv"
    csv.write_text("\n".join(rows) + "\n")
    res = subprocess.run([sys.executable, "-m", "afmctl", "identify", "--model", "pi", "--data", str(csv),
                          "--out", str(tmp_path / "m.json")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in res.stderr
    assert str(csv) in lines[0] and "column measured" in lines[0] and why in lines[0] and "allowed 0" in lines[0]


def test_a_kind_without_a_row_mask_says_it_fits_them():
    """``bouc-wen`` cannot leave rows out: the fit says so in its notes rather than keep silent."""
    t, u, y, joined, measured = held_record()
    fit = afmctl.identify("bouc-wen", t_s=t, u_V=u, y_nm=joined, measured=measured.astype(float))
    assert any("not measured" in n and "bouc-wen" in n for n in fit.notes), fit.notes


def test_model_validate_scores_only_what_was_measured(tmp_path):
    """``afmctl model validate`` on a recording with the column: its figures are those of
    the measured rows, not the 2 µm the holds are off."""
    t, u, y, joined, measured = held_record()
    fit = afmctl.identify("preisach+creep", t_s=t, u_V=u, y_nm=y, n_operators=16)
    model = tmp_path / "m.json"
    afmctl.save_model(fit.model, model)
    masked = afmctl.validate(fit.model, t, u, joined, measured=measured.astype(float)).stats[0]
    true = afmctl.validate(fit.model, t, u, y, measured=measured.astype(float)).stats[0]
    blind = afmctl.validate(fit.model, t, u, joined).stats[0]
    assert masked.max_nm == true.max_nm < 1000.0 < blind.max_nm
    csv = tmp_path / "rec.csv"
    write_csv(csv, {"t": t, "u": u, "y": joined, "measured": measured.astype(float)})
    res = subprocess.run([sys.executable, "-m", "afmctl", "model", "validate", "--model", str(model), "--data",
                          str(csv)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert f"{masked.max_nm:.4g}" in res.stdout, res.stdout
