"""Block principal pivoting (compensators/nnls_gram.py) against its reference,
``scipy.optimize.nnls`` on the Cholesky factor: the same x on random problems with many
active bounds, on a Preisach grid's normal equations, and at the edges."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.compensators import preisach_identify as pid
from afmctl.compensators.nnls_gram import nnls_gram, reference_nnls


def _problem(seed: int, n: int, rows: int, smooth: float = 0.0):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((rows, n)) + 0.5 * rng.random((rows, 1))      # correlated columns
    c = A @ np.where(rng.random(n) < 0.4, rng.random(n), 0.0) + 0.3 * rng.standard_normal(rows)
    D = np.diff(np.eye(n), axis=0)
    H = A.T @ A + smooth * D.T @ D + 1e-9 * np.eye(n)
    return H, A.T @ c


@pytest.mark.parametrize("seed, n, rows, smooth", [(0, 5, 20, 0.0), (1, 60, 200, 0.0), (2, 150, 400, 10.0),
                                                   (3, 300, 310, 1.0), (4, 40, 40, 0.0)])
def test_the_same_solution_as_lawson_hanson(seed, n, rows, smooth):
    H, b = _problem(seed, n, rows, smooth)
    x = nnls_gram(H, b)
    ref = reference_nnls(H, b)
    assert (x >= 0).all()
    assert 0 < np.count_nonzero(x) < n                        # bounds active and inactive
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-7 * np.abs(ref).max())
    obj = lambda v: 0.5 * v @ H @ v - b @ v                   # noqa: E731
    assert obj(x) <= obj(ref) + 1e-9 * abs(obj(ref))
    y = H @ x - b                                             # KKT: y ≥ 0, y = 0 where x > 0
    assert y.min() >= -1e-8 * np.abs(b).max() and np.abs(y[x > 0]).max() <= 1e-8 * np.abs(b).max()


def test_edges_all_zero_all_positive_and_shape():
    H = np.diag([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(nnls_gram(H, -np.ones(3)), 0.0)
    np.testing.assert_allclose(nnls_gram(H, np.array([1.0, 4.0, 9.0])), [1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="H must be"):
        nnls_gram(np.eye(2), np.ones(3))


def test_falls_back_to_the_reference_when_the_pivoting_does_not_settle():
    H, b = _problem(5, 80, 200)
    np.testing.assert_allclose(nnls_gram(H, b, max_iter=0), reference_nnls(H, b), atol=1e-12)


def test_a_preisach_fit_gives_the_reference_masses(monkeypatch):
    """The 32-level regularised Preisach normal equations from a nested-triangle record."""
    from afmctl.sim_backend.scanner import Scanner, default_scanner_config
    legs = [(0, 150), (150, 20), (20, 120), (120, 50), (50, 150), (150, 0)]
    u = np.concatenate([np.linspace(a, b, 600) for a, b in legs])
    y = Scanner(default_scanner_config()).run(np.column_stack([u, 0 * u, 0 * u]), 1e-3)[:, 0]
    from afmctl.compensators.preisach import PreisachModel
    seen = {}

    def spy(H, b):
        seen["H"], seen["b"] = H.copy(), b.copy()
        return nnls_gram(H, b)
    monkeypatch.setattr(pid, "nnls_gram", spy)
    PreisachModel.identify(np.arange(u.size) * 1e-3, u, y, n_operators=32, method="nnls")
    H, b = seen["H"], seen["b"]
    x, ref = nnls_gram(H, b), reference_nnls(H, b)
    assert H.shape == (528, 528) and 0 < np.count_nonzero(x) < 528
    np.testing.assert_allclose(x, ref, rtol=0, atol=1e-6 * np.abs(ref).max())


def test_an_ill_conditioned_real_fit_goes_to_lawson_hanson_within_a_bounded_number_of_solves(monkeypatch):
    """The 64-level preisach+creep fit on the first half of the real pea record (condition
    number ~1e12): the block exchanges stop gaining and the backup rule would fix one
    variable per full solve (some 700 solves; with the old budget of 5n exchanges the fit ran
    for 14 minutes). Pivoting gives up within its budget and Lawson–Hanson solves it: x
    meets the KKT conditions."""
    from pathlib import Path

    from afmctl.api.identify import fit, prepare
    from afmctl.compensators import nnls_gram as ng
    from afmctl.data.datafiles import read_csv
    d = read_csv(Path(__file__).parent / "data" / "smarthysteresis-pea" / "ident.csv", ("t", "u", "y"))
    n = d["t"].size // 2
    seen = []

    def spy(H, b):
        x = nnls_gram(H, b)
        seen.append((H.copy(), b.copy(), x))
        return x
    monkeypatch.setattr(pid, "nnls_gram", spy)
    c, where = prepare("preisach+creep", t_s=d["t"][:n], u_V=d["u"][:n], y_nm=d["y"][:n])
    fit("preisach+creep", c, where)
    H, b, x = max(seen, key=lambda s: s[1].size)             # the 64-level round (2089 variables)
    assert b.size == 2089
    got, solves = ng._block_pivoting(H, b, 10_000)
    assert got is None and solves <= ng._MAX_SOLVES            # gave up early, not after ~700 solves
    g = H @ x - b                                              # KKT: x ≥ 0, g ≥ 0, x·g = 0
    scale = np.abs(b).max()
    assert np.all(x >= 0) and np.all(g >= -1e-6 * scale) and np.all(np.abs(g[x > 0]) <= 1e-6 * scale)
