"""The codebook's cell formatter: numbers rounded to their column's declared precision, and nothing else lost."""

from __future__ import annotations

import math
from decimal import Decimal

from hypothesis import given
from hypothesis import strategies as st

from experiment.codebook import CODEBOOK, NUMERIC_TYPES, TYPES, format_cell, format_number


def decimals_of(cell: str) -> int:
    """Digits after the decimal point of a number cell written in fixed notation."""
    return len(cell.split(".")[1]) if "." in cell else 0


def test_every_fractional_column_declares_its_precision():
    for file, cols in CODEBOOK.items():
        for c in cols:
            assert c.type in TYPES, (file, c.name)
            if c.type == "number":
                assert c.decimals is not None and c.decimals >= 0, (file, c.name)
            elif c.type != "json":
                assert c.decimals is None, (file, c.name)


def test_float_noise_is_rounded_away():
    assert format_number(1214.6999999999534, 1) == "1214.7"
    assert format_number(0.1 + 0.2, 6) == "0.3"
    assert format_number(-4.0, 6) == "-4" and format_number(3, 1) == "3"
    assert format_number(-0.00001, 1) == "0"  # no negative zero
    assert format_number(0.00001, 6) == "0.00001"  # fixed notation, never 1e-05
    assert format_number(math.nan, 10) == format_number(None, 10) == ""
    assert format_cell("json", {"t": 1214.6999999999534, "n": [0.1 + 0.2, 2], "s": "x"}, 6) == \
        '{"n":[0.3,2],"s":"x","t":1214.7}'
    assert [format_cell("flag", v) for v in (True, False, None)] == ["1", "0", ""]
    assert [format_cell("integer", v) for v in (-2, 0, 3.0, None)] == ["-2", "0", "3", ""]


@given(st.floats(allow_nan=False, allow_infinity=False, min_value=-1e9, max_value=1e9), st.integers(0, 12))
def test_a_number_cell_is_the_value_rounded_to_its_decimals(value, decimals):
    cell = format_number(value, decimals)
    assert decimals_of(cell) <= decimals and "e" not in cell and cell != "-0"
    assert not cell.endswith(".") and (("." not in cell) or not cell.endswith("0"))
    # The cell is exactly the value rounded half-even to ``decimals`` places (as Decimal of the float sees it) ...
    exact = Decimal(value).quantize(Decimal(1).scaleb(-decimals))
    assert Decimal(cell) == exact
    # ... so reading it back is within half a unit of the last place, and formatting it again changes nothing.
    assert abs(float(cell) - value) <= 0.5 * 10.0 ** -decimals * (1 + 1e-9) + abs(value) * 2.0 ** -52
    assert format_number(float(cell), decimals) == cell


@given(st.integers(-2**63, 2**63 - 1))
def test_integers_stay_integers(value):
    for column_type in NUMERIC_TYPES - {"flag"}:
        assert format_cell(column_type, value, 10 if column_type == "number" else None) == str(value)
