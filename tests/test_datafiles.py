"""``read_csv``: the vectorised pass over a plain table and the row-by-row reader give the
same numbers; everything irregular reaches the row-by-row reader and its one-line errors."""
from __future__ import annotations

import numpy as np
import pytest

from afmctl.data.datafiles import _careful_rows, _plain_table, read_csv, write_csv
from afmctl.errors import AfmctlError


def _values() -> np.ndarray:
    rng = np.random.default_rng(7)
    v = rng.standard_normal((500, 3)) * 10.0 ** rng.integers(-12, 12, (500, 3))
    v[:5] = [[0.0, -0.0, 1e-308], [5e-324, 1.7976931348623157e308, -2.5], [1, 2, 3], [0.1, 0.2, 0.3],
             [123456789.123456789, -1e-5, 7]]
    return v


def test_the_vectorised_pass_reads_every_float_as_the_careful_reader_does(tmp_path):
    v = _values()
    body = "".join(f"{float(a)!r},{float(b)!r},{float(c)!r}\n" for a, b, c in v) + "1E5, -2.5e-3 ,+4\n"
    table = _plain_table(body, 3)
    assert table is not None
    careful = _careful_rows(tmp_path / "x.csv", "a,b,c\n" + body, ["a", "b", "c"], ["a", "b", "c"])
    np.testing.assert_array_equal(table, careful)
    np.testing.assert_array_equal(table[:-1], v)


def test_written_files_come_back_bit_for_bit_through_both_readers(tmp_path):
    v = _values()
    t = np.arange(v.shape[0]) * 1e-3
    write_csv(tmp_path / "d.csv", {"t": t, "u": v[:, 0], "y": v[:, 1], "extra": v[:, 2]})
    got = read_csv(tmp_path / "d.csv", ("t", "u", "y"))
    assert set(got) == {"t", "u", "y"}
    np.testing.assert_array_equal(got["u"], v[:, 0])
    text = (tmp_path / "d.csv").read_text()
    (tmp_path / "blank.csv").write_text(text.replace("\n", "\n\n", 3))      # blank lines: the careful reader
    np.testing.assert_array_equal(read_csv(tmp_path / "blank.csv", ("t", "u", "y"))["y"], v[:, 1])


@pytest.mark.parametrize("text", [
    "\ufefft,u\r\n0,1\r\n1,2\r\n",        # a spreadsheet's BOM and CRLF
    "t,u\n0,1\n1,2",                      # no newline after the last row
    "t,u\n 0 , 1\n1,\t2\n",               # spaces around cells
    't,u\n"0",1\n1,2\n',                  # quoted cells: the careful reader
])
def test_common_spellings_of_the_same_table(tmp_path, text):
    (tmp_path / "f.csv").write_bytes(text.encode("utf-8"))
    got = read_csv(tmp_path / "f.csv", ("t", "u"))
    np.testing.assert_array_equal(got["t"], [0.0, 1.0])
    np.testing.assert_array_equal(got["u"], [1.0, 2.0])


@pytest.mark.parametrize("body, message", [
    ("0,1\n1,abc\n", "row 3: column u: 'abc' is not a number"),
    ("0,1\n1,nan\n", "row 3: column u: 'nan' is not finite"),
    ("0,1\n1,1e400\n", "row 3: column u: '1e400' is not finite"),
    ("0,1\n1\n", "row 3: column u is missing"),
    ("0,1\n1,0x10\n", "row 3: column u: '0x10' is not a number"),
    ("0,1\n0,2\n", "column t: time must be strictly increasing; row 3"),
])
def test_bad_cells_are_named_by_row_and_column(tmp_path, body, message):
    (tmp_path / "f.csv").write_text("t,u\n" + body)
    with pytest.raises(AfmctlError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_csv(tmp_path / "f.csv", ("t", "u"))


def test_empty_file_and_missing_columns(tmp_path):
    (tmp_path / "e.csv").write_text("")
    with pytest.raises(AfmctlError, match="empty file"):
        read_csv(tmp_path / "e.csv", ("t", "u"))
    (tmp_path / "h.csv").write_text("t,v\n0,1\n")
    with pytest.raises(AfmctlError, match="missing column"):
        read_csv(tmp_path / "h.csv", ("t", "u"))
    (tmp_path / "n.csv").write_text("t,u\n")
    with pytest.raises(AfmctlError, match="0 data row"):
        read_csv(tmp_path / "n.csv", ("t", "u"), min_rows=2)
